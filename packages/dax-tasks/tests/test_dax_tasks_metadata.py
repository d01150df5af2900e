"""The installed dax-tasks is the one in this source tree and fits its declared siblings."""

import re
from importlib.metadata import requires, version
from pathlib import Path

from packaging.requirements import Requirement

import dax_tasks

DIST = "dax-tasks"
PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"
# The sibling packages dax-tasks may use: only layers below it (DESIGN.md section 1).
ALLOWED_SIBLINGS = {"dax-physics"}


def _declared_siblings() -> list[Requirement]:
    reqs = [Requirement(r) for r in requires(DIST) or []]
    return [r for r in reqs if r.name.startswith("dax-") and r.marker is None]


def test_version_attribute_equals_installed_distribution_version():
    installed = version(DIST)
    assert dax_tasks.__version__ == installed, (
        f"expected dax_tasks.__version__ == {installed!r} (installed {DIST}), "
        f"got {dax_tasks.__version__!r}"
    )


def test_installed_version_equals_version_in_source_pyproject():
    match = re.search(r'^version\s*=\s*"([^"]+)"', PYPROJECT.read_text(), re.MULTILINE)
    assert match, f'expected a version = "..." line in {PYPROJECT}, found none'
    assert version(DIST) == match.group(1), (
        f"expected installed {DIST} {match.group(1)} (from {PYPROJECT}), "
        f"got {version(DIST)}: the installed copy is stale; reinstall it"
    )


def test_declares_only_lower_layer_siblings():
    declared = {r.name for r in _declared_siblings()}
    assert declared == ALLOWED_SIBLINGS, (
        f"expected sibling dependencies {sorted(ALLOWED_SIBLINGS)}, got {sorted(declared)}"
    )


def test_declared_sibling_ranges_admit_installed_sibling_versions():
    for req in _declared_siblings():
        installed = version(req.name)
        assert req.specifier.contains(installed, prereleases=True), (
            f"expected installed {req.name} within {DIST}'s declared range "
            f"'{req.specifier}', got {installed}"
        )
