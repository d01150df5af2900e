"""Cross-package checks, one parametrised test per property over the four DaX packages:
each installed copy is the source tree's, fits the siblings it declares, declares only
lower layers, imports no higher layer, declares exactly the third-party packages its code
imports, and imports no other package's private names.

Run by `nox -s integration`, which installs all four packages from packages/.
"""

import ast
import importlib
import re
import subprocess
import sys
from importlib.metadata import packages_distributions, requires, version
from pathlib import Path

import pytest
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parents[1]

# Distribution name -> import name, lowest layer first.
LAYERS = {
    "dax-physics": "dax_physics",
    "dax-tasks": "dax_tasks",
    "dax-data": "dax_data",
    "dax-algos": "dax_algos",
}
DISTS = list(LAYERS)


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirements(dist: str) -> list[Requirement]:
    return [Requirement(r) for r in requires(dist) or []]


def _extra(req: Requirement) -> str | None:
    """The extra a requirement belongs to (None for a core dependency)."""
    if req.marker is None:
        return None
    match = re.search(r'extra\s*==\s*"([^"]+)"', str(req.marker))
    return match.group(1) if match else None


def _siblings(dist: str) -> list[Requirement]:
    return [r for r in _requirements(dist) if r.name in LAYERS and _extra(r) is None]


def _source_version(dist: str) -> str:
    pyproject = REPO / "packages" / dist / "pyproject.toml"
    match = re.search(r'^version\s*=\s*"([^"]+)"', pyproject.read_text(), re.MULTILINE)
    assert match, f'expected a version = "..." line in {pyproject}, found none'
    return match.group(1)


def _sources(dist: str) -> list[Path]:
    return sorted((REPO / "packages" / dist / "src" / LAYERS[dist]).rglob("*.py"))


def _imports(dist: str):
    """``(module path, line, imported dotted name, names imported from it)`` for every
    import statement in the package's sources (lazy ones inside functions included)."""
    src = REPO / "packages" / dist / "src"
    for path in _sources(dist):
        tree = ast.parse(path.read_text(), str(path))
        package = list(path.relative_to(src).with_suffix("").parts[:-1])
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for alias in node.names:
                    yield path, node.lineno, alias.name, ()
            elif isinstance(node, ast.ImportFrom):
                name = node.module or ""
                if node.level:  # relative: resolve against the module's package
                    base = package[: len(package) - node.level + 1]
                    name = ".".join(base + ([node.module] if node.module else []))
                yield path, node.lineno, name, tuple(a.name for a in node.names)


@pytest.mark.parametrize("dist", DISTS)
def test_installed_package_is_this_source_tree(dist):
    module = importlib.import_module(LAYERS[dist])
    expected = _source_version(dist)
    assert version(dist) == expected, (
        f"expected installed {dist} {expected} (packages/{dist}/pyproject.toml), "
        f"got {version(dist)}: the installed copy is stale")
    assert module.__version__ == expected, (
        f"expected {LAYERS[dist]}.__version__ == {expected!r}, got {module.__version__!r}")


@pytest.mark.parametrize("dist", DISTS)
def test_declared_siblings_are_lower_layers_whose_installed_versions_fit(dist):
    below = set(DISTS[: DISTS.index(dist)])
    declared = {r.name for r in _siblings(dist)}
    assert declared <= below, (
        f"expected {dist} to depend only on lower layers {sorted(below)}, got {sorted(declared)}")
    for req in _siblings(dist):
        installed = version(req.name)
        assert req.specifier.contains(installed, prereleases=True), (
            f"expected installed {req.name} within {dist}'s declared range "
            f"'{req.specifier}', got {installed}")


@pytest.mark.parametrize("dist", DISTS)
def test_importing_package_loads_no_higher_layer(dist):
    above = [LAYERS[d] for d in DISTS[DISTS.index(dist) + 1:]] + (
        ["gymnasium"] if dist == "dax-tasks" else [])  # only dax_tasks.gym imports it
    code = (f"import sys\nimport {LAYERS[dist]}\n"
            f"print(sorted(m for m in sys.modules if m.split('.')[0] in {above!r}))\n")
    # A fresh interpreter, so modules imported by other tests do not count.
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, (
        f"expected import {LAYERS[dist]} to succeed, got exit {proc.returncode}:\n{proc.stderr}")
    assert proc.stdout.strip() == "[]", (
        f"expected import {LAYERS[dist]} to load none of {above}, got {proc.stdout.strip()}")


@pytest.mark.parametrize("dist", DISTS)
def test_declared_dependencies_match_the_imports(dist):
    """Every third-party package the sources import is declared (as a dependency or in an
    extra other than ``test``), and every declared dependency and extra is imported."""
    owners = {top: {_norm(d) for d in ds} for top, ds in packages_distributions().items()}
    owners.update({imp: {dist_name} for dist_name, imp in LAYERS.items()})
    own = LAYERS[dist]
    declared = {}
    for req in _requirements(dist):
        extra = _extra(req)
        if extra != "test":
            declared.setdefault(_norm(req.name), extra)
    imported = {}
    for path, line, name, _ in _imports(dist):
        top = name.split(".")[0]
        if top == own or top in sys.stdlib_module_names or top == "__future__":
            continue
        if top not in owners and declared.get(_norm(top)):
            # an optional extra this session does not install (``ray``): the import's own
            # name is the distribution's, and the code imports it lazily
            owners[top] = {_norm(top)}
        assert top in owners, f"{path}:{line}: imports {top!r}, which no package provides"
        for owner in owners[top]:
            imported.setdefault(owner, f"{path.name}:{line}")
    undeclared = sorted(set(imported) - set(declared))
    assert not undeclared, (
        f"{dist} imports {[(u, imported[u]) for u in undeclared]} without declaring them")
    unused = sorted(set(declared) - set(imported))
    assert not unused, (
        f"{dist} declares {[(u, declared[u] or 'core') for u in unused]} but never imports "
        f"them (declare a dependency when the code that uses it lands)")


