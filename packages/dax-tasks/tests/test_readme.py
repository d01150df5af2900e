"""The README's examples run: the custom task (under 60 lines, registered and built by
``dax_tasks.make``) and the system identification, which must recover the rope's Young's
modulus."""

import re
from pathlib import Path

import pytest

import dax_tasks

README = Path(__file__).resolve().parents[1] / "README.md"


def _example(heading: str) -> str:
    text = README.read_text()
    head = text.index(heading)
    return re.search(r"```python\n(.*?)```", text[head:], re.S).group(1)


def test_custom_task_example_is_short_and_runs(capsys, monkeypatch, tmp_path):
    from dax_tasks.core import registry

    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))  # unregistered after
    monkeypatch.setenv("DAX_CACHE_DIR", str(tmp_path))
    code = _example("### A custom task")
    n = len(code.strip().splitlines())
    assert n < 60, f"expected the README example under 60 lines, got {n}"
    exec(compile(code, str(README), "exec"), {"__name__": "readme_example"})
    out = capsys.readouterr().out
    assert "r_gt" in out and "done True" in out, f"unexpected example output: {out!r}"
    assert "nudge_block" in dax_tasks.available()
    assert list(tmp_path.glob("goals/nudge_block-*.npz")), "make did not cache the goal"


def test_system_identification_example_recovers_the_youngs_modulus(capsys):
    code = _example("### Differentiable parameters")
    exec(compile(code, str(README), "exec"), {"__name__": "readme_example"})
    out = capsys.readouterr().out
    match = re.search(r"recovered E = (\d+) Pa", out)
    assert match, f"unexpected example output: {out!r}"
    assert float(match.group(1)) == pytest.approx(2e4, rel=0.01), out
