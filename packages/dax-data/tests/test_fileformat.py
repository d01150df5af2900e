"""The HDF5 demonstration format: exact round trips, schema checks, refusals (in-process)."""

import json

import h5py
import jax
import numpy as np
import pytest

import dax_data
from dax_data import fileformat as ff
from dax_data.record import Recorder, make_task


@pytest.fixture(scope="module")
def cloth(tmp_path_factory):
    """fold_cloth1 at its default resolution, 2 expert episodes from seed 3."""
    path = tmp_path_factory.mktemp("ff") / "fold.h5"
    out = dax_data.generate("fold_cloth1", 2, 3, path, progress=False)
    return path, out


def test_generated_episodes_equal_a_fresh_recording_exactly(cloth):
    path, _ = cloth
    recorder = Recorder(make_task("fold_cloth1"), "expert", 1)
    meta, episodes = dax_data.load(path)
    assert meta["task"] == "fold_cloth1" and meta["format_version"] == ff.FORMAT_VERSION
    assert [e.seed for e in episodes] == [3, 4], f"got seeds {[e.seed for e in episodes]}"
    for ep in episodes:
        fresh = recorder.episode(ep.seed)
        for key, value in fresh.items():
            got = getattr(ep, key)
            assert got.dtype == np.dtype(ff.EPISODE_DATASETS[key][0])
            np.testing.assert_array_equal(got, value, err_msg=f"{key} of seed {ep.seed}")
        assert ep.score == pytest.approx(float(fresh["r_gt"][-1]), abs=0)


def test_file_records_spec_versions_units_and_goal(cloth):
    path, _ = cloth
    with dax_data.open_file(path) as f:
        meta = f.meta
        assert meta["spec"]["scene_type"] == "ClothScene" and meta["spec"]["scene"]["n"] == 11
        assert "dax_tasks" not in json.dumps(meta["spec"]), "a module path in the spec"
        assert meta["fingerprint"] == make_task("fold_cloth1").spec.fingerprint()
        assert meta["params"]["lam"] == 10.0 and meta["params"]["aux_weight"] == 0.0
        assert meta["params"]["physics"]["stretch"] == 10.0
        assert ff.spec_from_meta(meta) == make_task("fold_cloth1").spec
        assert {"dax-data", "dax-tasks", "dax-physics", "jax", "h5py"} <= set(meta["versions"])
        assert meta["units"]["points"] == "m" and "dt" in meta["scene_doc"]
        assert meta["generator"] == {"task": "fold_cloth1", "seed": 3, "policy": "expert",
                                     "point_stride": 1, "overrides": {}, "obs": ["state"],
                                     "image_size": 64, "episodes": 2}
        assert meta["images"] == {"modes": []} and f.image_modes == ()
        task = make_task("fold_cloth1")
        np.testing.assert_array_equal(f.goal, task.goal)
        ep = f.episode(1, as_jax=True)
        assert isinstance(ep.actions, jax.Array) and ep.actions.shape == (3, 6)
        f.verify()


def test_datasets_are_chunked_compressed_and_checksummed(cloth):
    with h5py.File(cloth[0], "r") as f:
        ds = f["episodes/000000/observations"]
        assert ds.chunks is not None and ds.compression == "gzip" and ds.fletcher32


def test_point_stride_keeps_every_kth_frame_and_the_last(tmp_path):
    rec = Recorder(make_task("fold_cloth1"), "random", 2)
    arrays = rec.episode(0)
    assert arrays["point_steps"].tolist() == [0, 2, 3]
    assert arrays["points"].shape == (3, 121, 3)
    # the last stored frame is the final state the last observation shows
    np.testing.assert_array_equal(arrays["points"][-1].reshape(-1),
                                  arrays["observations"][-1][:-3])


def _rewrite_attr(path, key, value):
    with h5py.File(path, "a") as f:
        f.attrs[key] = value


def test_newer_format_version_is_refused(cloth, tmp_path):
    path = tmp_path / "newer.h5"
    path.write_bytes(cloth[0].read_bytes())
    _rewrite_attr(path, "format_version", ff.FORMAT_VERSION + 1)
    with pytest.raises(dax_data.DataFileError, match="newer than this dax-data reads"):
        dax_data.open_file(path)


def test_schema_violations_are_named(cloth, tmp_path):
    path = tmp_path / "bad.h5"
    path.write_bytes(cloth[0].read_bytes())
    with h5py.File(path, "a") as f:
        del f["episodes/000001/rewards"]
        f["episodes/000001"].create_dataset("rewards", data=np.zeros(5, np.float32))
    with pytest.raises(dax_data.DataFileError, match=r"episode 1: dataset 'rewards' has shape"):
        dax_data.open_file(path)
    _rewrite_attr(path, "format", "something-else")
    with pytest.raises(dax_data.DataFileError, match="not a dax-data demonstration file"):
        dax_data.open_file(path)


