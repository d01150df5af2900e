"""Policy parameter files: one msgpack file per policy (Flax's serialisation, never
pickle), written atomically, with a SHA-256 checksum over the metadata and every array.

Layout: ``{"format": "dax-policy", "version": 1, "meta": <JSON text>, "params": <nested
dict of arrays>, "sha256": <hex>}``. ``<path>.json`` beside it repeats the metadata for
people; loading never reads it. A truncated, corrupted or foreign file, one whose
parameters are not arrays of finite real numbers (a forged file with a recomputed
checksum and NaN weights included), or one made for something other than what the caller
expects (``expect``), is refused with a one-line ``ValueError`` that starts with the path.
The shapes a method's network expects are checked by its loader
(:func:`dax_algos.bench.trained.load_trained`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
from flax import serialization

from dax_tasks.io import atomic_write

FORMAT = "dax-policy"
VERSION = 1


def _leaves(tree, prefix=""):
    for key in sorted(tree):
        value = tree[key]
        path = f"{prefix}/{key}"
        if isinstance(value, dict):
            yield from _leaves(value, path)
        else:
            yield path, value


def _digest(meta_text: str, params: dict) -> str:
    h = hashlib.sha256(meta_text.encode())
    for path, leaf in _leaves(params):
        a = np.ascontiguousarray(leaf)
        h.update(f"{path}|{a.dtype.str}|{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _numpy_tree(tree, prefix=""):
    if not isinstance(tree, dict):
        raise ValueError(f"params{prefix or '/'} must be a dict of arrays, got "
                         f"{type(tree).__name__}")
    out = {}
    for key, value in tree.items():
        if not isinstance(key, str):
            raise ValueError(f"params{prefix}/{key!r}: keys must be strings")
        if isinstance(value, dict):
            out[key] = _numpy_tree(value, f"{prefix}/{key}")
        else:
            a = np.asarray(value)
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                raise ValueError(f"params{prefix}/{key} contains NaN or inf; refusing to save "
                                 f"a broken policy")
            out[key] = a
    return out


def save_policy(path, params: dict, meta: dict) -> Path:
    """Write ``params`` (nested dict, str keys, array leaves) and ``meta`` (JSON data)."""
    path = Path(path)
    try:
        meta_text = json.dumps(meta, sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: policy metadata is not strict JSON ({err})") from None
    params = _numpy_tree(params)
    payload = {"format": FORMAT, "version": VERSION, "meta": meta_text, "params": params,
               "sha256": _digest(meta_text, params)}
    data = serialization.msgpack_serialize(payload)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, data)
    atomic_write(path.with_name(path.name + ".json"),
                 json.dumps(meta, indent=2, sort_keys=True) + "\n")
    return path


def _read(path) -> tuple[dict, dict]:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such policy file")
    raw = path.read_bytes()
    try:
        payload = serialization.msgpack_restore(raw)
    except Exception as err:  # noqa: BLE001 - msgpack raises several kinds
        raise ValueError(f"{path}: not a readable policy file (truncated or corrupted: "
                         f"{type(err).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path}: not a {FORMAT} file")
    if payload.get("version") != VERSION:
        raise ValueError(f"{path}: unsupported {FORMAT} version {payload.get('version')!r} "
                         f"(this reader knows {VERSION})")
    meta_text, params = payload.get("meta"), payload.get("params")
    if not isinstance(meta_text, str) or not isinstance(params, dict):
        raise ValueError(f"{path}: malformed {FORMAT} file")
    try:
        digest = _digest(meta_text, params)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{path}: malformed {FORMAT} file ({err})") from None
    if digest != payload.get("sha256"):
        raise ValueError(f"{path}: checksum mismatch: the file is corrupted")
    _check_leaves(path, params)
    try:
        meta = json.loads(meta_text)
    except ValueError:
        raise ValueError(f"{path}: malformed {FORMAT} file (its metadata is not JSON)"
                         ) from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: malformed {FORMAT} file (its metadata is not an object)")
    return meta, params


def _check_leaves(path, params: dict) -> None:
    """Every leaf of ``params`` an array of real numbers, the float ones finite
    (``ValueError`` naming the file and the leaf)."""
    for where, leaf in _leaves(params):
        a = np.asarray(leaf) if isinstance(leaf, (np.ndarray, np.generic)) else None
        if a is None or a.dtype.kind not in "fiu":
            raise ValueError(f"{path}: parameter {where} is not an array of real numbers "
                             f"({type(leaf).__name__}{'' if a is None else ' ' + str(a.dtype)})")
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise ValueError(f"{path}: parameter {where} contains NaN or inf; refusing to "
                             f"load a broken policy")


def read_meta(path) -> dict:
    """The metadata of a policy file (after the same checks as :func:`load_policy`)."""
    return _read(path)[0]


def _norm(v) -> str:
    return json.dumps(v, sort_keys=True)


def _config_diff(saved: dict, want: dict) -> str:
    parts = []
    for k in sorted(set(saved) | set(want)):
        if _norm(saved.get(k)) != _norm(want.get(k)):
            parts.append(f"{k} (saved {saved.get(k)!r}, expected {want.get(k)!r})")
    return ", ".join(parts[:3])


def load_policy(path, expect: dict | None = None) -> tuple[dict, dict]:
    """``(params, meta)``; every key of ``expect`` must equal the saved metadata's."""
    meta, params = _read(path)
    for key, want in (expect or {}).items():
        if key not in meta:
            raise ValueError(f"{path}: policy metadata has no {key!r} (expected {want!r})")
        if _norm(meta[key]) != _norm(want):
            if key == "config" and isinstance(want, dict) and isinstance(meta[key], dict):
                raise ValueError(f"{path}: config differs in {_config_diff(meta[key], want)}")
            raise ValueError(f"{path}: policy was trained for {key}={meta[key]!r}, "
                             f"expected {want!r}")
    return params, meta
