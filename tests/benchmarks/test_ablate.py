"""The ablation benchmark's bookkeeping (``benchmarks/ablate.py``): a variant is called
better only when its paired difference from the baseline over the same seeds exceeds 2 SE;
a resumed run reads back what a killed one wrote, a torn last line dropped."""

import json
import math
import re

import pytest

from benchmarks import ablate


def _rec(variant, seed, score, untrained=0.3):
    return {"method": "apg", "task": "fold_cloth1", "budget": "full", "variant": variant,
            "changes": {}, "seed": seed, "status": "ok", "score": score,
            "untrained": untrained, "env_steps_per_s": 5.0}


def test_summary_pairs_variants_with_the_baseline_by_seed():
    base = [0.40, 0.50, 0.60]
    records = [_rec("baseline", s, x) for s, x in enumerate(base)]
    # +0.05 on every seed: the paired SE is 0, the unpaired spread 0.06: better
    records += [_rec("steady", s, x + 0.05) for s, x in enumerate(base)]
    # the same mean gain, but from one seed: its paired SE is 0.05, not better
    gains = (0.15, 0.0, 0.0)
    records += [_rec("lucky", s, base[s] + gains[s]) for s in range(3)]
    records.append({**_rec("broken", 0, 0.9), "status": "failed"})  # left out
    out = {s["variant"]: s for s in ablate.summarise(records)}
    assert list(out) == ["baseline", "lucky", "steady"]
    assert out["steady"]["minus_baseline"] == pytest.approx(0.05)
    assert out["steady"]["minus_baseline_se"] == pytest.approx(0.0, abs=1e-12)
    assert out["steady"]["better"]
    assert out["lucky"]["minus_baseline"] == pytest.approx(0.05)
    assert out["lucky"]["minus_baseline_se"] == pytest.approx(0.05)
    assert not out["lucky"]["better"]
    assert out["baseline"]["score_mean"] == pytest.approx(0.5)
    assert out["baseline"]["score_se"] == pytest.approx(0.1 / math.sqrt(3))
    assert math.isnan(out["baseline"]["minus_baseline"]) and not out["baseline"]["better"]


def test_a_method_without_env_steps_summarises_without_a_rate():
    """Transporter trains on demonstrations only: its records have no env steps per
    second, and its summary says none (a run once crashed here after its first seed)."""
    records = [{**_rec("baseline", s, 0.4 + 0.01 * s), "method": "transporter",
                "env_steps_per_s": None} for s in range(2)]
    (summary,) = ablate.summarise(records)
    assert summary["env_steps_per_s"] is None
    assert summary["score_mean"] == pytest.approx(0.405)


def test_a_resumed_run_reads_the_records_and_drops_a_torn_line(tmp_path):
    path = tmp_path / "ablate.jsonl"
    assert ablate.read_records(path) == []
    records = [_rec("baseline", 0, 0.4), _rec("baseline", 1, 0.5)]
    ablate.write(path, records)
    text = path.read_text()
    assert text.count('"summary": true') == 1  # the summary is rewritten, not read back
    path.write_text(text + json.dumps(_rec("baseline", 2, 0.6))[:40])  # a killed writer
    assert ablate.read_records(path) == records


