"""The cheap checks of the validation suite (``python -m dax_physics.validate``) as tests, on
the coarsest grids of their sweeps and few steps: each asserts the known answer within the
error that resolution allows (measured values in the comments), and the report writer's
exit status. The full sweeps, their convergence orders and charts are ``nox -s
validate``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dax_physics import validate
from dax_physics.validate import __main__ as cli
from dax_physics.validate import cloth, fluid, gradients, solid


def test_collapsing_column_matches_martin_and_moyce_and_rests_on_the_floor():
    """8 cells across: residual height 3.5 % from the lab data (14.6 % before the walls
    were moved to their surface and the fluid's tension removed); the surge front leads the
    lab's by about 9 %; no particle below the floor wall's surface (they reached 0.94
    cells below it before)."""
    r = fluid.dam_break(8)
    height = float(np.mean(np.abs(r["height_error"])))
    front = float(np.mean(r["front_error"]))
    assert height < 0.05, f"residual height error {height:.2%} against Martin & Moyce"
    assert 0.0 < front < 0.15, f"surge front error {front:+.2%} (expected about +9 %)"
    assert r["lowest_particle_cells"] > -0.1, (
        f"water sank {-r['lowest_particle_cells']:.2f} cells into the floor wall")


def test_hydrostatic_pressure_profile():
    r = fluid.hydrostatic(4)  # measured 2.4 % (8 cells: 0.8 %)
    assert r["rms"] < 0.04, f"RMS pressure error {r['rms']:.2%} of rho g h"


def test_sound_speed_pins_the_bulk_modulus():
    """c = J0 sqrt(K / rho) within the O(dx) end effect (8 cells: -5.4 %). A pressure that
    misread K (e.g. by the factor J of the old energy, or 2K) would be off by > 10 %."""
    r = fluid.sound_speed(8)
    assert r["c"] == pytest.approx(r["c_exact"], rel=0.07), (r["c"], r["c_exact"])
    assert r["c"] < r["c_exact"], "the closed ends should lengthen the column, not shorten it"


def test_elastic_cantilever_under_its_weight_does_not_creep():
    """2 cells thick, 4 periods: the per-period mean tip deflection stays within 0.3 % of
    the first (-0.03 % measured; +1.8 % with F stored directly in float32) and within 5 %
    of beam theory (+2.8 %)."""
    r = solid.cantilever(2, periods=4)
    m = np.asarray(r["means"])
    assert len(m) >= 3, f"only {len(m)} periods measured"
    drift = m / m[0] - 1.0
    assert np.abs(drift).max() < 0.003, f"mean deflection drifted: {drift}"
    assert m[0] == pytest.approx(r["reference"], rel=0.05), (m[0], r["reference"])


def test_lateral_contraction_is_poissons_ratio():
    r = solid.compression(4, solid.POISSON_SOLID, 0.01, unload=False, stress=False)
    hold = r["phases"][1][len(r["phases"][1]) // 4:]
    nu = -hold[:, 2].mean() / hold[:, 1].mean()
    assert nu == pytest.approx(solid.POISSON_SOLID.poisson_ratio, rel=0.03), nu


def test_plastic_cube_yields_at_the_yield_stress_and_keeps_its_set():
    mat = solid.DOUGH
    eps_y = mat.yield_stress / mat.youngs_modulus
    r = solid.compression(4, mat, 5 * eps_y, unload=True, speed_fraction=0.003)
    load, _, _, rest = r["phases"]
    plateau = -load[load[:, 1] < -2 * eps_y, 3].mean()
    eps_set = rest[len(rest) // 2:, 1].mean()
    expected_set = load[-1, 1] + eps_y
    assert plateau == pytest.approx(mat.yield_stress, rel=0.05), plateau
    assert eps_set == pytest.approx(expected_set, rel=0.10), (eps_set, expected_set)
    assert abs(rest[len(rest) // 2:, 3].mean()) < 0.05 * mat.yield_stress, "residual stress"


def test_rope_swings_as_a_compound_pendulum():
    r = solid.rope_pendulum(8)  # +2.3 % at 8 cells, +0.65 % at 16
    assert r["period"] == pytest.approx(r["period_exact"], rel=0.04)


def test_cloth_strip_hangs_as_a_catenary():
    r = cloth.catenary(9)  # +0.8 % at 9 vertices
    assert r["sag"] == pytest.approx(r["reference"], rel=0.015)
    assert r["max_strain"] < 1e-3, "the strip stretched: not a catenary"


def test_hanging_sheet_swings_in_the_hanging_chain_mode():
    r = cloth.hanging_sheet(9)  # +0.6 % at 9 vertices
    assert r["period"] == pytest.approx(r["period_exact"], rel=0.01)


def test_catenary_reference():
    # a shallow chain: sag ~ span^2 / (8 a) and length - span ~ 8 sag^2 / (3 span)
    span, sag = 1.0, 0.02
    length = span + 8 * sag ** 2 / (3 * span)
    assert cloth.catenary_sag(span, length) == pytest.approx(sag, rel=0.01)


@pytest.mark.parametrize("check", [gradients.check_gradient_mpm_fluid,
                                   gradients.check_gradient_mpm_plastic])
def test_solver_gradient_matches_float64_finite_differences(check):
    r = check("quick")
    assert r.passed, [(p.cell_size, p.error) for p in r.points]


def _result(error, tolerance=0.01, **kw):
    pts = [validate.Point(n, 1.0 / n, error * (8 / n), 0.1 * n) for n in (8, 16, 32)]
    return validate.Result(name="fake", solver="s", reference="r", quantity="q",
                           resolution_label="cells", default=16, points=pts,
                           tolerance=tolerance, expected_order=1.0, **kw)


def test_result_reports_error_order_and_pass():
    r = _result(0.03)
    assert r.error == pytest.approx(0.015)
    assert r.measured_order == pytest.approx(1.0)
    assert not r.passed and _result(0.015).passed
    assert not _result(0.001, conditions={"c": False}).passed
    assert validate.pareto_front(r.points) == r.points


def test_cli_writes_the_report_and_exits_nonzero_on_a_failure(tmp_path, monkeypatch):
    fake = {"ok": lambda level: _result(0.01), "bad": lambda level: _result(0.5)}
    for name, fn in fake.items():
        fn.__name__, fn.__doc__ = f"check_{name}", f"{name} check"
    monkeypatch.setattr(cli, "checks", lambda plugins=True: fake)
    assert cli.main(["--out", str(tmp_path), "--only", "ok"]) == 0
    assert cli.main(["--out", str(tmp_path)]) == 1
    data = json.loads((tmp_path / "validation.json").read_text())
    assert [r["passed"] for r in data["results"]] == [True, False]
    assert "| fake |" in (tmp_path / "validation.md").read_text()
    with pytest.raises(SystemExit, match="unknown check"):
        cli.main(["--out", str(tmp_path), "--only", "nope"])
    fake["boom"] = lambda level: 1 / 0
    assert cli.main(["--out", str(tmp_path), "--only", "boom"]) == 2
    assert math.isfinite(data["meta"]["total_s"])
