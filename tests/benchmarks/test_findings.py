"""The findings and untrained-policy tables (``benchmarks/findings.py``) on a grid written
for the test: each comparison's verdict follows its 2-SE rule, a finding with a failing
comparison lists it with its numbers, and a learner is above / within / below its
untrained policy by the paired difference over seeds."""

import pytest

from benchmarks import findings
from dax_algos.bench.rows import append_row, make_row


def _grid(tmp_path, scores):
    """A results.csv of ``{(task, method): [score or (score, untrained), ...]}`` (one row
    per seed)."""
    path = tmp_path / "results.csv"
    for (task, method), values in scores.items():
        for seed, v in enumerate(values):
            score, untrained = v if isinstance(v, tuple) else (v, "")
            append_row(path, make_row(task, method, seed, "full", status="ok", score=score,
                                      untrained_score=untrained))
    return tmp_path


def test_findings_follow_the_two_standard_error_rule(tmp_path):
    grid = _grid(tmp_path, {
        # F2 on whip_rope: APG 0.6 > SHAC 0.45 > PPO 0.3, each SE 0.006: reproduced
        ("whip_rope", "apg"): [0.59, 0.60, 0.61], ("whip_rope", "shac"): [0.44, 0.45, 0.46],
        ("whip_rope", "ppo"): [0.29, 0.30, 0.31],
        # F1 on fold_cloth1: PPO 0.40 vs APG 0.50 (SE 0.01 / sqrt(3) each): PPO >= APG fails
        ("fold_cloth1", "ppo"): [0.39, 0.40, 0.41], ("fold_cloth1", "apg"): [0.49, 0.50, 0.51],
        ("fold_cloth1", "shac"): [0.39, 0.40, 0.41],
        # F3 on push_rope: RGB 0.80 below height maps 0.85: fails where a reason is named
        ("push_rope", "transporter_rgb"): [0.79, 0.80, 0.81],
        ("push_rope", "transporter"): [0.84, 0.85, 0.86],
    })
    out = {f["finding"].name: f for f in findings.findings(
        findings._grid_rows(grid, include_stale=True)[0])}
    assert out["F2"]["verdict"] == "reproduced" and out["F2"]["measured"] == ["whip_rope"]
    assert out["F1"]["verdict"] == "not reproduced"
    ((task, claim, (holds, diff, se)),) = out["F1"]["failed"]
    assert (task, claim, holds) == ("fold_cloth1", ("ppo", ">=", "apg"), False)
    assert diff == pytest.approx(-0.10) and se == pytest.approx(0.01 * (2 / 3) ** 0.5)
    assert out["F3"]["verdict"] == "not reproduced" and out["F4"]["verdict"] == "not measured"
    table = findings.render_findings(grid, include_stale=True)
    assert "fold_cloth1: ppo >= apg: -0.100 ± 0.008" in table, table
    # each failing task's measured reason, or that none was measured, in the last column
    f1, f2, f3 = (next(line for line in table.splitlines() if line.startswith(f"| {n} "))
                  for n in ("F1", "F2", "F3"))
    assert f1.endswith("| fold_cloth1: no measured reason |"), f1
    assert f2.endswith("| — |"), f2
    assert f3.endswith(f"| push_rope: {findings.FINDINGS[2].reason('push_rope')} |"), f3
    assert "transporter_picks" in f3 and "no measured reason" not in f3


def test_a_tie_within_two_standard_errors_is_at_or_above_not_above(tmp_path):
    stats = {("t", "a"): (0.50, 0.02, 5), ("t", "b"): (0.52, 0.02, 5)}
    assert findings.check_claim(stats, "t", "a", ">=", "b")[0]
    assert not findings.check_claim(stats, "t", "a", ">", "b")[0]
    assert findings.check_claim(stats, "t", "a", ">", "c") is None


def test_learners_against_their_untrained_policy_are_paired_by_seed(tmp_path):
    grid = _grid(tmp_path, {
        ("fold_cloth1", "apg"): [(0.45, 0.35), (0.52, 0.41), (0.40, 0.31)],  # +0.10 steady
        ("fold_cloth1", "ppo"): [(0.30, 0.40), (0.31, 0.40), (0.29, 0.40)],  # -0.10: below
        ("fold_cloth1", "shac"): [(0.50, 0.40), (0.30, 0.40), (0.40, 0.40)],  # 0 ± 0.058
        ("fold_cloth1", "random"): [0.4, 0.4],  # a planner: no untrained score
    })
    out = {f["method"]: f for f in findings.versus_untrained(
        findings._grid_rows(grid, include_stale=True)[0])}
    assert set(out) == {"apg", "ppo", "shac"}
    assert out["apg"]["verdict"] == "above"
    assert out["apg"]["difference"][0] == pytest.approx(0.10)
    assert out["ppo"]["verdict"] == "below" and out["shac"]["verdict"] == "within"
    table = findings.render_untrained(grid, include_stale=True)
    assert "1 above, 1 within, 1 below" in table, table


