"""The validation suite's cheap rope, cloth and gradient checks as tests (see
test_validation_mpm.py), and the report writer's exit status."""

from __future__ import annotations

import json
import math

import pytest
from benchmarks.validate import __main__ as cli
from benchmarks.validate import cloth, gradients, solid

from benchmarks import validate


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
    monkeypatch.setattr(cli, "checks", lambda tasks=True: fake)
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
