"""Reliability, third pass (issue 38), on a tiny file (a 4 x 4 cloth, 2 steps, 8-pixel
pictures):

* a seeded fuzz of single-bit flips anywhere in the file: every one is a one-line
  ``DataFileError`` naming the file, or leaves the data exactly as written;
* h5py edits (values, attributes, structure) are refused; edits whose every digest and
  checksum a forger recomputed are refused by ``validate``'s value and task checks
  (an action outside the box, the goal moved, a NaN observation, a changed ``r_gt``);
* a symbolic-link ``--out`` is written through and shares its target's lock, in both
  orders of the two writers;
* a waiting writer says who holds the lock (a stopped holder as stopped) and gives up
  after ``--lock-timeout`` in one line;
* sizes and time steps a machine cannot run are refused before anything is written, and a
  first episode that fails leaves no file behind;
* a file recorded in float32 is not resumed in float64; older files warn what they
  cannot check.
"""

import os
import shutil
import signal
import subprocess
import sys
from collections import Counter

import h5py
import numpy as np
import pytest

import dax_data
from dax_data import cli, semantics
from dax_data import fileformat as ff
from dax_tasks import io

TASK = "fold_cloth1"
TINY = ["scene.n=4", "substeps=40", "scene.settle_substeps=20", "horizon=2"]
TINY_ARGS = [a for o in TINY for a in ("--override", o)]
#: single-bit flips of the fuzz (a third of them in the root group's object header,
#: where the probe's flips raised "Object visitation failed"), and the seed placing them
FLIPS, FUZZ_SEED = 300, 38


def one_line_error(capsys, argv, *needles):
    """Run the CLI in-process; assert exit 2 and one error line naming every needle (after
    any ``dax-data: waiting`` notice); return that line."""
    code = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, f"expected exit 2, got {code}: {err}"
    lines = [ln for ln in err.strip().splitlines() if "waiting for another process" not in ln]
    assert len(lines) == 1 and "Traceback" not in err, f"got stderr {err!r}"
    for needle in needles:
        assert needle in lines[0], f"expected {needle!r} in {lines[0]!r}"
    return lines[0]


def generate_args(out, episodes=2, *extra):
    return ["generate", "--task", TASK, "--episodes", episodes, "--out", out,
            "--no-progress", "--obs", "state,height,rgb", "--image-size", 8, *TINY_ARGS,
            *extra]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    path = tmp_path_factory.mktemp("tiny") / "tiny.h5"
    assert cli.main([str(a) for a in generate_args(path)]) == 0
    return path


@pytest.fixture(scope="module")
def tiny_env(tiny):
    with dax_data.open_file(tiny) as f:
        return semantics.task_env(f.meta)


def content(path, env=None):
    """Everything a reader gets from ``path`` after every check ``validate`` runs: the
    metadata, the goal and each episode's arrays and attributes."""
    with dax_data.open_file(path) as f:
        f.verify()
        semantics.check_semantics(f, env)
        out = {"meta": f.meta, "goal": f.goal, "provenance": f.goal_provenance}
        for k in range(len(f)):
            ep = f.episode(k)
            out.update({f"{k}/{key}": value for key, value in vars(ep).items()})
    return out


def assert_same(got, want, what):
    assert got.keys() == want.keys(), what
    for key, value in want.items():
        if isinstance(value, np.ndarray):
            np.testing.assert_array_equal(got[key], value, err_msg=f"{what}: {key}")
        else:
            assert got[key] == value, f"{what}: {key}"


def reseal(path):
    """What a forger does after an edit: every dataset's and episode's digest and the
    attributes' checksum recomputed, so only the value and task checks remain."""
    with h5py.File(path, "a") as f:
        f["goal"].attrs[ff.DIGEST_ATTR] = ff.array_digest(f["goal"][()])
        for g in f["episodes"].values():
            digests = {}
            for key, ds in g.items():
                ds.attrs[ff.DIGEST_ATTR] = digests[key] = ff.array_digest(ds[()])
            g.attrs[ff.DIGEST_ATTR] = ff.episode_digest(digests, dict(g.attrs))
        ff.seal(f)


