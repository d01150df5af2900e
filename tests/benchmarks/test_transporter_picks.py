"""``benchmarks/transporter_picks.py``'s table: medians over every start and seed, the first
step apart from the later ones, r_gt per seed then over seeds."""

import json

import pytest

from benchmarks import transporter_picks


def _rec(method, seed, pick, place, r_gt):
    return {"task": "push_rope", "method": method, "seed": seed, "n_starts": len(pick),
            "pick_err_cm": pick, "place_err_cm": place, "r_gt": r_gt,
            "expert_r_gt_first": [0.7] * len(pick)}


def test_the_table_splits_the_first_step_from_the_later_ones(tmp_path):
    # two starts x three steps per seed; the first step's picks 1 and 3 cm, later 0.5-5 cm
    recs = [_rec("transporter", 0, [[1.0, 0.5, 5.0], [3.0, 0.5, 5.0]],
                 [[2.0, 2.0, 2.0], [2.0, 4.0, 4.0]], [[0.6, 0.7, 0.8], [0.6, 0.7, 0.9]]),
            _rec("transporter", 1, [[1.0, 0.5, 0.5], [3.0, 5.0, 5.0]],
                 [[2.0, 2.0, 2.0], [2.0, 4.0, 4.0]], [[0.7, 0.7, 0.6], [0.7, 0.7, 0.7]])]
    path = tmp_path / "picks.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))
    table = transporter_picks.render_table(path)
    (row,) = [line for line in table.splitlines() if line.startswith("| push_rope")]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:3] == ["push_rope", "transporter", "2"]
    assert cells[3] == "2.0 / 2.8"      # medians of [1, 3, 1, 3] and of the 8 later picks
    assert cells[4] == "50% / 50%"      # picks within 2 cm
    assert cells[5] == "2.0 / 3.0"
    # per step: the medians of [1, 3, 1, 3], [.5, .5, .5, 5] and [5, 5, .5, 5]; r_gt each
    # seed's mean, then their mean
    assert cells[6] == "2.0 / 0.5 / 5.0"
    assert cells[7] == "0.650 / 0.700 / 0.750"
    first, score = cells[8], cells[9]
    assert first.startswith("0.650 ± 0.050") and first.endswith("(0.700)")
    assert score == "0.750 ± 0.100"     # seeds' final means 0.85 and 0.65
    assert transporter_picks._mean_se([0.85, 0.65]) == pytest.approx((0.75, 0.1))


def test_saved_policies_are_found_by_task_method_and_seed(tmp_path):
    from benchmarks.eval_trained import saved_policies

    for rel in ("push_rope/transporter/seed1.msgpack", "push_rope/transporter/seed10.msgpack",
                "push_rope/ppo/seed0.msgpack", "fold_cloth1/transporter/seed0.msgpack",
                "push_rope/transporter/seed1.msgpack.json"):
        (tmp_path / "policies" / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / "policies" / rel).write_text("")
    found = [(t, m, s) for _, t, m, s in saved_policies(tmp_path, {"push_rope"},
                                                        {"transporter"})]
    assert found == [("push_rope", "transporter", 1), ("push_rope", "transporter", 10)]
    assert len(list(saved_policies(tmp_path))) == 4
