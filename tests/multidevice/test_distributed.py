"""Two local CPU processes joined by ``jax.distributed`` (``python -m
benchmarks.distributed``, run from the repository root) run one batch of Fold-Cloth-1
rollouts (coarse: 4 x 4 vertices, 12 substeps per action), forward and backward, split over
both processes' devices; both gather the same result, bit for bit, and it equals the
single-process run within ``rtol=1e-5, atol=1e-6`` (the same float-rounding reasons as in
``test_sharding.py``: the summed return and each process's program for 2 envs instead of
4)."""

import json
from pathlib import Path

import chex
import numpy as np
import pytest
from multidevice_helpers import free_port, run_all

ROOT = Path(__file__).resolve().parents[2]
ARGS = ["-m", "benchmarks.distributed", "--task", "fold_cloth1", "--batch", "4",
        "--steps", "3", "--seed", "0", "--set", "substeps=12", "--set", "scene.n=4",
        "--set", "scene.settle_substeps=6", "--no-goal-cache"]
TIMEOUT = 240
FIELDS = ("return", "rewards", "final_r_gt", "grad")


def _arrays(record):
    return {k: np.asarray(record[k], np.float32) for k in FIELDS}


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """The single-process run and the two processes, all started at once."""
    tmp = tmp_path_factory.mktemp("distributed")
    coordinator = f"127.0.0.1:{free_port()}"
    jobs = [([*ARGS, "--out", str(tmp / "single.json")], 1)]
    for pid in range(2):
        jobs.append(([*ARGS, "--coordinator", coordinator, "--num-processes", "2",
                      "--process-id", str(pid), "--timeout", "120",
                      "--out", str(tmp / f"{pid}.json")], 1))
    run_all(jobs, timeout=TIMEOUT, cwd=ROOT)
    return {name: json.loads((tmp / f"{name}.json").read_text())
            for name in ("single", "0", "1")}


@pytest.fixture(scope="module")
def single(results):
    return results["single"]


@pytest.fixture(scope="module")
def pair(results):
    return [results["0"], results["1"]]


def test_two_processes_form_one_job_over_both_devices(pair):
    for pid, rec in enumerate(pair):
        assert rec["process_id"] == pid
        assert rec["process_count"] == 2
        assert rec["device_count"] == 2 and rec["local_device_count"] == 1


def test_both_processes_gather_the_same_result(pair):
    assert pair[0]["digest"] == pair[1]["digest"]
    chex.assert_trees_all_equal(_arrays(pair[0]), _arrays(pair[1]))


def test_two_process_result_equals_the_single_process_run(pair, single):
    assert single["process_count"] == 1 and single["device_count"] == 1
    two, one = _arrays(pair[0]), _arrays(single)
    assert one["rewards"].shape == (4, 3) and one["grad"].shape == (4, 3, 6)
    assert np.all(np.isfinite(one["grad"])) and np.any(one["grad"] != 0)
    chex.assert_trees_all_close(two, one, rtol=1e-5, atol=1e-6)
