"""Provenance on every results row (issue 37): each row records the task's fingerprint, the
spec's and params' digests, the method's config digest, versions, commit, precision and
device; when the task's spec (or the method's config) changes, the report, results.md and
the page mark the old rows stale and leave them out of the means unless asked."""

import dataclasses
import re

import pytest
from algos_helpers import cheap_cloth_overrides

import dax_tasks
from dax_algos import registry
from dax_algos.bench import page, provenance, runner, summary
from dax_algos.bench.grid import run_grid
from dax_tasks.core import registry as task_registry

TASK = "fold_cloth1"
PPO = dict(total_env_steps=48, num_envs=8, unroll_length=2, minibatches=2, n_eval=2,
           policy_hidden=(16,), value_hidden=(16,))
OVERRIDES = {TASK: cheap_cloth_overrides(horizon=2)}


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    out = tmp_path_factory.mktemp("prov")
    rows = run_grid(TASK, "random,ppo", seeds=2, out=out, quick=True,
                    task_overrides=OVERRIDES, method_overrides={"ppo": PPO},
                    cache_goal=False, progress=False)
    return out, rows


@pytest.fixture
def changed_spec(monkeypatch):
    """Fold-Cloth-1's registered default spec with another observation stride."""
    entry = task_registry._REGISTRY[TASK]
    spec = dataclasses.replace(dax_tasks.get_spec(TASK), obs_stride=2)
    monkeypatch.setitem(task_registry._REGISTRY, TASK, dataclasses.replace(entry, spec=spec))


def _page_tables(out):
    text = (out / page.PAGE).read_text()
    return text, {tid: re.findall(r"<tr>(.*?)</tr>", body)
                  for tid, body in re.findall(r'<table id="(\w+)">(.*?)</table>', text, re.S)}


def test_every_row_records_what_it_was_measured_on(grid):
    _, rows = grid
    env = dax_tasks.make(TASK, cache_goal=False, **OVERRIDES[TASK])
    for r in rows:
        assert r["task_fingerprint"] == env.spec.fingerprint(), r
        assert r["spec_digest"] == provenance.spec_digest(env.spec)
        assert r["params_digest"] == provenance.tree_digest(env.default_params)
        config = registry.get(r["method"]).config("quick", TASK,
                                                  **(PPO if r["method"] == "ppo" else {}))
        assert r["config_digest"] == provenance.config_digest(config)
        assert "dax-algos=" in r["versions"] and "jax=" in r["versions"]
        assert r["precision"] == "float32" and r["device"].startswith("cpu:")
        assert r["commit"] == provenance.commit()
    digests = {r["config_digest"] for r in rows}
    assert len(digests) == 2  # random's and ppo's


def test_nothing_is_stale_while_the_code_is_unchanged(grid):
    out, _ = grid
    summary.report_dir(out)
    text, tables = _page_tables(out)
    assert "stale" not in tables and "rows are stale" not in text
    assert "## Stale rows" not in (out / "results.md").read_text()
    assert all("±" in cell for cell in re.findall(r"<td[^>]*>([^<]*)</td>",
                                                   tables["scores"][1])[1:])


def test_a_changed_task_spec_marks_the_old_rows_stale_on_the_page_and_in_the_report(
        grid, changed_spec, capsys):
    out, rows = grid
    assert runner.main(["report", "--out", str(out)]) == 0
    text, tables = _page_tables(out)
    assert "4 rows are stale (see Stale rows), left out" in text
    (stale_row,) = tables["stale"][1:]
    assert "the task&#x27;s spec changed" in stale_row and ">4<" in stale_row, stale_row
    assert re.findall(r"<td[^>]*>([^<]*)</td>", tables["scores"][1])[1:] == ["", ""]
    md = (out / "results.md").read_text()
    assert "## Stale rows" in md and "4 of 4 rows no longer describe today's code" in md
    assert "| random |  |" in md  # left out of the means
    # asked for, they are counted and marked
    assert runner.main(["report", "--out", str(out), "--include-stale"]) == 0
    _, tables = _page_tables(out)
    assert all(c.endswith("†") for c in re.findall(r"<td[^>]*>([^<]*)</td>",
                                                    tables["scores"][1])[1:])
    capsys.readouterr()
    assert runner.main(["report", "--out", str(out), "--markdown"]) == 0
    printed = capsys.readouterr().out
    assert "**4 of 4 rows are stale** (left out)" in printed and "spec changed" in printed