def test_truncated_and_foreign_files_are_refused(cloth, tmp_path):
    data = cloth[0].read_bytes()
    trunc = tmp_path / "trunc.h5"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(dax_data.DataFileError, match="truncated"):
        dax_data.open_file(trunc)
    text = tmp_path / "text.h5"
    text.write_text("hello")
    with pytest.raises(dax_data.DataFileError, match="not a readable HDF5 file"):
        dax_data.open_file(text)


def test_corrupted_chunk_is_detected_by_verify(cloth, tmp_path):
    path = tmp_path / "flip.h5"
    path.write_bytes(cloth[0].read_bytes())
    with h5py.File(path, "r") as f:
        info = f["episodes/000001/points"].id.get_chunk_info(0)
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(b"\x00\xff" * 8)
    with dax_data.open_file(path) as f, pytest.raises(dax_data.DataFileError,
                                                      match="episode 1: data unreadable"):
        f.verify()


def test_params_of_an_mpm_task_are_strict_json():
    from dax_data.record import make_task

    meta = ff.params_to_json(make_task("push_rope").default_params)
    text = json.dumps(meta, allow_nan=False)  # raises on a bare Infinity / NaN
    assert json.loads(text)["physics"]["yield_stress"] == ["inf"]
    assert json.loads(text)["physics"]["friction"] == [0.5, pytest.approx(0.3)]


def test_nothing_is_pickled(cloth):
    with h5py.File(cloth[0], "r") as f:
        def check(name, obj):
            if isinstance(obj, h5py.Dataset):
                assert obj.dtype.kind in "fiu", f"{name} has dtype {obj.dtype}"
            for key, value in obj.attrs.items():
                assert isinstance(value, (str, bytes, int, float, np.number)), (name, key)
        check("/", f)
        f.visititems(check)
        json.loads(f.attrs["spec"])


def test_generate_with_more_episodes_extends_the_file_keeping_earlier_ones(tmp_path):
    path = tmp_path / "grow.h5"
    first = dax_data.generate("fold_cloth1", 1, 7, path, policy="random", progress=False)
    assert first["recorded_now"] == 1
    before = dax_data.load(path)[1][0]
    second = dax_data.generate("fold_cloth1", 2, 7, path, policy="random", progress=False)
    assert (second["resumed_from"], second["recorded_now"]) == (1, 1), second
    meta, episodes = dax_data.load(path)
    assert meta["generator"]["episodes"] == 2 and [e.seed for e in episodes] == [7, 8]
    for key in ff.EPISODE_DATASETS:
        np.testing.assert_array_equal(getattr(episodes[0], key), getattr(before, key))
    again = dax_data.generate("fold_cloth1", 2, 7, path, policy="random", progress=False)
    assert again["recorded_now"] == 0
    with pytest.raises(dax_data.DataFileError, match="already holds 2 episodes"):
        dax_data.generate("fold_cloth1", 1, 7, path, policy="random", progress=False)


def _as_version_1(path):
    """Rewrite a file's header the way format version 1 wrote it: the spec with lam and
    aux_reward and the scene class's module path (and a scene field that became a
    param), no params attribute."""
    with h5py.File(path, "a") as f:
        spec = json.loads(f.attrs["spec"])
        spec.pop("scene_type")
        spec.update(lam=10.0, aux_reward=False, scene_class="dax_tasks.tasks._cloth.ClothScene")
        spec["scene"]["stretch"] = 10.0
        f.attrs["spec"] = json.dumps(spec)
        f.attrs["format_version"] = 1
        del f.attrs["params"]


def test_version_1_files_are_read_but_not_extended(cloth, tmp_path):
    path = tmp_path / "v1.h5"
    path.write_bytes(cloth[0].read_bytes())
    _as_version_1(path)
    with dax_data.open_file(path) as f:
        assert f.meta["format_version"] == 1 and len(f) == 2
        assert ff.spec_from_meta(f.meta) == make_task("fold_cloth1").spec
        f.verify()
    with pytest.raises(dax_data.DataFileError, match="format version 1"):
        dax_data.generate("fold_cloth1", 3, 3, path, progress=False)
    assert len(dax_data.open_file(path)) == 2, "the refused run changed the file"
    with h5py.File(path, "a") as f:
        f.attrs["format_version"] = 2  # a version 2 file must have params
    with pytest.raises(dax_data.DataFileError, match="missing file attribute 'params'"):
        dax_data.open_file(path)


# ----------------------------------------------------------------------------- pictures