def test_cells_extended_beyond_the_common_seeds_are_split_into_common_and_added(tmp_path):
    grid = _grid(tmp_path, {
        # seeds 0-1 within (+0.06, -0.04), seeds 2-3 above (+0.10 twice), all four +0.055
        ("fold_cloth1", "apg"): [(0.46, 0.40), (0.36, 0.40), (0.50, 0.40), (0.50, 0.40)],
        ("fold_cloth1", "ppo"): [(0.45, 0.40), (0.46, 0.40)],
        ("fold_cloth3", "ppo"): [(0.45, 0.40), (0.46, 0.40)],
        ("fold_cloth1", "random"): [0.4, 0.4, 0.4, 0.4],  # no untrained score: not a cell
    })
    rows = findings._grid_rows(grid, include_stale=True)[0]
    (f,) = findings.added_seeds(rows)
    assert (f["task"], f["method"]) == ("fold_cloth1", "apg")
    assert f["common_seeds"] == [0, 1] and f["added_seeds"] == [2, 3]
    assert f["common"]["difference"] == pytest.approx((0.01, 0.05))
    assert f["added"]["difference"][0] == pytest.approx(0.10)
    assert f["added"]["verdict"] == "above" and f["common"]["verdict"] == "within"
    assert f["all"]["difference"][0] == pytest.approx(0.055) and f["all"]["n"] == 4
    table = findings.render_added_seeds(grid, include_stale=True)
    assert "| apg | fold_cloth1 | +0.010 ± 0.050 | within | 2-3 | +0.100 ± 0.000 |" in table, table
    assert "beyond 0-1" in table
    (tmp_path / "same").mkdir()
    same = _grid(tmp_path / "same", {("fold_cloth1", "ppo"): [(0.45, 0.40), (0.46, 0.40)]})
    with pytest.raises(ValueError, match="no learner cell holds more seeds"):
        findings.render_added_seeds(same, include_stale=True)


def test_a_path_without_results_is_refused_naming_it(tmp_path):
    with pytest.raises(ValueError, match="no results.csv"):
        findings.render_findings(tmp_path / "nothing")


def test_stale_rows_are_counted_by_why_when_included_and_left_out_otherwise():
    reasons = ["the dax-tasks or dax-physics code changed (fingerprint a, today b)",
               "the method's config changed (config c, today d)",
               "the dax-tasks or dax-physics code changed (fingerprint a, today b); the "
               "method's config changed (config c, today d)"]
    assert findings.stale_note([], 5, True) == ""
    assert findings.stale_note(reasons, 5, False) == ", 3 stale rows left out"
    note = findings.stale_note(reasons, 5, True)
    assert "**3 of 5 rows are stale** and included" in note
    assert "the dax-tasks or dax-physics code changed: 2" in note
    assert "the method's config changed: 2" in note  # the third row counts under both


def test_whip_rope_is_compared_at_equal_training_time(tmp_path):
    """APG above PPO on Whip-Rope counts as an equal-time result only when APG trained no
    longer than PPO (the learning curves' training wall time)."""
    from dax_algos.bench import learning

    grid = _grid(tmp_path, {("whip_rope", "apg"): [0.59, 0.60, 0.61],
                            ("whip_rope", "ppo"): [0.29, 0.30, 0.31]})

    def curves(apg_s, ppo_s):
        path = learning.learning_path(grid, "whip_rope")
        path.unlink(missing_ok=True)
        for method, secs in (("apg", apg_s), ("ppo", ppo_s)):
            for seed in range(3):
                learning.append_curve(path, [dict(
                    task="whip_rope", method=method, seed=seed, budget="full", update=u,
                    env_steps=10.0 * (u + 1), wall_s=secs * (u + 1) / 2, score=0.5)
                    for u in range(2)])
        rows = findings._grid_rows(grid, include_stale=True)[0]
        return findings.equal_time_text(grid, rows)

    assert "apg +0.300 ± 0.008 against ppo, training 100 s against 120 s per seed: above " \
           "at equal time" in curves(100.0, 120.0)
    assert "trained 2.0x as long: not yet an equal-time comparison" in curves(240.0, 120.0)