@pytest.mark.parametrize("dist", DISTS)
def test_no_package_imports_another_packages_private_names(dist):
    own = LAYERS[dist]
    bad = []
    for path, line, name, names in _imports(dist):
        parts = name.split(".")
        if parts[0] == own or parts[0] not in LAYERS.values():
            continue
        private = [p for p in parts[1:] if p.startswith("_")]
        private += [n for n in names if n.startswith("_")]
        if private:
            bad.append(f"{path.relative_to(REPO)}:{line}: {name} {private}")
    assert not bad, f"{dist} imports private names of other packages: {bad}"


def _module_name(dist: str, path: Path) -> str:
    parts = path.relative_to(REPO / "packages" / dist / "src").with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _internal_graph(dist: str) -> dict[str, set[str]]:
    """Module -> the modules of the same package it imports (at the top or inside a
    function). ``from a.b import c`` points at ``a.b.c`` when that is a module, else at
    ``a.b``. Parent packages that an import runs first are not edges: a package's
    ``__init__`` re-exporting its modules is not a circle."""
    own = LAYERS[dist]
    modules = {_module_name(dist, p) for p in _sources(dist)}
    graph = {m: set() for m in modules}
    for path, _, name, names in _imports(dist):
        if name.split(".")[0] != own:
            continue
        src = _module_name(dist, path)
        targets = {f"{name}.{n}" for n in names if f"{name}.{n}" in modules}
        if not targets or len(targets) < len(names):
            targets.add(name)
        graph[src] |= {t for t in targets if t in modules and t != src}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str]:
    """One import circle of ``graph`` as a list of modules (empty if there is none)."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                return stack[stack.index(t):] + [t]
            if t not in state and (found := visit(t)):
                return found
        state[m] = 2
        stack.pop()
        return []

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return []


@pytest.mark.parametrize("dist", DISTS)
def test_no_import_circle_inside_the_package(dist):
    circle = _cycle(_internal_graph(dist))
    assert not circle, f"{dist}: modules import each other in a circle: {' -> '.join(circle)}"


def _console_modules(dist: str) -> set[str]:
    text = (REPO / "packages" / dist / "pyproject.toml").read_text()
    block = re.search(r"^\[project\.scripts\]\n(.*?)(?:^\[|\Z)", text, re.M | re.S)
    targets = re.findall(r'=\s*"([\w.]+):\w+"', block.group(1)) if block else []
    return set(targets) | {t.rsplit(".", 1)[0] + ".__main__" for t in targets}


@pytest.mark.parametrize("dist", DISTS)
def test_no_library_module_is_a_script(dist):
    """Benchmarks, studies and demos live in benchmarks/, not in the libraries: the only
    modules that run as programs are the package's declared console commands."""
    allowed = _console_modules(dist)
    scripts = []
    for path in _sources(dist):
        if "__main__" in path.read_text() and _module_name(dist, path) not in allowed:
            if re.search(r"^if __name__ == .__main__.:", path.read_text(), re.M) or \
                    path.name == "__main__.py":
                scripts.append(str(path.relative_to(REPO)))
    assert not scripts, (f"{dist}: library modules that run as programs (move them to "
                         f"benchmarks/ or declare a console command): {scripts}")


#: Arrows inside a package: modules under the first prefix never import the second.
INNER_ARROWS = {
    "dax-physics": [],
    "dax-tasks": [("dax_tasks.core", "dax_tasks.tasks"), ("dax_tasks.core", "dax_tasks.gym"),
                  ("dax_tasks.viz", "dax_tasks.core"), ("dax_tasks.viz", "dax_tasks.tasks"),
                  ("dax_tasks.tasks", "dax_tasks.gym")],
    "dax-data": [],
    "dax-algos": [(m, "dax_algos.bench") for m in (
        "dax_algos.rl", "dax_algos.il", "dax_algos.planning", "dax_algos.registry",
        "dax_algos.method", "dax_algos.learner", "dax_algos.actions", "dax_algos.checks",
        "dax_algos.episode", "dax_algos.mlp_policy", "dax_algos.optim", "dax_algos.nets",
        "dax_algos.toy")],
}


def _under(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


@pytest.mark.parametrize("dist", DISTS)
def test_inner_arrows_point_one_way(dist):
    """dax-algos: the methods never import the runner (dax_algos.bench); dax-tasks: the
    core never imports the tasks or the Gymnasium adapter, the pictures neither."""
    graph = _internal_graph(dist)
    bad = [f"{src} imports {dst}" for src, dsts in graph.items() for dst in sorted(dsts)
           for a, b in INNER_ARROWS[dist] if _under(src, a) and _under(dst, b)]
    assert not bad, f"{dist}: imports against the package's inner arrows: {bad}"
