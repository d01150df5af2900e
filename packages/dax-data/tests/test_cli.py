"""The dax-data command line, run as a subprocess: generate (interrupted and resumed),
inspect, validate, export, goals, score, and one-line refusals with exit code 2."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

import dax_data
import dax_tasks
from dax_data import fileformat as ff
from dax_tasks.core import goals

TASK = "fold_cloth1"  # cheap, with an expert; default (full) resolution
_SCRIPT = Path(sys.executable).with_name("dax-data")
CMD = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "dax_data"]


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    out = dict(os.environ)
    out["DAX_CACHE_DIR"] = str(tmp_path_factory.mktemp("cache"))
    return out


def run(env, *args, timeout=300):
    return subprocess.run([*CMD, *map(str, args)], env=env, capture_output=True, text=True,
                          timeout=timeout)


def assert_one_line_error(proc, *needles):
    assert proc.returncode == 2, f"expected exit 2, got {proc.returncode}: {proc.stderr}"
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, f"got stderr {proc.stderr!r}"
    for needle in needles:
        assert needle in lines[0], f"expected {needle!r} in {lines[0]!r}"


def read_all(path):
    with dax_data.open_file(path) as f:
        return [f.episode(k) for k in range(len(f))]


@pytest.fixture(scope="module")
def demo(env, tmp_path_factory):
    path = tmp_path_factory.mktemp("demo") / "demo.h5"
    proc = run(env, "generate", "--task", TASK, "--episodes", 3, "--seed", 0, "--out", path,
               "--point-stride", 2)
    assert proc.returncode == 0, proc.stderr
    assert "3 episodes" in proc.stdout, proc.stdout
    assert "3/3" in proc.stderr, f"expected a progress bar on stderr, got {proc.stderr!r}"
    return path


def test_generate_then_inspect_and_validate(env, demo):
    proc = run(env, "inspect", demo, "--json")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["task"] == TASK and info["episodes"] == 3 and info["seeds"] == [0, 1, 2]
    assert info["generator"]["point_stride"] == 2
    assert info["episode_0_shapes"]["points"] == [3, 121, 3]  # steps 0, 2 and 3
    proc = run(env, "validate", demo)
    assert proc.returncode == 0 and "ok (3 episodes" in proc.stdout, proc.stderr


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


def test_mismatched_arguments_are_refused(env, demo):
    proc = run(env, "generate", "--task", TASK, "--episodes", 3, "--seed", 1, "--out", demo)
    assert_one_line_error(proc, str(demo), "seed=0, not 1")
    proc = run(env, "generate", "--task", TASK, "--episodes", 3, "--seed", 0, "--out", demo,
               "--policy", "random")
    assert_one_line_error(proc, "policy=\"expert\", not \"random\"")


def test_truncated_file_is_refused_in_one_line(env, demo, tmp_path):
    data = demo.read_bytes()
    trunc = tmp_path / "trunc.h5"
    trunc.write_bytes(data[: len(data) * 2 // 3])
    for command in ("validate", "inspect"):
        assert_one_line_error(run(env, command, trunc), str(trunc), "truncated")
    proc = run(env, "generate", "--task", TASK, "--episodes", 3, "--out", trunc)
    assert_one_line_error(proc, str(trunc), "truncated")


def test_newer_format_version_is_refused(env, demo, tmp_path):
    newer = tmp_path / "newer.h5"
    newer.write_bytes(demo.read_bytes())
    with h5py.File(newer, "a") as f:
        f.attrs["format_version"] = ff.FORMAT_VERSION + 1
    assert_one_line_error(run(env, "validate", newer), str(newer),
                          f"format version {ff.FORMAT_VERSION + 1} is newer")


def test_export_writes_cloth_triangles_and_points(env, demo, tmp_path):
    import meshio

    ep = read_all(demo)[1]
    faces = dax_tasks.make(TASK).object_faces
    for fmt in ("vtu", "xdmf", "ply"):
        out = tmp_path / fmt
        proc = run(env, "export", demo, "--episode", 1, "--format", fmt, "--out", out)
        assert proc.returncode == 0, proc.stderr
        mesh = meshio.read(out / f"episode_1_0003.{fmt}")
        np.testing.assert_allclose(mesh.points, ep.points[-1], rtol=0, atol=1e-7)
        np.testing.assert_array_equal(mesh.cells_dict["triangle"], faces)
    assert (tmp_path / "vtu" / "episode_1.pvd").is_file()
    assert_one_line_error(run(env, "export", demo, "--episode", 7, "--format", "ply",
                              "--out", tmp_path), "no episode 7")


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


SMALL = ["--override", "scene.n=6", "--override", "scene.settle_substeps=200",
         "--override", "substeps=400"]  # the README example


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


def test_minari_export_loads_with_minari_and_recovers_the_env(env, demo, tmp_path):
    import gymnasium as gym
    import minari

    out = tmp_path / "minari"
    proc = run(env, "export", demo, "--format", "minari", "--out", out)
    assert proc.returncode == 0, proc.stderr
    assert "dax/fold_cloth1/expert-v0" in proc.stdout, proc.stdout
    assert not list(out.glob(".minari-*")), "the temporary build directory was left behind"
    os.environ["MINARI_DATASETS_PATH"] = str(out)
    try:
        ds = minari.load_dataset("dax/fold_cloth1/expert-v0")
        episodes = read_all(demo)
        assert ds.total_episodes == 3 and ds.total_steps == sum(e.length for e in episodes)
        for got, want in zip(ds.iterate_episodes(), episodes, strict=True):
            np.testing.assert_array_equal(got.observations, want.observations)
            np.testing.assert_array_equal(got.actions, want.actions)
            np.testing.assert_allclose(got.rewards, want.rewards, rtol=1e-7)
            assert not got.terminations.any() and got.truncations[-1]
            assert not got.truncations[:-1].any()
        recovered = ds.recover_environment()
        assert recovered.spec.id == "dax/FoldCloth1-v0"
        obs, _ = recovered.reset(seed=0)
        assert obs.shape == ds.observation_space.shape == episodes[0].observations.shape[1:]
        assert isinstance(ds.action_space, gym.spaces.Box)
    finally:
        os.environ.pop("MINARI_DATASETS_PATH", None)
    # a fresh process that imports neither dax_tasks nor dax_data rebuilds the env too
    code = ("import sys, minari\n"
            "ds = minari.load_dataset('dax/fold_cloth1/expert-v0')\n"
            "env = ds.recover_environment()\n"
            "print(env.spec.id, env.reset(seed=0)[0].shape, 'dax_tasks.gym' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**env, "MINARI_DATASETS_PATH": str(out)}, timeout=300)
    assert proc.returncode == 0, proc.stderr
    want = f"dax/FoldCloth1-v0 {episodes[0].observations.shape[1:]} True"
    assert proc.stdout.strip() == want, proc.stdout
    # the same id again is refused; a file recorded with overrides cannot name the env
    assert_one_line_error(run(env, "export", demo, "--format", "minari", "--out", out),
                          "already exists")
    small = tmp_path / "small.h5"
    assert run(env, "generate", "--task", TASK, "--episodes", 1, "--out", small,
               "--no-progress", *SMALL).returncode == 0
    assert_one_line_error(run(env, "export", small, "--format", "minari", "--out", out,
                              "--dataset-id", "dax/fold_cloth1/small-v0"), "overrides")
    assert not (out / "dax" / "fold_cloth1" / "small-v0").exists()
    assert_one_line_error(run(env, "export", demo, "--format", "ply", "--out", tmp_path),
                          "--episode")
