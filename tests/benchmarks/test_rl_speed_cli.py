"""The RL speed benchmark's command line: methods it cannot measure are refused by name."""

import pytest

from benchmarks import rl_speed


def test_ild_is_refused_with_a_pointer_to_the_imitation_benchmark(capsys):
    with pytest.raises(SystemExit) as exc:
        rl_speed.main(["--tasks", "fold_cloth1", "--methods", "apg,ild"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--methods ild" in err and "benchmarks.il_speed" in err
