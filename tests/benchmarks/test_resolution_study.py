"""The resolution study (``python -m benchmarks.tasks resolution``): its comparison of
trajectories at different resolutions is exact on analytic motions, its ladders are what
they claim, and a tiny study runs with the finest rung at zero error against itself."""

import dataclasses
import math

import numpy as np
import pytest

import dax_tasks
from benchmarks import resolution as res
from benchmarks import tasks as bench
from dax_physics.cloth import mesh as dmesh


def _square(n):
    v, f = dmesh.square_mesh(n, n, (0.3, 0.3), (-0.15, -0.15), 0.0)
    return np.asarray(v, np.float64), np.asarray(f)


def test_mesh_probe_follows_an_affine_motion_at_any_resolution():
    coarse, fc = _square(5)
    fine, ff = _square(9)
    points = _square(11)[0]  # material points that are vertices of neither mesh
    probe_c = res.MeshProbe.build(coarse, fc, points)
    probe_f = res.MeshProbe.build(fine, ff, points)
    a = np.array([[0.9, -0.3, 0.0], [0.2, 1.1, 0.0], [0.4, -0.5, 1.0]])
    b = np.array([0.05, -0.02, 0.03])

    def move(x):
        return x @ a.T + b

    expected = move(points)
    for probe, mesh in ((probe_c, coarse), (probe_f, fine)):
        got = probe(move(mesh))
        assert np.abs(got - expected).max() < 1e-12, np.abs(got - expected).max()
    assert res.point_error("mesh", probe_c(move(coarse)), probe_f(move(fine))) < 1e-12


def test_rigidly_shifted_cloth_has_an_error_equal_to_the_shift():
    coarse, fc = _square(5)
    fine, ff = _square(9)
    points = _square(11)[0]
    shift = np.array([0.03, -0.04, 0.0])  # 5 cm
    err = res.point_error("mesh", res.MeshProbe.build(coarse, fc, points)(coarse + shift),
                          res.MeshProbe.build(fine, ff, points)(fine))
    assert err == pytest.approx(0.05, abs=1e-12), f"expected 0.05 m, got {err}"


def test_points_outside_the_mesh_go_to_the_nearest_triangle_edge():
    v, f = _square(3)
    probe = res.MeshProbe.build(v, f, np.array([[0.2, 0.0, 0.0]]))  # 5 cm off the edge
    assert np.allclose(probe(v), [[0.15, 0.0, 0.0]], atol=1e-12)
    assert np.all(probe.w >= 0) and np.allclose(probe.w.sum(1), 1.0)


def test_centreline_probe_and_chamfer_on_known_answers():
    rng = np.random.default_rng(0)
    s = rng.uniform(0.0, 0.24, 400)
    x = np.stack([s, rng.uniform(-0.01, 0.01, 400), rng.uniform(-0.01, 0.01, 400)], 1)
    probe = res.CentrelineProbe.build(s, np.linspace(0.0, 0.24, 25))
    shift = np.array([0.0, 0.0, 0.02])
    assert res.point_error("centreline", probe(x + shift), probe(x)) == pytest.approx(0.02)
    assert res.chamfer(x, x) == 0.0
    a, b = np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 0.03, 0.04], [0.0, 0.0, 0.01]])
    # a -> nearest of b: 0.01; b -> a: mean(0.05, 0.01) = 0.03; symmetric: 0.02
    assert res.chamfer(a, b) == pytest.approx(0.02, abs=1e-15)
    with pytest.raises(ValueError, match="no particle"):
        res.CentrelineProbe.build(s, [0.5])


@pytest.mark.parametrize("name", dax_tasks.TASKS)
def test_every_ladder_has_the_default_and_a_twice_as_fine_reference(name):
    rungs = res.ladder(name)
    default = [r for r in rungs if r.is_default]
    fine = [r for r in rungs if r.is_fine]
    assert len(default) == 1 and len(fine) == 1 and rungs[-1].is_fine, [r.label for r in rungs]
    spec = dax_tasks.get_spec(name)
    d = default[0]
    if d.overrides:  # the default rung builds exactly the default spec
        assert dataclasses.replace(spec, **d.overrides) == spec
    assert fine[0].spacing <= 0.5 * d.spacing + 1e-12, (fine[0].spacing, d.spacing)
    step_time = spec.substeps * spec.scene.dt
    for r in rungs:  # every rung simulates the default's time per env step
        s = dataclasses.replace(spec, **r.overrides)
        assert math.isclose(s.substeps * s.scene.dt, step_time, rel_tol=1e-9), r.label


@pytest.mark.parametrize("name", ["fold_cloth1", "fold_tshirt"])
def test_scaled_contact_keeps_the_pressure_between_layers(name):
    """With ``scale_contact`` each rung's per-pair contact constants are the default's times
    (spacing / default spacing)^4, so k h^3 / s^4, the pressure between two layers at a
    given gap, is the same on every mesh; without it they are the default's."""
    base = dax_tasks.get_spec(name).scene
    for scaled in (False, True):
        for r in res.ladder(name, scale_contact=scaled):
            scene = r.overrides.get("scene", base)
            f = (scene.mesh_spacing / base.mesh_spacing) ** 4 if scaled else 1.0
            for key in ("self_stiffness", "self_damping", "self_friction"):
                assert math.isclose(getattr(scene, key), getattr(base, key) * f,
                                    rel_tol=1e-9), (r.label, key, scaled)
            pressure = scene.self_stiffness * scene.thickness ** 3 / scene.mesh_spacing ** 4
            want = base.self_stiffness * base.thickness ** 3 / base.mesh_spacing ** 4
            assert math.isclose(pressure, want, rel_tol=1e-9) == (scaled or r.is_default), (
                r.label, scaled)


