"""Bad input and concurrent writers at dax-data's boundary (issue 17).

* one writer per file: a second ``generate`` of a file is refused at once (two real
  processes), and a refused run leaves the first one's temporary file alone;
* every dataset and every attribute is checksummed (since format version 4): a flipped bit
  anywhere, ``/goal`` and the pictures included, is caught by ``validate``; older files
  warn that their goal is unchecked;
* seeds beyond what a ``PRNGKey`` holds are refused before any file exists;
* overrides of the wrong type are refused in one line, before anything runs.
"""

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

import dax_data
from dax_data import cli
from dax_data import fileformat as ff
from dax_tasks import io

TASK = "fold_cloth1"  # cheap, with an expert
_SCRIPT = Path(sys.executable).with_name("dax-data")
CMD = [str(_SCRIPT)] if _SCRIPT.exists() else [sys.executable, "-m", "dax_data"]


def one_line_error(capsys, argv, *needles):
    """Run the CLI in-process; assert exit 2 with one line naming every needle."""
    code = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, f"expected exit 2, got {code}: {err}"
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, f"got stderr {err!r}"
    for needle in needles:
        assert needle in lines[0], f"expected {needle!r} in {lines[0]!r}"
    return lines[0]


# ----------------------------------------------------------------------------- checksums

@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """One fold_cloth1 expert episode with height maps and pictures (8 pixels)."""
    path = tmp_path_factory.mktemp("sums") / "small.h5"
    dax_data.generate(TASK, 1, 0, path, progress=False, obs="state,height,rgb", image_size=8)
    return path


def _datasets(path):
    names = []
    with h5py.File(path, "r") as f:
        f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
    return names


