"""The self-collision benchmark's targets and table, from hand-made records (no timing)."""

import json

from benchmarks import cloth_self_collision as sc


def _record(task, resolution, batch, off, lst):
    return dict(task=task, resolution=resolution, batch=batch, step_off_s=off,
                step_list_s=lst, ratio_list=round(lst / off, 2), ratio_all=None,
                info={"list": {"n_vertices": 121, "substeps": 700, "pairs": 139,
                               "builds": 85, "overflow": 0}},
                reps=3, load_1min_before=1.0, load_1min_after=1.2)


def test_targets_at_batch_one_carry_the_issue_names_and_limits():
    recs = [_record("fold_cloth1", "default", 1, 0.004, 0.005),
            _record("fold_cloth1", "reference", 1, 0.030, 0.090)]
    t = sc.targets(recs)
    assert t["fold_cloth1: self-collision / off"] == dict(value=1.25, limit=1.5, met=True)
    assert t["fold_cloth1@reference: self-collision / off"]["met"] is False  # 3.0 > 2
    assert t["fold_cloth1@reference off [s] (DaXBench / 1.5)"]["met"] is True


def test_targets_at_another_batch_name_it_and_the_table_says_it(tmp_path):
    recs = [_record("unfold_cloth3", "default", 16, 0.020, 0.034)]
    grad = [{**recs[0], "grad": True}]
    assert list(sc.targets(grad)) == [
        "unfold_cloth3: self-collision / off (batch 16, with the action gradient)"]
    t = sc.targets(recs)
    assert list(t) == ["unfold_cloth3: self-collision / off (batch 16)"]
    assert t["unfold_cloth3: self-collision / off (batch 16)"]["met"] is False  # 1.7 > 1.5
    path = tmp_path / "r.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in [*recs, {"targets": t}]) + "\n")
    table = sc.render_table(path)
    assert "batch 16, the expert's first action" in table
    assert "| unfold_cloth3: self-collision / off (batch 16) | 1.7 | 1.5 | no |" in table


def test_before_after_table_averages_each_codes_arms(tmp_path):
    """``render_before_after``: per case the mean over each code's arms (ABBA), the ratios
    to off and the factor before ÷ after; summary lines and one-code cases are left out."""
    arms = [("before", 0, 0.20, 0.60), ("after", 1, 0.20, 0.40), ("after", 2, 0.22, 0.44),
            ("before", 3, 0.22, 0.64)]
    lines = []
    for code, arm, off, lst in arms:
        tag = dict(code=code, arm=arm, commit=code[:3], load1_at_arm_start=1.0)
        lines.append({**_record("fold_cloth1", "default", 64, off, lst), **tag})
        lines.append({"targets": {}, **tag})
    lines.append({**_record("unfold_cloth3", "default", 64, 0.2, 0.5), "code": "after",
                  "arm": 1, "commit": "aft", "load1_at_arm_start": 1.0})
    lines.append({"task": "fold_cloth1", "method": "ppo", "update_s": 1.0, "code": "after",
                  "arm": 1, "commit": "aft", "load1_at_arm_start": 1.0})  # rl_speed's
    path = tmp_path / "2026-12-06-x.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in lines) + "\n")
    table = sc.render_before_after(path)
    assert "| fold_cloth1 | 64, step | 0.21 / 0.21 | 0.62 / 0.42 | 2.95 → 2.00 | 1.48 |" in table
    assert "unfold_cloth3" not in table
    assert "before (bef, load 1.0), after (aft, load 1.0), after" in table
