"""The RL speed benchmark's command line: methods it cannot measure are refused by name."""

import json

import pytest

from benchmarks import rl_speed


def test_ild_is_refused_with_a_pointer_to_the_imitation_benchmark(capsys):
    with pytest.raises(SystemExit) as exc:
        rl_speed.main(["--tasks", "fold_cloth1", "--methods", "apg,ild"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--methods ild" in err and "benchmarks.il_speed" in err


def _record(task, method, code, arm, update_s, temp):
    return {"task": task, "method": method, "steps_per_update": 12, "update_s": update_s,
            "xla_temp_mb": temp, "config": {"num_envs": 4}, "code": code,
            "commit": "c0ffee0" if code == "before" else "beef001", "arm": arm,
            "load1_at_arm_start": 0.5, "device": "cpu:0"}


def test_before_after_table_averages_each_code_s_arms_and_divides(tmp_path):
    """Per (task, method): each code's mean over its arms, the range, before ÷ after and
    the scratch memory; a pair measured on one side only has no row."""
    recs = [_record("fold_cloth1", "apg", "before", 1, 0.6, 32.5),
            _record("fold_cloth1", "apg", "after", 2, 0.45, 11.2),
            _record("fold_cloth1", "apg", "after", 3, 0.47, 11.2),
            _record("fold_cloth1", "apg", "before", 4, 0.64, 32.5),
            _record("fold_tshirt", "apg", "before", 1, 2.0, 40.0),
            # another benchmark's record in the same file (before_after runs several)
            {"task": "fold_cloth1", "resolution": "default", "step_list_s": 0.5,
             "code": "after", "arm": 2, "commit": "beef001", "load1_at_arm_start": 0.5}]
    path = tmp_path / "2026-12-05-before-after.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))
    table = rl_speed.render_before_after(path)
    rows = [line for line in table.splitlines() if line.startswith("| fold")]
    assert rows == ["| fold_cloth1 | apg (4 envs × 3 steps) | 0.620 (0.600–0.640) | "
                    "0.460 (0.450–0.470) | 1.35 | 32.5 → 11.2 |"]
    assert "before (c0ffee0, load 0.5), after (beef001, load 0.5)" in table
    assert "(2026-12-05)" in table