def _flip_a_bit(path, name):
    """Flip one bit in the middle of the stored bytes of dataset ``name``."""
    with h5py.File(path, "r") as f:
        ds = f[name]
        if ds.chunks is not None:
            info = ds.id.get_chunk_info(0)
            offset, size = info.byte_offset, info.size
        else:
            offset, size = ds.id.get_offset(), ds.id.get_storage_size()
    with open(path, "r+b") as fh:
        fh.seek(offset + size // 2)
        byte = fh.read(1)
        fh.seek(offset + size // 2)
        fh.write(bytes([byte[0] ^ 0x01]))  # the lowest bit: a value stays finite


def test_every_dataset_is_checksummed_and_a_flipped_bit_anywhere_is_caught(small, tmp_path,
                                                                          capsys):
    names = _datasets(small)
    assert "goal" in names and "episodes/000000/rgb" in names and \
        "episodes/000000/height" in names, names
    with dax_data.open_file(small) as f:
        assert f.meta["format_version"] == ff.FORMAT_VERSION == 5
        f.verify()
    missed = []
    for name in names:
        copy = tmp_path / "flip.h5"
        shutil.copyfile(small, copy)
        _flip_a_bit(copy, name)
        try:
            with dax_data.open_file(copy) as f:
                f.verify()
        except dax_data.DataFileError as err:
            assert str(copy) in str(err)
            continue
        missed.append(name)
    assert not missed, f"a flipped bit went unnoticed in {missed}"
    copy = tmp_path / "flip.h5"
    shutil.copyfile(small, copy)
    _flip_a_bit(copy, "goal")
    one_line_error(capsys, ["validate", copy], str(copy), "/goal: data unreadable")


def _attributes(path):
    out = []
    with h5py.File(path, "r") as f:
        names = [""]
        f.visit(names.append)
        for name in names:
            obj = f[name] if name else f
            out += [(name, key) for key in obj.attrs]
    return out


def _flipped(value):
    """``value`` with one bit flipped (a number's lowest, a text's middle character's)."""
    if isinstance(value, (bytes, str)):
        text = value.decode() if isinstance(value, bytes) else value
        i = len(text) // 2
        return text[:i] + chr(ord(text[i]) ^ 1) + text[i + 1:]
    if np.issubdtype(np.asarray(value).dtype, np.integer):
        return np.asarray(value) ^ 1
    bits = np.asarray(value, np.float64).view(np.int64) ^ 1
    return bits.view(np.float64)


def test_every_attribute_is_checksummed_a_changed_value_anywhere_is_caught(small, tmp_path):
    """Attribute values need not be covered by HDF5's own checksums (text lives in the global
    heap): the file's ``checksum`` attribute covers them all."""
    attributes = _attributes(small)
    assert ("", "spec") in attributes and ("goal", "provenance") in attributes and \
        ("episodes/000000", "score") in attributes, attributes
    missed = []
    for name, key in attributes:
        copy = tmp_path / "attr.h5"
        shutil.copyfile(small, copy)
        with h5py.File(copy, "a") as f:
            obj = f[name] if name else f
            obj.attrs[key] = _flipped(obj.attrs[key])
        try:
            with dax_data.open_file(copy) as f:
                f.verify()
        except dax_data.DataFileError:
            continue
        missed.append(f"/{name} {key}")
    assert not missed, f"a changed attribute went unnoticed: {missed}"
    # a bit flipped in the file's bytes, inside the spec's text
    copy = tmp_path / "raw.h5"
    shutil.copyfile(small, copy)
    raw = bytearray(copy.read_bytes())
    at = raw.find(b'"substeps"')
    assert at > 0 and raw.count(b'"substeps"') == 1
    raw[at + 3] ^= 0x01
    copy.write_bytes(bytes(raw))
    with pytest.raises(dax_data.DataFileError, match="metadata checksum mismatch"):
        dax_data.open_file(copy)


def _with_contiguous_goal(path, version=None):
    """Rewrite ``/goal`` without a checksum, as format versions 1 to 3 stored it."""
    with h5py.File(path, "a") as f:
        goal, prov = f["goal"][()], f["goal"].attrs["provenance"]
        del f["goal"]
        ds = f.create_dataset("goal", data=goal)
        ds.attrs["provenance"], ds.attrs["units"] = prov, "m"
        if version is not None:
            f.attrs["format_version"] = version
            del f.attrs["checksum"]
        else:
            ff.seal(f)  # only the goal's checksum is missing


def test_version_3_file_opens_with_a_warning_that_its_goal_is_unchecked(small, tmp_path,
                                                                        capsys):
    old = tmp_path / "v3.h5"
    shutil.copyfile(small, old)
    _with_contiguous_goal(old, version=3)
    with pytest.warns(ff.UncheckedDataWarning, match="v3.h5: format version 3: /goal and the "
                                                     "attributes carry no checksum"):
        f = dax_data.open_file(old)
    with f:
        f.verify()
    assert cli.main(["validate", str(old)]) == 0
    out = capsys.readouterr()
    assert "ok (1 episodes, format version 3)" in out.out
    assert out.err.startswith("dax-data: warning: ") and "goal is unchecked" in out.err, out.err
    # a version 4 file whose goal lost its checksum is refused
    bad = tmp_path / "v4.h5"
    shutil.copyfile(small, bad)
    _with_contiguous_goal(bad)
    with dax_data.open_file(bad) as f, pytest.raises(dax_data.DataFileError,
                                                     match="/goal carries no checksum"):
        f.verify()


# ----------------------------------------------------------------------------- seeds

@pytest.mark.parametrize("seed, episodes", [(4294967296, 1), (9223372036854775807, 1),
                                            (2**70, 1), (4294967295, 2)])
def test_seeds_beyond_32_bits_are_refused_before_any_file(tmp_path, capsys, seed, episodes):
    out = tmp_path / "seeds.h5"
    line = one_line_error(capsys, ["generate", "--task", TASK, "--episodes", episodes,
                                   "--seed", seed, "--out", out, "--no-progress"],
                          "outside 0..4294967295")
    assert str(seed) in line
    assert not out.exists() and os.listdir(tmp_path) == [], os.listdir(tmp_path)
    one_line_error(capsys, ["score", "--task", TASK, "--seeds", episodes, "--seed", seed],
                   "outside 0..4294967295")


def test_the_largest_seed_is_accepted():
    from dax_data.record import MAX_SEED, check_seeds

    assert check_seeds(MAX_SEED) == MAX_SEED == 2**32 - 1
    assert check_seeds(MAX_SEED - 4, 5) == MAX_SEED - 4
    with pytest.raises(ValueError, match="seed must be an integer"):
        check_seeds(True)


# ----------------------------------------------------------------------------- overrides

@pytest.mark.parametrize("override, message", [
    ("lam=abc", "lam must be a number, got str 'abc'"),
    ("scene.n=abc", "scene.n must be an integer, got str 'abc'"),
    ("scene.n=6.5", "scene.n must be an integer, got float 6.5"),
    ("action_low=5", "action_low must be a list of 6 entries"),
    ("horizon=true", "horizon must be an integer, got bool True"),
    ("scene.rotation_range=NaN", "scene.rotation_range must be a finite number"),
])
def test_overrides_of_the_wrong_type_are_one_line_errors(tmp_path, capsys, override, message):
    out = tmp_path / "o.h5"
    one_line_error(capsys, ["generate", "--task", TASK, "--episodes", 1, "--out", out,
                            "--override", override, "--no-progress"], message)
    assert not out.exists() and os.listdir(tmp_path) == []
    one_line_error(capsys, ["score", "--task", TASK, "--seeds", 1, "--override", override],
                   message)


# ----------------------------------------------------------------------------- one writer

def test_a_refused_writer_leaves_the_holders_temporary_file_alone(tmp_path, capsys):
    out = tmp_path / "held.h5"
    live = tmp_path / ".held.h5.abc123.tmp"  # what a running writer is filling
    live.write_bytes(b"episode in progress")
    with io.exclusive(out, program="the first writer"):
        line = one_line_error(capsys, ["generate", "--task", TASK, "--episodes", 2, "--out",
                                       out, "--no-progress"],
                              str(out), "another process is writing it", "the first writer",
                              f"pid {os.getpid()}")
    assert live.read_bytes() == b"episode in progress", line
    assert not out.exists()


def test_two_generate_processes_on_one_file_exactly_one_writes(tmp_path):
    env = dict(os.environ, DAX_CACHE_DIR=str(tmp_path / "cache"))
    out = tmp_path / "race.h5"
    args = [*CMD, "generate", "--task", TASK, "--episodes", "10", "--seed", "0", "--out",
            str(out), "--no-progress"]
    t0 = time.monotonic()
    procs = [subprocess.Popen(args, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for _ in range(2)]
    ends, results = {}, {}
    while len(ends) < 2:
        for p in procs:
            if p.pid not in ends and p.poll() is not None:
                ends[p.pid] = time.monotonic() - t0
        time.sleep(0.05)
    for p in procs:
        stdout, stderr = p.communicate(timeout=600)
        results[p.pid] = (p.returncode, stdout, stderr)
    codes = sorted(r[0] for r in results.values())
    assert codes == [0, 2], {pid: (r[0], r[2][-500:]) for pid, r in results.items()}
    (winner,) = [pid for pid, r in results.items() if r[0] == 0]
    (loser,) = [pid for pid, r in results.items() if r[0] == 2]
    err = results[loser][2].strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"dax-data: error: {out}: another process is "
                                               f"writing it (pid {winner} on "), err
    assert ends[loser] < ends[winner], f"the refused run took {ends[loser]:.1f} s, the " \
                                       f"writer {ends[winner]:.1f} s"
    print(f"writer {ends[winner]:.1f} s, refused run {ends[loser]:.1f} s")
    proc = subprocess.run([*CMD, "validate", str(out)], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0 and "ok (10 episodes, format version 5)" in proc.stdout, \
        proc.stdout + proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache", "race.h5"], \
        "a lock or temporary file was left behind"
    with dax_data.open_file(out) as f:
        assert [f.episode(k).seed for k in range(len(f))] == list(range(10))
        np.testing.assert_array_equal(f.episode(9).point_steps[-1], f.episode(9).length)