def _tiny_rung(label, n, fine=False):
    spec = dax_tasks.get_spec("fold_cloth1")
    scene = dataclasses.replace(spec.scene, n=n, thickness=0.0, dt=1e-3, settle_substeps=20)
    return res.Rung(label, 0.3 / (n - 1), {"substeps": 60, "scene": scene}, is_fine=fine)


def test_tiny_study_runs_with_zero_error_only_at_the_reference(tmp_path):
    rungs = [_tiny_rung("5 x 5", 5), _tiny_rung("7 x 7", 7, fine=True)]
    out = res.study("fold_cloth1", rungs, seed=0, steps=2)
    coarse, fine = out["rungs"]
    assert out["steps"] == 2 and len(coarse["error"]) == 2
    for r in out["rungs"]:
        for key in ("step_cpu_s", "step_wall_s", "error_mean", "error_max", "final_r_gt"):
            assert math.isfinite(r[key]), (r["label"], key, r[key])
        assert r["finite"] and r["object_points"] == int(r["label"][0]) ** 2
        assert 0.0 <= r["layer_gap_under_1mm"] <= 1.0 and r["layer_overlaps"] >= 0
    assert fine["error_mean"] == 0.0 and fine["error_max"] == 0.0 and fine["score_diff"] == 0.0
    # both start as the same flat cloth at the same pose: no error at t = 0, some after
    assert coarse["error_t0"] < 1e-6, coarse["error_t0"]
    assert coarse["error_mean"] > 1e-4, coarse["error_mean"]
    assert coarse["error_max"] >= coarse["error_mean"]
    assert 1 in res.pareto(out["rungs"])  # the reference (error 0) is on the front
    assert out["default_on_front"] is None  # neither rung is the task's default
    # the chaos floor reruns the first rung from a start moved 10 um along x
    chaos = out["chaos_floor"]
    assert chaos["rung"] == "5 x 5" and chaos["shift_m"] == res.FLOOR_SHIFT
    assert chaos["error_t0"] == pytest.approx(res.FLOOR_SHIFT, rel=1e-2), chaos["error_t0"]
    assert all(math.isfinite(e) for e in chaos["error"])


def test_replay_mode_drives_every_rung_with_the_defaults_actions():
    """Replaying a closed-loop episode's actions on its own rung reproduces it exactly
    (same states, same scores), so a replay study's rungs differ only by resolution; the
    study replays the default rung's actions on the others."""
    coarse = dataclasses.replace(_tiny_rung("5 x 5", 5), is_default=True)
    closed = res.run_rung("fold_cloth1", coarse, seed=1, steps=2)
    again = res.run_rung("fold_cloth1", coarse, seed=1, steps=2, actions=closed["_actions"])
    assert again["r_gt"] == closed["r_gt"]
    for a, b in zip(closed["_points"], again["_points"], strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="actions to replay"):
        res.run_rung("fold_cloth1", coarse, seed=1, steps=2, actions=closed["_actions"][:1])
    out = res.study("fold_cloth1", [coarse, _tiny_rung("7 x 7", 7, fine=True)], seed=1,
                    steps=2, floor=0.0, mode="replay")
    assert out["mode"] == "replay" and out["rungs"][0]["r_gt"] == closed["r_gt"]
    assert out["rungs"][1]["error_mean"] == 0.0 and out["rungs"][0]["error_mean"] > 1e-4
    with pytest.raises(ValueError, match="study mode"):
        res.study("fold_cloth1", [coarse], mode="open")


def test_rungs_whose_layers_pass_through_each_other_are_off_the_front():
    """A faster, nearer rung whose layers pass through each other does not push the
    default off the front; without the layer record it would."""
    def rec(label, t, e, through=None, default=False):
        r = {"label": label, "step_cpu_s": t, "error_mean": e, "error_max": e,
             "score_diff": 0.0, "is_default": default}
        if through is not None:
            r["layer_gap_under_1mm"] = through
        return r
    recs = [rec("coarse", 0.02, 0.024, 0.48), rec("default", 0.05, 0.031, 0.0, True),
            rec("fine", 1.2, 0.0, 0.0)]
    assert not res.valid(recs[0]) and res.valid(recs[1])
    assert res.pareto(recs) == [1, 2]
    out = res.verdict(recs)
    assert out["default_on_front"] and out["invalid"] == ["coarse"]
    recs[0].pop("layer_gap_under_1mm")  # MPM rungs have no layer record: all valid
    assert res.pareto(recs) == [0, 2] and not res.verdict(recs)["default_on_front"]


def test_bench_resolution_subcommand_refuses_an_unknown_task(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        bench.main(["resolution", "--task", "fold_origami", "--out", str(tmp_path)])
    assert exc.value.code == 2
    assert "valid names" in capsys.readouterr().err
