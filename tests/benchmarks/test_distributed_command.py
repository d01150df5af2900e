"""The multi-host job's command line (``python -m benchmarks.distributed``) refuses bad input
in one ``error:`` line with exit status 2, before it joins any job; the two-process run
itself is tested in ``tests/multidevice/test_distributed.py``."""

import pytest

from benchmarks import distributed


@pytest.mark.parametrize("argv, message", [
    (["--num-processes", "2"], "--num-processes / --process-id need --coordinator"),
    (["--coordinator", "nohost"], "coordinator must be HOST:PORT"),
    (["--set", "substeps"], "--set takes KEY=VALUE"),
    (["--set", "scene.nope=3"], "unknown ClothScene field(s) ['scene.nope']"),
    (["--set", "substeps=1.5"], "substeps"),
])
def test_distributed_command_reports_bad_input_in_one_line(argv, message, capsys):
    assert distributed.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and "\n" not in err, err