def test_a_changed_method_config_marks_only_that_methods_rows_stale(grid, monkeypatch):
    out, _ = grid
    ppo = registry.get("ppo")
    budgets = {**ppo.budgets, "quick": {**ppo.budgets["quick"], "learning_rate": 0.5}}
    monkeypatch.setitem(registry._METHODS, "ppo", dataclasses.replace(ppo, budgets=budgets))
    summary.report_dir(out)
    _, tables = _page_tables(out)
    (stale_row,) = tables["stale"][1:]
    assert "the method&#x27;s config changed" in stale_row and "ppo" in stale_row
    cells = re.findall(r"<td[^>]*>([^<]*)</td>", tables["scores"][1])[1:]
    assert "±" in cells[0] and cells[1] == "", cells  # random counted, ppo left out


def test_stale_reason_tells_a_changed_spec_from_changed_code(grid, monkeypatch):
    _, rows = grid
    today = provenance.Today(OVERRIDES, {"ppo": PPO})
    assert provenance.stale_reason(rows[0], today) == ""
    other_code = dict(rows[0], task_fingerprint="0123456789ab")
    assert "code changed" in provenance.stale_reason(other_code, today)
    other_spec = dict(other_code, spec_digest="ba9876543210")
    assert "spec changed" in provenance.stale_reason(other_spec, today)


def test_a_forward_equivalence_keeps_only_the_rows_of_methods_without_env_gradients(grid):
    """A ledger entry from a row's fingerprint to today's keeps a random or PPO row current
    (neither differentiates the env), not an APG row of the same task unless the entries
    cover the gradients; an entry for another fingerprint, or a row whose spec changed,
    keeps nothing; entries chain."""
    from dax_algos.bench.equivalence import Equivalence, forward_equivalent

    _, rows = grid
    today = provenance.Today(OVERRIDES, {"ppo": PPO})
    now = today.fingerprint(TASK)[0][0]
    old = "0123456789ab"
    ledger = (Equivalence(TASK, old, "feedfacecafe", "test"),
              Equivalence(TASK, "feedfacecafe", now, "test"))
    assert forward_equivalent(old, now, ledger) and not forward_equivalent(now, old, ledger)
    by_method = {r["method"]: r for r in rows}
    for method in ("random", "ppo"):
        row = dict(by_method[method], task_fingerprint=old)
        assert "code changed" in provenance.stale_reason(row, today)  # the real ledger
        assert provenance.stale_reason(row, today, ledger) == ""
        assert "code changed" in provenance.stale_reason(row, today, ledger[:1])
        other_spec = dict(row, spec_digest="ba9876543210")
        assert "spec changed" in provenance.stale_reason(other_spec, today, ledger)
    apg = dict(by_method["ppo"], method="apg", task_fingerprint=old)
    assert "code changed" in provenance.stale_reason(apg, today, ledger)
    # entries whose evidence covers the action gradients keep every method's rows; a chain
    # through a forward-only entry keeps only the forward-only methods'
    values = (Equivalence(TASK, old, "feedfacecafe", "test", gradients=True),
              Equivalence(TASK, "feedfacecafe", now, "test", gradients=True))
    assert forward_equivalent(old, now, values, gradients=True)
    assert not forward_equivalent(old, now, ledger, gradients=True)
    assert "code changed" not in provenance.stale_reason(apg, today, values)  # config: PPO's
    assert provenance.stale_reason(dict(by_method["random"], task_fingerprint=old), today,
                                   values) == ""
    mixed = (values[0], ledger[1])
    assert "code changed" in provenance.stale_reason(apg, today, mixed)
    assert provenance.stale_reason(dict(by_method["ppo"], task_fingerprint=old), today,
                                   mixed) == ""


