"""The dax-data command line on one recorded file, run as a subprocess: inspect, validate,
export (meshes, Minari), and one-line refusals with exit code 2. Generation itself
(interrupted and resumed, overrides), goals and score: ``test_cli_generate.py``."""

import json
import os
import subprocess
import sys

import h5py
import numpy as np
import pytest
from data_cli_helpers import SMALL, TASK, assert_one_line_error, read_all, run

import dax_tasks
from dax_data import fileformat as ff


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
