"""The custom-task example in README.md runs and stays under 60 lines."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def _example() -> str:
    text = README.read_text()
    head = text.index("### A custom task")
    return re.search(r"```python\n(.*?)```", text[head:], re.S).group(1)


def test_custom_task_example_is_short_and_runs(capsys):
    code = _example()
    n = len(code.strip().splitlines())
    assert n < 60, f"expected the README example under 60 lines, got {n}"
    exec(compile(code, str(README), "exec"), {"__name__": "readme_example"})
    out = capsys.readouterr().out
    assert "r_gt" in out and "done True" in out, f"unexpected example output: {out!r}"