def test_max_minutes_stops_between_seeds_of_one_variant(tmp_path, monkeypatch):
    """``--max-minutes`` is read after every seed, not only between variants: a run of
    2-minute seeds with 3 minutes left stops after its second seed and starts no other
    variant; the records written so far stay on disk for the resumed run."""
    clock = [0.0]
    monkeypatch.setattr(ablate.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(ablate.execute, "use_default_compilation_cache", lambda: None)
    monkeypatch.setattr(ablate, "chart", lambda records, summaries, path: str(path))

    def fake_run_seeds(task, method, variant, changes, seeds, *rest):
        for seed in seeds:
            clock[0] += 120.0
            yield {**_rec(variant, seed, 0.5), "method": method, "task": task}

    monkeypatch.setattr(ablate, "run_seeds", fake_run_seeds)
    out = tmp_path / "ablate.jsonl"
    argv = ["apg", "fold_cloth1", "--variants", "baseline,raw_obs", "--seeds", "5",
            "--max-minutes", "3", "--out", str(out)]
    assert ablate.main(argv) == 0
    assert [(r["variant"], r["seed"]) for r in ablate.read_records(out)] == [
        ("baseline", 0), ("baseline", 1)]


def test_a_variant_run_on_another_budget_is_not_resumed(tmp_path, monkeypatch, capsys):
    """A variant is its changes from the budget: records whose config digest is not
    today's (the budget changed since) are named, and nothing is appended to them."""
    from dax_algos import registry
    from dax_algos.bench import provenance

    monkeypatch.setattr(ablate.execute, "use_default_compilation_cache", lambda: None)
    today = provenance.config_digest(registry.get("apg").config("full", "fold_cloth1"))
    out = tmp_path / "ablate.jsonl"
    ablate.write(out, [{**_rec("baseline", 0, 0.4), "provenance": {"config_digest": today}},
                       {**_rec("baseline", 1, 0.5), "provenance": {"config_digest": "old"}}])
    assert ablate.stale_seeds(ablate.read_records(out), "apg", "fold_cloth1", "baseline",
                              {}, "full") == [1]
    with pytest.raises(SystemExit):
        ablate.main(["apg", "fold_cloth1", "--variants", "baseline", "--seeds", "3",
                     "--out", str(out)])
    assert "variant 'baseline' seeds [1] were run with another config" in (
        capsys.readouterr().err)
    assert len(ablate.read_records(out)) == 2


def test_a_variant_run_on_other_task_code_is_not_resumed(tmp_path):
    """Records whose task fingerprint is not today's (the spec or the physics changed
    since) are stale too; a record without provenance is judged on nothing."""
    from dax_algos import registry
    from dax_algos.bench import provenance

    config = provenance.config_digest(registry.get("apg").config("full", "fold_cloth1"))
    task = provenance.task_spec("fold_cloth1").fingerprint()
    out = tmp_path / "ablate.jsonl"
    ablate.write(out, [
        {**_rec("baseline", 0, 0.4),
         "provenance": {"config_digest": config, "task_fingerprint": task}},
        {**_rec("baseline", 1, 0.5),
         "provenance": {"config_digest": config, "task_fingerprint": "0123456789ab"}},
        _rec("baseline", 2, 0.5)])
    assert ablate.stale_seeds(ablate.read_records(out), "apg", "fold_cloth1", "baseline",
                              {}, "full") == [1]


def _grid_with_rows(tmp_path, task, method, rows, machine=None):
    """A benchmark grid directory with ``rows`` ((seed, score, untrained, config digest))
    of ``method`` on ``task`` at the full budget and a two-update curve per seed, run on
    this device and ``machine`` class (this host's if ``None``)."""
    from dax_algos.bench import learning, provenance, rundir
    from dax_algos.bench import rows as rows_mod

    machine = rundir.machine_class() if machine is None else machine

    fingerprint = provenance.task_spec(task).fingerprint()
    tmp_path.mkdir()
    for seed, score, untrained, config in rows:
        learning.append_curve(learning.learning_path(tmp_path, task), [
            dict(task=task, method=method, seed=seed, budget="full", update=u,
                 env_steps=10.0 * (u + 1), wall_s=1.0 + u, score=0.1 * (u + 1) + seed)
            for u in range(2)])
        rows_mod.append_row(tmp_path / "results.csv", rows_mod.make_row(
            task, method, seed, "full", status="ok", score=score, untrained_score=untrained,
            wall_s=12.5, compile_s=2.0, env_steps=40, nonfinite_grads=0,
            task_fingerprint=fingerprint, config_digest=config,
            device=provenance.device(), machine=machine))
    return tmp_path


def _fake_training(monkeypatch, score):
    """Make ``ablate.main`` train nothing: each (variant, seed) it would train is appended
    to the list returned and recorded with ``score(seed)``; no chart, no compilation cache."""
    monkeypatch.setattr(ablate.execute, "use_default_compilation_cache", lambda: None)
    monkeypatch.setattr(ablate, "chart", lambda records, summaries, path: str(path))
    trained = []

    def fake_run_seeds(task, method, variant, changes, seeds, *rest):
        for seed in seeds:
            trained.append((variant, seed))
            yield {**_rec(variant, seed, score(seed)), "method": method, "task": task}

    monkeypatch.setattr(ablate, "run_seeds", fake_run_seeds)
    return trained


def test_the_baseline_is_taken_from_a_grids_rows_of_todays_config(tmp_path, monkeypatch):
    """``--baseline-from GRID``: the grid's rows of today's baseline config and task code
    become the baseline's seed records (score, untrained, curve), only the variants are
    trained, and the summary pairs them by seed; a row of another config is refused by
    seed, and nothing is written."""
    from dax_algos import registry
    from dax_algos.bench import provenance

    trained = _fake_training(monkeypatch, lambda seed: 0.6 + 0.01 * seed)
    today = provenance.config_digest(registry.get("apg").config("full", "fold_cloth1"))
    grid = _grid_with_rows(tmp_path / "grid", "fold_cloth1", "apg",
                           [(0, 0.40, 0.30, today), (1, 0.50, 0.31, today)])
    out = tmp_path / "ablate.jsonl"
    assert ablate.main(["apg", "fold_cloth1", "--variants", "baseline,raw_obs",
                        "--seeds", "2", "--baseline-from", str(grid), "--out",
                        str(out)]) == 0
    assert trained == [("raw_obs", 0), ("raw_obs", 1)]
    base = [r for r in ablate.read_records(out) if r["variant"] == "baseline"]
    assert [(r["seed"], r["score"], r["untrained"]) for r in base] == [
        (0, 0.40, 0.30), (1, 0.50, 0.31)]
    assert base[1]["curve"] == pytest.approx([1.1, 1.2])
    assert base[0]["source"].startswith("grid:")
    summary = {s["variant"]: s for s in ablate.summarise(ablate.read_records(out))}
    assert summary["raw_obs"]["minus_baseline"] == pytest.approx(0.155)
    assert f"apg on fold_cloth1: the grid `{grid}`" in ablate.render_table(out)

    stale = _grid_with_rows(tmp_path / "stale", "fold_cloth1", "apg",
                            [(0, 0.40, 0.30, today), (1, 0.50, 0.31, "0123456789ab")])
    with pytest.raises(ValueError, match="seed 1 is not today's baseline.*config changed"):
        ablate.grid_baseline(stale, "fold_cloth1", "apg", [0, 1], "full", {})


def test_seeds_a_to_b_run_those_seeds_only(tmp_path, monkeypatch):
    """``--seeds 1-2`` trains seeds 1 and 2 (a piece beside another process); ``--seeds 2``
    seeds 0 and 1."""
    trained = _fake_training(monkeypatch, lambda seed: 0.5)
    for text, want in (("1-2", [1, 2]), ("2", [0, 1])):
        trained.clear()
        assert ablate.main(["apg", "fold_cloth1", "--variants", "raw_obs", "--seeds", text,
                            "--out", str(tmp_path / f"{text}.jsonl")]) == 0
        assert trained == [("raw_obs", s) for s in want]


def test_pieces_run_into_their_own_files_are_joined_and_not_retrained(tmp_path, monkeypatch,
                                                                       capsys):
    """``--join PIECE`` adds the piece's seed records that ``--out`` lacks (a seed both
    hold is kept once), so the joined run trains nothing already trained and summarises
    every seed; a piece that scores a seed otherwise, or is of another task, is refused
    and ``--out`` is left as it was."""
    trained = _fake_training(monkeypatch, lambda seed: 0.5)
    out, piece = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    ablate.write(out, [_rec("baseline", 0, 0.4), _rec("raw_obs", 0, 0.45)])
    ablate.write(piece, [_rec("baseline", 0, 0.4), _rec("baseline", 1, 0.5),
                         _rec("raw_obs", 1, 0.6)])
    assert ablate.main(["apg", "fold_cloth1", "--variants", "baseline,raw_obs", "--seeds", "2",
                        "--join", str(piece), "--out", str(out)]) == 0
    assert trained == []
    assert sorted((r["variant"], r["seed"]) for r in ablate.read_records(out)) == [
        ("baseline", 0), ("baseline", 1), ("raw_obs", 0), ("raw_obs", 1)]
    (raw,) = [s for s in ablate.summarise(ablate.read_records(out)) if s["variant"] == "raw_obs"]
    assert raw["seeds"] == [0, 1] and raw["minus_baseline"] == pytest.approx(0.075)
    before = out.read_text()
    for bad, says in (([_rec("raw_obs", 1, 0.7)], "raw_obs' seed 1 scores 0.7"),
                      ([{**_rec("raw_obs", 2, 0.7), "task": "fold_cloth3"}], "fold_cloth3")):
        ablate.write(piece, bad)
        with pytest.raises(SystemExit):
            ablate.main(["apg", "fold_cloth1", "--variants", "raw_obs", "--seeds", "3",
                         "--join", str(piece), "--out", str(out)])
        assert says in capsys.readouterr().err
        assert out.read_text() == before and trained == []


def test_a_grids_row_of_another_machine_class_is_not_borrowed_unless_asked(tmp_path):
    """Training repeats to the bit only within one machine class: a grid row of another
    class, or of none recorded (rows of before the column), is refused by seed with the two
    classes named; with ``any_machine`` it is taken, its record says its class, and the
    table of a file mixing classes says so."""
    from dax_algos import registry
    from dax_algos.bench import provenance, rundir

    today = provenance.config_digest(registry.get("apg").config("full", "fold_cloth1"))
    for machine in ("sse4_1+avx", ""):
        grid = _grid_with_rows(tmp_path / f"grid{machine}", "fold_cloth1", "apg",
                               [(0, 0.40, 0.30, today)], machine=machine)
        with pytest.raises(ValueError, match=(
                f"seed 0 ran on device cpu:cpu, machine class "
                f"{re.escape(repr(machine or 'unknown'))}, "
                f"not this one .*--baseline-any-machine")):
            ablate.grid_baseline(grid, "fold_cloth1", "apg", [0], "full", {})
    (base,) = ablate.grid_baseline(grid, "fold_cloth1", "apg", [0], "full", {},
                                   any_machine=True)
    assert ablate.record_machine(base) == "unknown" and base["score"] == 0.40
    out = tmp_path / "mixed.jsonl"
    here = {**_rec("raw_obs", 0, 0.5), "machine": rundir.cpu_info()}
    ablate.write(out, [base, here])
    assert ablate.record_machine(here) == rundir.machine_class()
    assert f"paired difference may compare two machines' runs: `{out.as_posix()}` (2 " \
           f"classes)" in ablate.render_table(out)
    ablate.write(out, [{**base, "provenance": {**base["provenance"],
                                               "machine": rundir.machine_class()}}, here])
    assert "machine class" not in ablate.render_table(out)


@pytest.mark.parametrize("method,task,named", [("shac", "unfold_cloth1", "steps_800"),
                                               ("ppo", "fold_cloth3", "steps_2688"),
                                               ("ppo", "unfold_cloth1", "steps_6528"),
                                               ("apg", "whip_rope", "longest")])
def test_to_read_is_the_run_the_named_budget_reads_took(method, task, named):
    """``to_read``, computed from the config, is the config the first budget reads ran
    under their own names; with a ``--set`` that halves the envs per update it asks for
    the same updates per env, so half the env steps."""
    from benchmarks.budgets import MIN_UPDATES

    from dax_algos import registry

    assert ablate.to_read_variant(method, task, "full", {}) == ablate.VARIANTS[method][named]
    cfg = registry.get(method).config("full", task)
    half = {"num_envs": cfg.num_envs // 2}
    steps = ablate.to_read_variant(method, task, "full", half)["total_env_steps"]
    assert steps * 2 == ablate.VARIANTS[method][named]["total_env_steps"]
    assert steps >= MIN_UPDATES * cfg.num_envs // 2  # at least one step per env per update


def test_scaled_variants_scale_the_budget_steps_under_its_overrides():
    """``x3`` and ``half`` are the budget's config (after ``--set``) run three times or half
    as long; a method without env steps (Transporter trains on demonstrations) gets no
    change."""
    from dax_algos import registry

    cfg = registry.get("shac").config("full", "fold_cloth3")
    x3, half = ablate.SCALED["x3"], ablate.SCALED["half"]
    assert ablate.scaled_variant("shac", "fold_cloth3", "full", {}, x3) == {
        "total_env_steps": 3 * cfg.total_env_steps}
    assert ablate.scaled_variant("apg", "unfold_cloth1", "full", {"total_env_steps": 100},
                                 x3) == {"total_env_steps": 300}
    assert ablate.scaled_variant("ild", "fold_tshirt", "full", {"total_env_steps": 480},
                                 half) == {"total_env_steps": 240}
    assert ablate.scaled_variant("apg", "fold_tshirt", "full", {"total_env_steps": 1},
                                 half) == {"total_env_steps": 1}
    assert ablate.scaled_variant("transporter", "fold_cloth1", "full", {}, x3) == {}
