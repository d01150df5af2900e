"""Learning-curve files: round trip, interrupted writes, duplicates after a resume, the
results.csv filter, bands, charts."""

import math

import numpy as np
import pytest

from dax_algos.bench import learning


def _curve(method, seed, n=4, offset=0.0, budget="quick"):
    return [dict(task="t", method=method, seed=seed, budget=budget, update=u,
                 env_steps=(u + 1) * 10, wall_s=(u + 1) * 0.5,
                 score=math.nan if u == 0 else u / 10 + offset) for u in range(n)]


def test_round_trip_and_nan(tmp_path):
    path = learning.learning_path(tmp_path, "t")
    learning.append_curve(path, _curve("ppo", 0))
    learning.append_curve(path, _curve("apg", 1))
    rows = learning.read_curves(path)
    assert len(rows) == 8 and path.read_text().splitlines()[0] == ",".join(learning.COLUMNS)
    first = rows[0]
    assert first["seed"] == 0 and first["update"] == 0 and math.isnan(first["score"])
    assert rows[5]["env_steps"] == 20 and rows[5]["score"] == pytest.approx(0.1)


def test_interrupted_write_duplicates_and_keep(tmp_path):
    path = learning.learning_path(tmp_path, "t")
    learning.append_curve(path, _curve("ppo", 0))
    with open(path, "a") as f:
        f.write("t,ppo,1,quick,0,1")  # killed mid-write
    learning.append_curve(path, _curve("ppo", 0, offset=1.0))  # the run re-done
    rows = learning.read_curves(path)
    assert path.read_text().endswith("\n")
    assert len(rows) == 4 and rows[-1]["score"] == pytest.approx(1.3)  # the last copy wins
    learning.append_curve(path, _curve("ppo", 2))
    kept = learning.read_curves(path, keep={("t", "ppo", 2, "quick")})
    assert {r["seed"] for r in kept} == {2}


def test_a_rerun_with_fewer_updates_replaces_the_whole_curve(tmp_path):
    path = learning.learning_path(tmp_path, "t")
    learning.append_curve(path, _curve("ppo", 0, n=6))
    learning.append_curve(path, _curve("apg", 0, n=6))
    learning.append_curve(path, _curve("ppo", 0, n=3, offset=1.0))  # re-run, other budget
    ppo = [r for r in learning.read_curves(path) if r["method"] == "ppo"]
    assert [r["update"] for r in ppo] == [0, 1, 2]  # none of the first run's updates 3-5
    assert ppo[-1]["score"] == pytest.approx(1.2)
    assert len([r for r in learning.read_curves(path) if r["method"] == "apg"]) == 6


def test_wrong_header_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "learning_t.csv"
    path.write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match="learning_t.csv has columns"):
        learning.read_curves(path)


def test_bands_mean_and_standard_error():
    rows = []
    for seed, off in ((0, 0.0), (1, 2.0)):
        rows += [dict(method="m", seed=seed, update=u, env_steps=float(u), wall_s=float(u),
                      score=u + off) for u in range(5)]
    grid, mean, se, n = learning.curve_bands(rows, "env_steps", points=5)["m"]
    np.testing.assert_allclose(grid, np.arange(5.0))
    np.testing.assert_allclose(mean, grid + 1.0)
    np.testing.assert_allclose(se, 1.0)
    assert n == 2
    # seeds covering different ranges: the common range is used
    rows = [dict(method="m", seed=0, update=u, env_steps=float(u), wall_s=0.0, score=1.0)
            for u in range(5)]
    rows += [dict(method="m", seed=1, update=u, env_steps=float(u + 2), wall_s=0.0,
                  score=3.0) for u in range(5)]
    grid, mean, _, _ = learning.curve_bands(rows, "env_steps", points=3)["m"]
    np.testing.assert_allclose(grid, [2.0, 3.0, 4.0])
    np.testing.assert_allclose(mean, 2.0)


def test_charts_are_pngs_per_task(tmp_path):
    rows = _curve("ppo", 0) + _curve("ppo", 1, offset=0.1) + _curve("apg", 0)
    written = learning.charts(rows, tmp_path, method_order=("apg", "ppo"))
    assert written == [tmp_path / "learning_t.png"]
    data = written[0].read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000
    assert learning.charts([], tmp_path) == []
