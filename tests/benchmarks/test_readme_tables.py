"""The READMEs' generated tables (issue 37): every block between
``<!-- generated: python -m benchmarks.tables ... -->`` and ``<!-- end generated -->`` in
every README.md of the repository is what its command renders from its result files now;
a table edited by hand, or a result file changed under it, fails here."""

import shutil

import pytest

from benchmarks import tables

READMES = tables.readmes()
BLOCKS = [(path, m["args"]) for path in READMES for m, _ in tables.blocks(path.read_text())]


def test_the_score_tables_of_the_package_readmes_are_generated():
    where = {path.relative_to(tables.ROOT).as_posix() for path, _ in BLOCKS}
    assert {"packages/dax-algos/README.md", "packages/dax-tasks/README.md"} <= where, where
    for path in READMES:  # no block opened and left unclosed, or the other way round
        text = path.read_text()
        assert text.count(tables.BEGIN) == text.count(tables.END) == len(
            tables.blocks(text)), path


@pytest.mark.parametrize("path, args", BLOCKS,
                         ids=[f"{p.parent.name}:{a}" for p, a in BLOCKS])
def test_readme_block_is_what_its_command_renders_now(path, args):
    problems = [d for a, d in tables.stale_blocks(path) if a == args]
    assert not problems, (f"{path}: `python -m benchmarks.tables {args}` renders another "
                          f"table now (run `python -m benchmarks.tables update`):\n"
                          + "\n".join(problems))


def test_a_table_edited_by_hand_is_caught_and_update_restores_it(tmp_path):
    src = tables.ROOT / "packages" / "dax-tasks" / "README.md"
    copy = tmp_path / "README.md"
    shutil.copy(src, copy)
    text = copy.read_text()
    (m, _), *_ = tables.blocks(text)
    body = m["body"]
    edited = body.replace("0.", "0.9", 1)
    assert edited != body
    copy.write_text(text.replace(body, edited, 1))
    (args, diff), = tables.stale_blocks(copy)
    assert args == m["args"] and "-" in diff and "+" in diff
    assert tables.main(["check", str(copy)]) == 1
    assert tables.update(copy) == 1
    assert copy.read_text() == text and tables.stale_blocks(copy) == []


def test_the_scores_command_prints_the_table_with_its_conventions(capsys):
    grid = "benchmarks/results/2026-11-25-grid-random-expert"
    assert tables.main(["scores", grid, "--methods", "expert,random", "--tasks",
                        "push_rope"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[:2] == ["| method | push_rope |", "|---|---|"]
    assert lines[2].startswith("| expert | ") and lines[3] == "| random |  |"  # left out
    assert "over episodes, one per seed" in out and "provenance unknown" in out
    assert tables.main(["scores", "benchmarks/results/no-such-grid"]) == 2


def test_the_throughput_kind_renders_with_benchmarks_tasks(monkeypatch, capsys, tmp_path):
    from benchmarks import tasks

    seen = []
    monkeypatch.setattr(tasks, "render_throughput_table",
                        lambda path: seen.append(path) or "| task |\n|---|", raising=False)
    doc = tmp_path / "throughput.json"
    assert tables.main(["throughput", str(doc)]) == 0
    assert seen == [doc] and capsys.readouterr().out == "| task |\n|---|\n"
    assert tables.render(["throughput", str(doc)]) == "| task |\n|---|\n"
