"""The charts (issue 37): each method keeps one colour on every chart, and a learning curve
with no finished training episode, or with a single point, draws without NumPy's warnings
("Mean of empty slice", "Degrees of freedom <= 0")."""

import math
import warnings

import numpy as np

from dax_algos import registry
from dax_algos.bench import learning, report
from dax_algos.bench.rows import make_row


def test_every_registered_method_has_a_colour_of_its_own():
    names = registry.names()
    colours = [report.colour(m) for m in names]
    assert len(set(colours)) == len(names), dict(zip(names, colours, strict=True))
    assert all(report.colour(m) == report.COLOURS[m] for m in names)


def test_a_method_outside_the_palette_gets_the_same_colour_every_time():
    assert report.colour("my_planner") == report.colour("my_planner")
    assert report.colour("my_planner") not in report.COLOURS.values()


def _curve(method, seed, scores):
    return [dict(task="fold_cloth1", method=method, seed=seed, budget="quick", update=u,
                 env_steps=float(8 * (u + 1)), wall_s=float(u + 1), score=s)
            for u, s in enumerate(scores)]


def test_learning_curves_with_empty_or_single_points_draw_without_warnings(tmp_path):
    rows = (_curve("ppo", 0, [math.nan, 0.4, math.nan])  # one finished update
            + _curve("ppo", 1, [math.nan, math.nan, 0.5])  # seeds not overlapping
            + _curve("apg", 0, [math.nan, math.nan])  # nothing finished
            + _curve("shac", 0, [0.3, 0.35]) + _curve("shac", 1, [0.2]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bands = learning.curve_bands(rows, "env_steps")
        (path,) = learning.charts(rows, tmp_path,
                                  references={"fold_cloth1": {"random": 0.4, "expert": 0.99}})
    assert "apg" not in bands and path.is_file() and path.stat().st_size > 0
    grid, mean, se, n = bands["ppo"]
    assert n == 2 and np.isfinite(mean).any()


def test_score_charts_of_one_seed_draw_without_warnings(tmp_path):
    rows = [make_row("fold_cloth1", m, 0, "quick", status="ok", score=0.4, wall_s=1.0,
                     compile_s=1.0, env_steps=3, backprop_steps=0)
            for m in ("random", "cem_mpc")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        (path,) = report.charts(rows, tmp_path)
    assert path.is_file()
