"""The per-op profiler's command line refuses workloads it cannot profile, by name."""

import pytest

from benchmarks import profile_fusions


@pytest.mark.parametrize("argv, message", [
    (["--workload", "nonsense"], "unknown workload 'nonsense'"),
    (["--workload", "train:apg"], "train:METHOD:TASK"),
    (["--workload", "train:apg:fold_cloth1", "--mode", "grad"], "--mode fwd"),
])
def test_bad_workloads_are_refused_by_name(argv, message, capsys):
    with pytest.raises(SystemExit):
        profile_fusions.main(argv)
    assert message in capsys.readouterr().err


def test_train_workload_takes_a_reinforcement_learner_only():
    with pytest.raises(ValueError, match="ppo, apg, shac.*'transporter'"):
        profile_fusions.train_workload("train:transporter:fold_cloth1")
