"""Cross-package checks: the four DaX packages, installed together, fit one another.

Run by `nox -s integration`, which installs all four packages from packages/.
"""

import importlib
import re
import subprocess
import sys
from importlib.metadata import requires, version
from pathlib import Path

import pytest
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parents[1]

# Distribution name -> import name, lowest layer first (DESIGN.md section 1).
LAYERS = {
    "dax-physics": "dax_physics",
    "dax-tasks": "dax_tasks",
    "dax-data": "dax_data",
    "dax-algos": "dax_algos",
}
DISTS = list(LAYERS)


def _sibling_requirements(dist: str) -> list[Requirement]:
    reqs = [Requirement(r) for r in requires(dist) or []]
    return [r for r in reqs if r.name in LAYERS and r.marker is None]


def _source_version(dist: str) -> str:
    pyproject = REPO / "packages" / dist / "pyproject.toml"
    match = re.search(r'^version\s*=\s*"([^"]+)"', pyproject.read_text(), re.MULTILINE)
    assert match, f'expected a version = "..." line in {pyproject}, found none'
    return match.group(1)


@pytest.mark.parametrize("dist", DISTS)
def test_package_imports(dist):
    module = importlib.import_module(LAYERS[dist])
    assert module.__name__ == LAYERS[dist], (
        f"expected module {LAYERS[dist]!r}, got {module.__name__!r}"
    )


@pytest.mark.parametrize("dist", DISTS)
def test_installed_version_equals_version_in_source_tree(dist):
    expected = _source_version(dist)
    assert version(dist) == expected, (
        f"expected installed {dist} {expected} (packages/{dist}/pyproject.toml), "
        f"got {version(dist)}: the installed copy is stale"
    )


@pytest.mark.parametrize(
    ("dist", "sibling"),
    [(d, r.name) for d in DISTS for r in _sibling_requirements(d)],
)
def test_declared_sibling_range_admits_installed_sibling(dist, sibling):
    (req,) = [r for r in _sibling_requirements(dist) if r.name == sibling]
    installed = version(sibling)
    assert req.specifier.contains(installed, prereleases=True), (
        f"expected installed {sibling} within {dist}'s declared range '{req.specifier}', "
        f"got {installed}"
    )


@pytest.mark.parametrize("dist", DISTS)
def test_package_depends_only_on_lower_layers(dist):
    below = set(DISTS[: DISTS.index(dist)])
    declared = {r.name for r in _sibling_requirements(dist)}
    assert declared <= below, (
        f"expected {dist} to depend only on lower layers {sorted(below)}, got {sorted(declared)}"
    )


@pytest.mark.parametrize("dist", DISTS)
def test_importing_package_loads_no_higher_layer(dist):
    above = [LAYERS[d] for d in DISTS[DISTS.index(dist) + 1 :]]
    code = (
        "import sys\n"
        f"import {LAYERS[dist]}\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] in {above!r}))\n"
    )
    # A fresh interpreter, so modules imported by other tests do not count.
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, (
        f"expected import {LAYERS[dist]} to succeed, got exit {proc.returncode}:\n{proc.stderr}"
    )
    loaded = proc.stdout.strip()
    assert loaded == "[]", f"expected import {LAYERS[dist]} to load none of {above}, got {loaded}"