# ----------------------------------------------------------------------------- fuzz

def test_fuzz_single_bit_flips_are_one_line_errors_or_change_nothing(tiny, tiny_env,
                                                                     tmp_path, capsys):
    """Each flip is either refused (``DataFileError`` naming the file, and the CLI's
    ``validate`` and ``inspect`` exit 2 with one line) or lands in bytes no reader uses
    (the data read back are those written). Any other exception fails the test."""
    rng = np.random.default_rng(FUZZ_SEED)
    data = tiny.read_bytes()
    want = content(tiny, tiny_env)
    with h5py.File(tiny, "r") as f:
        info = h5py.h5o.get_info(f.id)
        root = (info.addr * 8, (info.addr + info.hdr.space.total) * 8)
    outcomes = Counter()
    path = tmp_path / "flip.h5"
    for i in range(FLIPS):
        bit = int(rng.integers(*root) if i % 3 == 0 else rng.integers(len(data) * 8))
        raw = bytearray(data)
        raw[bit // 8] ^= 1 << (bit % 8)
        path.write_bytes(bytes(raw))
        try:
            got = content(path, tiny_env)
        except dax_data.DataFileError as err:
            assert str(err).startswith(f"{path}: ") and "\n" not in str(err), err
            outcomes["refused"] += 1
            one_line_error(capsys, ["validate", path], str(path))
            code = cli.main(["inspect", str(path)])
            err_lines = capsys.readouterr().err.strip().splitlines()
            assert code in (0, 2) and len(err_lines) == (code == 2), (bit, err_lines)
            continue
        assert_same(got, want, f"bit {bit} (byte {bit // 8}) flipped")
        outcomes["unchanged"] += 1
    print(dict(outcomes))
    assert outcomes["refused"] > FLIPS // 2, outcomes  # the file is mostly data


def _set(key, index, value):
    def edit(f):
        ds = f[key]
        a = ds[()]
        a[index] = value
        ds[...] = a
    return edit


def _shift_goal(f):
    f["goal"][...] = f["goal"][()] + np.float32([1.0, 0.0, 0.0])


def _attr(key, attr, value):
    def edit(f):
        (f[key] if key else f).attrs[attr] = value
    return edit


def _recreate(key, transform):
    """Replace dataset ``key`` by ``transform(values)`` written plainly (no chunks, no
    checksum), its attributes copied."""
    def edit(f):
        ds = f[key]
        data, attrs = transform(ds[()]), dict(ds.attrs)
        del f[key]
        new = f.create_dataset(key, data=data)
        for k, v in attrs.items():
            new.attrs[k] = v
    return edit


def _swap_episodes(f):
    f.move("episodes/000000", "episodes/tmp")
    f.move("episodes/000001", "episodes/000000")
    f.move("episodes/tmp", "episodes/000001")


def _rgt_consistent(f):
    """r_gt, the rewards and the score changed together (as a forger would)."""
    g = f["episodes/000000"]
    for key in ("r_gt", "rewards"):
        a = g[key][()]
        a[-1] -= np.float32(0.05)
        g[key][...] = a
    g.attrs["score"] = float(g["r_gt"][-1])


EP = "episodes/000000"
#: h5py edits: none may pass ``validate`` (open, verify, the task checks)
EDITS = {
    "action set to 100": _set(f"{EP}/actions", (0, 0), 100.0),
    "action nudged inside the box": _set(f"{EP}/actions", (0, 1), 0.001),
    "goal moved by 1 m": _shift_goal,
    "NaN observation": _set(f"{EP}/observations", (1, 2), np.nan),
    "observation changed": _set(f"{EP}/observations", (0, 0), 0.5),
    "r_gt changed": _set(f"{EP}/r_gt", -1, 0.5),
    "reward changed": _set(f"{EP}/rewards", 0, 0.25),
    "points moved": _set(f"{EP}/points", (-1, 0, 2), 0.1),
    "point_steps changed": _set(f"{EP}/point_steps", 1, 2),
    "end effector changed": _set(f"{EP}/end_effector", (0, 2), 0.3),
    "height pixel changed": _set(f"{EP}/height", (1, 3, 3), 0.01),
    "rgb pixel changed": _set(f"{EP}/rgb", (1, 3, 3, 0), 7),
    "score attribute": _attr(EP, "score", 0.999),
    "seed attribute": _attr(EP, "seed", 12345),
    "policy attribute": _attr(EP, "policy", "random"),
    "length attribute": _attr(EP, "length", 3),
    "episode digest": _attr(EP, ff.DIGEST_ATTR, "sha256:" + "0" * 64),
    "goal provenance": _attr("goal", "provenance", "{}"),
    "spec attribute": lambda f: f.attrs.__setitem__(
        "spec", f.attrs["spec"].replace('"horizon": 2', '"horizon": 3')),
    "generator attribute": _attr("", "generator", '{"task": "fold_cloth1"}'),
    "precision attribute": _attr("", "precision", "float64"),
    "format version 4": _attr("", "format_version", 4),
    "last episode deleted": lambda f: f.__delitem__("episodes/000001"),
    "dataset deleted": lambda f: f.__delitem__(f"{EP}/end_effector"),
    "dataset added to an episode": lambda f: f[EP].create_dataset("extra", data=[1.0]),
    "dataset added at the root": lambda f: f.create_dataset("extra", data=[1.0]),
    "group added to /episodes": lambda f: f["episodes"].create_group("extra"),
    "attribute added to a dataset": _attr(f"{EP}/actions", "note", "hello"),
    "actions rewritten unchecksummed": _recreate(f"{EP}/actions", lambda a: a),
    "observations as float64": _recreate(f"{EP}/observations", lambda a: a.astype("f8")),
    "actions reversed": _recreate(f"{EP}/actions", lambda a: a[::-1].copy()),
    "episodes swapped": _swap_episodes,
    "r_gt, rewards and score changed together": _rgt_consistent,
}
#: the edits of the issue (and a few more) again with every digest and checksum
#: recomputed: the value checks and the task checks must still refuse them
FORGED = {
    "action set to 100": "outside the task's action box",
    "goal moved by 1 m": "not the task's goal",
    "NaN observation": "contains NaN or inf",
    "r_gt changed": "rewards differ from r_gt",
    "r_gt, rewards and score changed together": "the stored object points give",
    "points moved": "the stored object points give",
    "point_steps changed": "point_steps must increase",
    "score attribute": "is not the last r_gt",
}


@pytest.mark.parametrize("forged", [False, True], ids=["edited", "forged"])
def test_h5py_edits_are_refused_by_validate(tiny, tiny_env, tmp_path, forged):
    refused, accepted = {}, []
    for name, edit in EDITS.items():
        if forged and name not in FORGED:
            continue
        path = tmp_path / "edit.h5"
        shutil.copyfile(tiny, path)
        with h5py.File(path, "a") as f:
            edit(f)
        if forged:
            reseal(path)
        try:
            content(path, tiny_env)
        except dax_data.DataFileError as err:
            assert str(err).startswith(f"{path}: "), err
            refused[name] = str(err)
            continue
        accepted.append(name)
    assert not accepted, f"edits accepted: {accepted}"
    if forged:
        for name, needle in FORGED.items():
            assert needle in refused[name], (name, refused[name])


def test_issue_edits_are_refused_by_load_and_the_goal_names_the_file(tiny, tmp_path):
    """What the probe found: an edited file loaded without complaint, and a corrupted goal
    read through the library raised a bare OSError."""
    for name in ("action set to 100", "goal moved by 1 m", "NaN observation",
                 "r_gt changed"):
        path = tmp_path / "load.h5"
        shutil.copyfile(tiny, path)
        with h5py.File(path, "a") as f:
            EDITS[name](f)
        with pytest.raises(dax_data.DataFileError, match="content digest mismatch"):
            dax_data.load(path)
        dax_data.load(path, verify=False)  # opted out: read as stored
    path = tmp_path / "goal.h5"
    shutil.copyfile(tiny, path)
    with h5py.File(path, "r") as f:
        info = f["goal"].id.get_chunk_info(0)
    raw = bytearray(path.read_bytes())
    raw[info.byte_offset + info.size // 2] ^= 0x10
    path.write_bytes(bytes(raw))
    with dax_data.open_file(path) as f, pytest.raises(dax_data.DataFileError,
                                                      match=f"{path}: /goal unreadable"):
        f.goal  # noqa: B018 - reading it is the test


def test_version_4_files_open_with_a_warning_that_edits_go_unnoticed(tiny, tmp_path,
                                                                     capsys):
    old = tmp_path / "v4.h5"
    shutil.copyfile(tiny, old)
    with h5py.File(old, "a") as f:
        for obj in [f["goal"], *f["episodes"].values(),
                    *(ds for g in f["episodes"].values() for ds in g.values())]:
            del obj.attrs[ff.DIGEST_ATTR]
        del f.attrs["precision"]
        f.attrs["format_version"] = 4
        ff.seal(f)
    with pytest.warns(ff.UncheckedDataWarning, match="format version 4: no dataset carries "
                                                     "a content digest"):
        f = dax_data.open_file(old)
    with f:
        f.verify()
    assert cli.main(["validate", str(old)]) == 0
    out = capsys.readouterr()
    assert "ok (2 episodes, format version 4)" in out.out
    assert out.err.startswith("dax-data: warning: ") and "content digest" in out.err


# ----------------------------------------------------------------------------- links, locks

def test_a_symlinked_out_is_written_through_to_its_target(tiny, tmp_path):
    target = tmp_path / "real" / "target.h5"
    target.parent.mkdir()
    shutil.copyfile(tiny, target)
    link = tmp_path / "link.h5"
    link.symlink_to(target)
    assert cli.main([str(a) for a in generate_args(link, 3)]) == 0
    assert link.is_symlink() and os.readlink(link) == str(target), "the link was replaced"
    with dax_data.open_file(target) as f:
        assert len(f) == 3
    assert sorted(p.name for p in target.parent.iterdir()) == ["target.h5"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link.h5", "real"]


@pytest.mark.parametrize("held", ["target", "link"])
def test_a_link_and_its_target_share_one_lock(tiny, tmp_path, capsys, held):
    """Both orders of the race: whichever name the first writer used, a second writer
    using the other name is refused, and the file is untouched."""
    target = tmp_path / "target.h5"
    shutil.copyfile(tiny, target)
    link = tmp_path / "link.h5"
    link.symlink_to(target)
    first, second = (target, link) if held == "target" else (link, target)
    before = target.read_bytes()
    with io.exclusive(first, program="the first writer"):
        one_line_error(capsys, generate_args(second, 3), str(second),
                       "another process is writing it", "the first writer")
    assert target.read_bytes() == before and link.is_symlink()


def test_a_symlink_loop_is_one_line(tmp_path, capsys):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    a.symlink_to(b)
    b.symlink_to(a)
    one_line_error(capsys, generate_args(a), "symbolic links form a loop")


def _holder(path):
    """A process holding ``path``'s lock (started, lock taken)."""
    code = ("import sys, time\nfrom dax_tasks import io\n"
            "with io.exclusive(sys.argv[1], program='the stopped writer'):\n"
            "    print('held', flush=True)\n    time.sleep(120)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(path)], stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_waiting_for_a_stopped_holder_names_it_and_gives_up(tiny, tmp_path, capsys):
    path = tmp_path / "held.h5"
    shutil.copyfile(tiny, path)
    proc = _holder(path)
    try:
        os.kill(proc.pid, signal.SIGSTOP)
        line = one_line_error(capsys, [*generate_args(path, 3), "--lock-timeout", "0.5"],
                              str(path), "another process is writing it",
                              f"pid {proc.pid} (stopped)", "waited 0.5 s")
        assert "the stopped writer" in line
    finally:
        proc.kill()
        proc.wait()


def test_the_waiting_notice_is_printed_once_before_the_error(tiny, tmp_path, capsys):
    path = tmp_path / "held.h5"
    shutil.copyfile(tiny, path)
    with io.exclusive(path, program="the first writer"):
        code = cli.main([str(a) for a in [*generate_args(path, 3), "--lock-timeout", "0.3"]])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 2, err
    assert err[0].startswith(f"dax-data: {path}: waiting for another process") and \
        "the first writer" in err[0] and "up to 0.3 s" in err[0], err
    assert err[1].startswith(f"dax-data: error: {path}: another process is writing it"), err


def test_a_standard_set_waited_for_gives_up_after_the_timeout(tmp_path, capsys):
    """``standard`` (``ensure_standard``) waited forever, silently, for a stopped holder:
    it now says who holds the set and gives up after ``lock_wait`` seconds."""
    from dax_data.record import make_task, parse_overrides
    from dax_data.standard import ensure_standard, standard_path

    overrides = parse_overrides(TASK, TINY)
    path = standard_path(make_task(TASK, overrides), "ild", tmp_path)
    with io.exclusive(path, program="the other standard"), \
            pytest.raises(io.FileLockedError, match=r"the other standard.*waited 0.3 s"):
        ensure_standard(TASK, "ild", tmp_path, overrides=overrides, lock_wait=0.3)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "waiting for another process" in err[0] and \
        "the other standard" in err[0], err
    assert not path.exists()


# ----------------------------------------------------------------------------- sizes

@pytest.mark.parametrize("argv, needles", [
    (["--override", "scene.n=100000"], ["up to 10000000000 object points", "GiB"]),
    (["--override", "scene.dt=1e-300"], ["scene.dt = 1e-300", "not representable"]),
    (["--override", "scene.dt=1e-12"], ["scene.dt = 1e-12 s is below 1e-06 s"]),
    (["--override", "substeps=3000000000"], ["substeps = 3000000000 does not fit"]),
    (["--obs", "rgb", "--image-size", "1000000"], ["1000000 x 1000000 pictures", "GiB"]),
])
def test_sizes_the_machine_cannot_run_are_refused_before_any_file(tmp_path, capsys, argv,
                                                                  needles):
    out = tmp_path / "big.h5"
    one_line_error(capsys, ["generate", "--task", TASK, "--episodes", 1, "--out", out,
                            "--no-progress", *argv], *needles)
    assert os.listdir(tmp_path) == [], os.listdir(tmp_path)


def test_too_many_seeds_for_one_batch_are_refused(capsys):
    one_line_error(capsys, ["score", "--task", TASK, "--seeds", 10**9, *TINY_ARGS],
                   "1000000000 environment(s)", "GiB")


def test_a_first_episode_that_fails_leaves_no_file(tmp_path, capsys, monkeypatch):
    from dax_data import record

    def fail(self, seed):
        raise RuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate")

    monkeypatch.setattr(record.Recorder, "episode", fail)
    out = tmp_path / "oom.h5"
    one_line_error(capsys, generate_args(out), "out of memory", "RESOURCE_EXHAUSTED")
    assert os.listdir(tmp_path) == [], os.listdir(tmp_path)


# ----------------------------------------------------------------------------- precision

def test_precision_is_recorded_and_a_resume_in_float64_is_refused(tiny, tmp_path):
    with dax_data.open_file(tiny) as f:
        assert f.meta["precision"] == "float32"
    path = tmp_path / "f32.h5"
    shutil.copyfile(tiny, path)
    before = path.read_bytes()
    env = dict(os.environ, JAX_ENABLE_X64="1")
    proc = subprocess.run([sys.executable, "-m", "dax_data",
                           *map(str, generate_args(path, 3))], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "its episodes ran in float32, this process runs in float64" \
        in lines[0], lines
    assert path.read_bytes() == before
