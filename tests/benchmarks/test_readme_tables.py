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
                        lambda path: seen.append(path) or "| task |\n|---|\n| a |",
                        raising=False)
    doc = tmp_path / "throughput.json"
    assert tables.main(["throughput", str(doc)]) == 0
    assert seen == [doc] and capsys.readouterr().out == "| task |\n|---|\n| a |\n"
    assert tables.render(["throughput", str(doc)]) == "| task |\n|---|\n| a |\n"


#: The README tables that are not measurements (module lists, options, budgets, file
#: layouts, API verbs): the header row of each. Any other table must be a generated block.
CONCEPT_TABLES = {
    "| session | what it does |",
    "| script | what it measures |",
    "| module | what it is |",
    "| name | module | uses simulator gradients | what it does |",
    "| method | what one update is | defaults |",
    "| method | quick (cloth) | quick (MPM tasks) | full (cloth) | full (MPM tasks) |",
    "| method | quick (cloth) | quick (MPM tasks) | full |",
    "| set | episodes | seeds | observations | tasks |",
    "| attribute | content |",
    "| path | dtype, shape | content |",
    "| stage | what |",
    "| kind | model | parameters (SI) |",
    "| check | known answer |",
    "| command | what |",
    "| verb | MPM (`dax_physics.mpm`, also top level) | cloth (`dax_physics.cloth`) |",
    "| function | what it does |",
    "| parameter | unit | meaning |",
    "| module | what it holds |",
    "| | |",
}


def _hand_tables(text: str) -> list[str]:
    """The header rows of the Markdown tables of ``text`` outside generated blocks and
    code fences."""
    heads, in_block, in_fence, in_table = [], False, False, False
    for line in text.splitlines():
        s = line.strip()
        if s.startswith("```"):
            in_fence = not in_fence
        if line.startswith(tables.BEGIN):
            in_block = True
        elif line.startswith(tables.END):
            in_block = False
        is_row = s.startswith("|") and not in_block and not in_fence
        if is_row and not in_table:
            heads.append(s)
        in_table = is_row
    return heads


def test_every_measurement_table_of_the_readmes_is_generated():
    """A table typed by hand outside a generated block is one of the concept tables; a
    new score or speed table must come from a result file (``python -m benchmarks.tables``)
    or, if it is not a measurement, be added to CONCEPT_TABLES."""
    stray = [(path.relative_to(tables.ROOT).as_posix(), head) for path in READMES
             for head in _hand_tables(path.read_text()) if head not in CONCEPT_TABLES]
    assert not stray, stray


def test_every_file_kind_renders_a_readme_block_with_its_module_function():
    import importlib

    used = {argv[0] for path in READMES for _, argv in tables.blocks(path.read_text())}
    for kind, (module, function, _, _) in tables.FILE_KINDS.items():
        assert callable(getattr(importlib.import_module(module), function)), kind
        assert kind in used, f"kind {kind} renders no README block"


def test_a_file_kind_rejects_a_file_of_another_benchmark(tmp_path, capsys):
    doc = tmp_path / "other.json"
    doc.write_text('{"bench": "task"}\n')
    for kind, (_, _, _, nargs) in tables.FILE_KINDS.items():
        files = [str(doc)] * (nargs if isinstance(nargs, int) else 1)
        assert tables.main([kind, *files]) == 2, kind
        assert str(doc) in capsys.readouterr().err, kind


def test_the_ild_weighting_table_states_its_standard_error_convention(tmp_path):
    """One training seed: the SE over its evaluation rollouts, said so; several seeds: the
    SE over the seeds (issue 37: learners' SE over training seeds)."""
    import json

    from benchmarks import ild_weighting

    rec = {"task": "pour_water", "weighting": "flat", "config": {"weighting": "flat"},
           "budget": "full", "env_steps": 30, "rollout_scores": [[0.5, 0.6], [0.7, 0.8]],
           "rollout_se": 0.05, "loss_per_update": [1.0, 0.5], "nonfinite_grads": 0,
           "seconds_per_seed": 3.0}
    one = {**rec, "seeds": 1, "score_mean": 0.55, "score_se": float("nan"),
           "rollout_scores": [[0.5, 0.6]]}
    two = {**rec, "seeds": 2, "score_mean": 0.65, "score_se": 0.1}
    for r, text in ((one, "over the 2 evaluation rollouts of its one training seed"),
                    (two, "over its 2 training seeds")):
        path = tmp_path / "w.jsonl"
        path.write_text(json.dumps(r) + "\n")
        table = ild_weighting.render_table(path)
        assert text in table and "0.50" in table.splitlines()[2], table


def test_result_files_are_read_as_json_or_json_lines(tmp_path):
    from benchmarks._report import file_date, load_range, read_result

    (tmp_path / "2026-01-02-a.json").write_text('{"x": 1}')
    (tmp_path / "b.jsonl").write_text('{"x": 1}\n\n{"x": 2}\n')
    assert read_result(tmp_path / "2026-01-02-a.json")[1] == {"x": 1}
    assert read_result(tmp_path / "b.jsonl")[1] == [{"x": 1}, {"x": 2}]
    assert file_date(tmp_path / "2026-01-02-a.json") == "2026-01-02"
    assert file_date(tmp_path / "b.jsonl") is None
    assert load_range([1.04, None, 2.96]) == "1.0-3.0" and load_range([]) == "not recorded"
