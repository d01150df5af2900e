"""The README's small-scene example (issue 17, item 10): run exactly as written, its expert
must fold the cloth, scoring what the README states."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np

import dax_data
from dax_data.record import parse_overrides

README = Path(__file__).resolve().parents[1] / "README.md"
_SCRIPT = Path(sys.executable).with_name("dax-data")
CMD = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "dax_data"]


def _example():
    """The example command and the expert score the README states for it."""
    text = " ".join(README.read_text().split())
    m = re.search(r"Example, a 6 x 6 cloth.*?`(dax-data generate [^`]*)`\. Its expert scores "
                  r"([0-9.]+) ± ([0-9.]+)", text)
    assert m, "the README's small-scene example is missing or reworded"
    return shlex.split(m.group(1))[1:], float(m.group(2)), float(m.group(3))


def test_readme_small_cloth_example_is_a_scene_the_expert_folds(tmp_path):
    args, stated, sem = _example()
    overrides = [a for i, a in enumerate(args) if i and args[i - 1] == "--override"]
    assert overrides == ["scene.n=6", "scene.settle_substeps=200", "substeps=400"], args
    env = dict(os.environ, DAX_CACHE_DIR=str(tmp_path / "cache"))
    proc = subprocess.run([*CMD, *args, "--no-progress"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    with dax_data.open_file(tmp_path / "small.h5") as f:
        f.verify()
        scores = [f.episode(k).score for k in range(len(f))]
        assert len(f) == 2 and f.episode(0).points.shape[1] == 36
    assert min(scores) > 0.8, f"the example's expert scores {scores}"
    # the README's number: 20 seeds, as one batch
    score = dax_data.score("fold_cloth1", 20, 0, policies=("expert",),
                           overrides=parse_overrides("fold_cloth1", overrides))
    mean = score["expert"]["mean"]
    assert mean > 0.8 and abs(mean - stated) < max(3 * sem, 0.005), (mean, stated)
    assert np.all(np.asarray(score["expert"]["scores"]) > 0.5), score["expert"]["scores"]