def test_rerun_stale_runs_again_only_the_runs_whose_rows_are_stale(grid, monkeypatch,
                                                                   tmp_path):
    """After PPO's config changes, a resumed grid leaves the stale PPO rows as they are;
    with ``rerun_stale`` it runs them again (and not the random rows, still current), and
    the new rows count."""
    import shutil

    from dax_algos.bench.rows import latest, read_rows

    out = tmp_path / "grid"
    shutil.copytree(grid[0], out)
    ppo = registry.get("ppo")
    budgets = {**ppo.budgets, "quick": {**ppo.budgets["quick"], "learning_rate": 0.5}}
    monkeypatch.setitem(registry._METHODS, "ppo", dataclasses.replace(ppo, budgets=budgets))
    kwargs = dict(seeds=2, out=out, quick=True, task_overrides=OVERRIDES,
                  method_overrides={"ppo": PPO}, cache_goal=False, progress=False)
    before = read_rows(out / "results.csv")
    run_grid(TASK, "random,ppo", **kwargs)
    assert read_rows(out / "results.csv") == before  # stale rows are done by default
    run_grid(TASK, "random,ppo", rerun_stale=True, **kwargs)
    after = read_rows(out / "results.csv")
    added = after[len(before):]
    assert sorted((r["method"], r["seed"]) for r in added) == [("ppo", "0"), ("ppo", "1")]
    today = provenance.Today(OVERRIDES, {"ppo": PPO})
    assert all(not provenance.stale_reason(r, today) for r in latest(after))


def test_stale_reasons_are_counted_by_kind_a_row_under_each_of_its_reasons():
    from dax_algos.bench import report

    reasons = ["the dax-tasks or dax-physics code changed (fingerprint a, today b)",
               "the dax-tasks or dax-physics code changed (fingerprint c, today b); the "
               "method's config changed (config d, today e)",
               "the task's spec changed (fingerprint f, today g)",
               provenance.UNKNOWN]
    assert report.stale_kinds(reasons) == {
        "the task's spec changed": 1, "the dax-tasks or dax-physics code changed": 2,
        "the method's config changed": 1,
        "provenance unknown or not checkable": 1}
    assert report.stale_kinds([]) == {}


def test_cpu_info_reads_the_first_processors_isa_features_and_the_xla_cap(tmp_path,
                                                                          monkeypatch):
    """The model and the instruction-set features XLA compiles for are read from the first
    processor, in :data:`rundir.ISA_FEATURES` order whatever the file's order (flags that do
    not change XLA's code are left out); ``--xla_cpu_max_isa`` in ``XLA_FLAGS`` is recorded
    as the cap; an unreadable file gives ``["unknown"]`` features rather than an error."""
    from dax_algos.bench import rundir

    path = tmp_path / "cpuinfo"
    path.write_text("processor\t: 0\nmodel name\t: Xeon A\nflags\t\t: fpu avx512f sse2 avx2"
                    " fma\n\nprocessor\t: 1\nmodel name\t: other\nflags\t\t: sse4_1\n")
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert rundir.cpu_info(path) == {"cpu_model": "Xeon A",
                                     "cpu_features": ["avx2", "fma", "avx512f"],
                                     "xla_max_isa": None}
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_max_isa=AVX2 --xla_foo=1")
    assert rundir.cpu_info(path)["xla_max_isa"] == "AVX2"
    assert rundir.cpu_info(tmp_path / "missing")["cpu_features"] == ["unknown"]
    assert {"cpu_model", "cpu_features", "xla_max_isa"} <= set(rundir.machine_info())
    # the class a row records: features and cap; none listed is a class, unreadable is not
    assert rundir.machine_class(rundir.cpu_info(path)) == "avx2+fma+avx512f max_isa=AVX2"
    assert rundir.machine_class({"cpu_features": [], "xla_max_isa": None}) == "none"
    assert rundir.machine_class(rundir.cpu_info(tmp_path / "missing")) == "unknown"
    assert rundir.machine_class({}) == "unknown"


def test_a_field_marked_omit_default_stales_nothing_at_its_default_only_off_it():
    import dataclasses

    from dax_algos.checks import OMIT_DEFAULT

    def config(*added):  # one config class, before and after fields were added to it
        return dataclasses.make_dataclass("Config", [("lr", float, 1e-3), *added],
                                          frozen=True)

    before = provenance.config_digest(config()())
    marked = config(("clip", str, dataclasses.field(default="raw", metadata=OMIT_DEFAULT)))
    assert provenance.config_digest(marked()) == before
    assert provenance.config_digest(marked(clip="median")) != before
    assert provenance.config_digest(config(("clip", str, "raw"))()) != before
