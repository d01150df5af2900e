"""The commands the READMEs tell a user to run exist (issue 37): every `nox -s NAME` is a
session of noxfile.py, the Quickstart's main job is `nox -s demo`, and the commands it names
(`dax-bench`, `dax-data`) are console scripts of the packages its sessions install."""

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _sessions() -> set:
    """The session names noxfile.py defines (``@nox.session`` functions, ``name=``)."""
    tree = ast.parse((ROOT / "noxfile.py").read_text())
    names = set()
    for node in tree.body:
        if not isinstance(node, ast.FunctionDef):
            continue
        for dec in node.decorator_list:
            call = dec if isinstance(dec, ast.Call) else None
            target = call.func if call else dec
            if ast.unparse(target) != "nox.session":
                continue
            named = [k.value.value for k in (call.keywords if call else [])
                     if k.arg == "name"]
            names.add(named[0] if named else node.name)
    return names


def _readmes():
    return [ROOT / "README.md", *sorted((ROOT / "packages").glob("*/README.md")),
            ROOT / "benchmarks" / "README.md"]


def test_every_nox_session_a_readme_names_exists():
    sessions = _sessions()
    assert {"demo", "report", "bench"} <= sessions, sessions
    for path in _readmes():
        for name in re.findall(r"nox -s ([a-z][\w-]*)", path.read_text()):
            assert name in sessions, f"{path.name}: `nox -s {name}` is not a session"


def test_the_quickstart_runs_the_demo_and_says_how_to_reach_dax_bench():
    text = (ROOT / "README.md").read_text()
    quick = text[text.index("## Quickstart"):text.index("## Layout")]
    assert "nox -s demo" in quick and "nox -s report" in quick
    assert ".nox/demo/bin/dax-bench" in quick
    assert "dax-bench report --out bench_out`, as" not in quick


def test_the_commands_the_readmes_name_are_console_scripts_of_installed_packages():
    scripts = {}  # (read without tomllib, which Python 3.10 lacks)
    for pyproject in (ROOT / "packages").glob("*/pyproject.toml"):
        text = pyproject.read_text()
        table = re.search(r"^\[project\.scripts\]\n(.*?)(?:\n\[|\Z)", text, re.M | re.S)
        for name in re.findall(r"^([\w-]+)\s*=", table.group(1), re.M) if table else ():
            scripts[name] = pyproject.parent.name
    assert scripts.get("dax-bench") == "dax-algos" and scripts.get("dax-data") == "dax-data"
    noxfile = (ROOT / "noxfile.py").read_text()
    for session in ("demo", "report", "bench"):  # each installs every layer
        body = noxfile[noxfile.index(f"def {session}("):]
        body = body[:body.index("\n\n\n")]
        assert "_install_local(session, LAYERS)" in body, session


def test_each_package_readme_starts_with_how_to_install_it():
    for path in sorted((ROOT / "packages").glob("*/README.md")):
        text = path.read_text()
        first_section = re.search(r"^## (.+)$", text, re.M)
        assert first_section and first_section.group(1).startswith("Install") or (
            "pip install" in text[:text.index("\n## ")]), path