@pytest.fixture(scope="module")
def pictures(tmp_path_factory):
    """fold_cloth1, 2 expert episodes from seed 3 with height maps and RGB pictures."""
    path = tmp_path_factory.mktemp("img") / "img.h5"
    dax_data.generate("fold_cloth1", 2, 3, path, progress=False, obs="state,height,rgb",
                      image_size=32)
    return path


def test_pictures_are_stored_per_step_as_the_observation_wrapper_renders_them(pictures):
    from dax_tasks.core.wrappers import ObservationMode, rgb_as_float

    env = make_task("fold_cloth1")
    meta, episodes = dax_data.load(pictures, as_jax=True)
    assert meta["format_version"] == ff.FORMAT_VERSION == 5
    assert meta["images"]["modes"] == ["height", "rgb"] and meta["images"]["size"] == 32
    ep = episodes[1]
    assert isinstance(ep.rgb, jax.Array) and ep.rgb.dtype == np.uint8
    assert ep.height.shape == (4, 32, 32) and ep.rgb.shape == (4, 32, 32, 3)
    rgbd = ObservationMode(env, "rgbd", 32)
    assert meta["images"]["window"] == list(rgbd.camera.window)
    obs, state = jax.jit(rgbd.reset)(jax.random.PRNGKey(4))  # episode 1 is seed 4
    # equal bits on CPU; a GPU may round the writer's and this program's renders 1 ulp
    # apart (as it does test_render's jitted and eager goal pictures), far below 1/255
    np.testing.assert_allclose(np.asarray(ep.height[0]), np.asarray(obs[..., 3]), rtol=0,
                               atol=1e-6)
    np.testing.assert_allclose(rgb_as_float(ep.rgb[0]), obs[..., :3], rtol=0, atol=1e-6)
    _, state, _, _, _ = jax.jit(rgbd.step)(state, ep.actions[0])
    assert not np.array_equal(np.asarray(ep.height[1]), np.asarray(ep.height[0]))
    with h5py.File(pictures, "r") as f:
        ds = f["episodes/000000/rgb"]
        assert ds.chunks == (1, 32, 32, 3) and ds.fletcher32 and ds.compression == "gzip"


def test_corrupted_picture_is_detected_and_missing_pictures_are_named(pictures, tmp_path):
    path = tmp_path / "flip.h5"
    path.write_bytes(pictures.read_bytes())
    with h5py.File(path, "r") as f:
        info = f["episodes/000001/rgb"].id.get_chunk_info(2)
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(b"\x00\xff" * 4)
    with dax_data.open_file(path) as f, pytest.raises(dax_data.DataFileError,
                                                      match="episode 1: data unreadable"):
        f.verify()
    path.write_bytes(pictures.read_bytes())
    with h5py.File(path, "a") as f:
        del f["episodes/000000/height"]
    with pytest.raises(dax_data.DataFileError, match="episode 0: missing dataset 'height'"):
        dax_data.open_file(path)


def test_resuming_with_other_observation_modes_is_refused(pictures, tmp_path):
    path = tmp_path / "grow.h5"
    path.write_bytes(pictures.read_bytes())
    with pytest.raises(dax_data.DataFileError, match='exists with obs=.*"height", "rgb"'):
        dax_data.generate("fold_cloth1", 3, 3, path, progress=False, obs="state,height",
                          image_size=32)
    with pytest.raises(ValueError, match="unknown observation mode"):
        dax_data.generate("fold_cloth1", 1, 0, tmp_path / "x.h5", obs="depth")


def test_standard_sets_are_made_once_and_named_by_what_made_them(tmp_path, monkeypatch):
    from dax_data.standard import STANDARD_SETS, ensure_standard, standard_path

    monkeypatch.setenv("DAX_CACHE_DIR", str(tmp_path / "cache"))
    path = ensure_standard("fold_cloth1", "ild", tmp_path)
    with dax_data.open_file(path) as f:
        assert len(f) == 1 and f.meta["generator"]["seed"] == STANDARD_SETS["ild"].seed
    stamp = path.stat().st_mtime_ns
    assert ensure_standard("fold_cloth1", "ild", tmp_path) == path
    assert path.stat().st_mtime_ns == stamp, "a complete set was recorded again"
    env = make_task("fold_cloth1")
    other = make_task("fold_cloth1", {"lam": 5.0})
    assert standard_path(other, "ild", tmp_path) != path, "other params, same file name"
    assert standard_path(env, "transporter", tmp_path, 32) != standard_path(
        env, "transporter", tmp_path, 64)
    with pytest.raises(ValueError, match="needs a macro-action task"):
        ensure_standard("pour_water", "transporter", tmp_path)
