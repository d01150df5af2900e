"""The dax-data command line generating files, run as a subprocess: generate (interrupted
and resumed bit for bit, with scene overrides), goals and score. The commands on one
recorded file: ``test_cli.py`` (two files, so that a parallel test run splits them)."""

import json
import signal
import subprocess
import time

import numpy as np
from data_cli_helpers import CMD, SMALL, TASK, assert_one_line_error, read_all, run

import dax_data
import dax_tasks
from dax_data import fileformat as ff
from dax_tasks.core import goals


def test_interrupted_generate_resumes_with_earlier_episodes_bit_identical(env, tmp_path):
    path = tmp_path / "resume.h5"
    args = ["generate", "--task", TASK, "--episodes", 30, "--seed", 5, "--out", path,
            "--no-progress"]
    proc = subprocess.Popen([*CMD, *map(str, args)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    n = 0
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:
            if path.exists():
                try:
                    with dax_data.open_file(path) as f:
                        n = len(f)
                except dax_data.DataFileError:
                    n = 0
                if n >= 1:
                    break
            time.sleep(0.01)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    before = read_all(path)
    assert 1 <= len(before) < 30, f"expected an interrupted run, got {len(before)} episodes"
    proc = run(env, *args)
    assert proc.returncode == 0, proc.stderr
    after = read_all(path)
    assert [e.seed for e in after] == list(range(5, 35))
    for old, new in zip(before, after, strict=False):
        for key in ff.EPISODE_DATASETS:
            np.testing.assert_array_equal(getattr(new, key), getattr(old, key),
                                          err_msg=f"episode {old.index} {key}")
    assert not ff.stale_temporaries(path)
    assert run(env, "validate", path).returncode == 0


def test_goals_are_written_where_tasks_read_them(env, tmp_path, monkeypatch):
    proc = run(env, "goals", "--task", TASK, "--out", tmp_path / "goals")
    assert proc.returncode == 0, proc.stderr
    spec = dax_tasks.get_spec(TASK)
    path = goals.goal_file(spec, tmp_path / "goals")
    assert path.is_file(), f"expected {path}; got {sorted((tmp_path / 'goals').iterdir())}"
    expected = goals.compute_goal(dax_tasks.env_class(TASK)(spec))
    task = dax_tasks.make(TASK, goal_path=path)
    np.testing.assert_array_equal(task.goal, expected)
    assert "dax-data" in task.goal_provenance["method"]
    monkeypatch.setenv("DAX_CACHE_DIR", str(tmp_path))  # the cache reads <dir>/goals
    cached = dax_tasks.make(TASK)
    assert "dax-data" in cached.goal_provenance["method"], cached.goal_provenance
    assert_one_line_error(run(env, "goals", "--task", "no_such", "--out", tmp_path),
                          "unknown task")


def test_expert_beats_random_on_fold_cloth1(env):
    proc = run(env, "score", "--task", TASK, "--seeds", 20, "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    expert, rand = out["expert"], out["random"]
    assert len(expert["scores"]) == 20 and len(rand["scores"]) == 20
    assert expert["mean"] - 3 * expert["sem"] > rand["mean"] + 3 * rand["sem"], (
        f"expected the expert's r_gt clearly above random's, got {expert['mean']:.3f} ± "
        f"{expert['sem']:.3f} vs {rand['mean']:.3f} ± {rand['sem']:.3f}")
    assert expert["mean"] > 0.8, f"expected expert final r_gt > 0.8, got {expert['mean']:.3f}"


def test_overrides_make_a_small_scene_and_are_part_of_the_arguments(env, tmp_path):
    path = tmp_path / "small.h5"
    args = ["generate", "--task", TASK, "--episodes", 1, "--out", path, "--no-progress"]
    proc = run(env, *args, *SMALL)
    assert proc.returncode == 0, proc.stderr
    with dax_data.open_file(path) as f:
        assert f.meta["spec"]["scene"]["n"] == 6 and f.meta["spec"]["substeps"] == 400
        assert f.episode(0).points.shape[1:] == (36, 3)
    proc = run(env, *args, *SMALL[:4])  # substeps differs from the file's
    assert_one_line_error(proc, str(path), "overrides=")
    assert_one_line_error(run(env, *args, "--override", "scene.nope=1"),
                          "unknown scene override")
    assert_one_line_error(run(env, *args, "--override", "substeps"), "KEY=VALUE")
