"""Trained policies on disk: what a learning run keeps so that its policy can be
re-evaluated, rendered or fine-tuned without retraining.

A policy file (:mod:`dax_algos.bench.policy_io`: one checksummed msgpack file, written
atomically, never pickle) holds the policy network's parameters and its observation
normaliser, and beside them the method, its full config, the task and the task spec's
fingerprint. :func:`load_trained` refuses a file made for another task, another spec
(resolution, horizon, ...) or, when a config is given, another config, naming what
differs.

    env = dax_tasks.make("fold_cloth1")
    act, policy = load_trained("results/policies/fold_cloth1/ppo/seed0.msgpack", env, "ppo")
    z = act(policy, dax_algos.mlp_policy.features(obs, state.t, env.horizon))  # normalised
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from .. import __version__, nets, registry
from ..learner import Policy
from ..method import LearnerMethod
from ..mlp_policy import ObsNorm, feature_dim
from . import policy_io


def _config_json(config) -> dict:
    def conv(v):
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        return v

    return {f.name: conv(getattr(config, f.name)) for f in dataclasses.fields(config)}


def _config_from_json(cls, data: dict):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in data.items()
              if k in fields}
    return cls(**kwargs)


def policy_meta(method: str, env, config) -> dict:
    """What a policy file records beside the arrays: the method, the task and its spec's
    fingerprint, the full config, the input and action sizes and this package's version."""
    return {"method": method, "task": env.spec.name,
            "task_fingerprint": env.spec.fingerprint(), "config": _config_json(config),
            "obs_dim": feature_dim(env), "action_dim": env.spec.action_dim,
            "dax_algos_version": __version__}


def trained_record(method: str, env, config, policy: Policy, **extra_meta) -> tuple:
    """``(tree, meta)``: what :func:`save_trained` writes for ``policy``, as plain data
    (NumPy arrays, JSON), so that a process without the env can write it
    (``policy_io.save_policy(path, tree, meta)``)."""
    tree = {"policy": nets.to_tree(policy.params)}
    if policy.obs_norm is not None:
        tree["obs_norm"] = {"mean": np.asarray(policy.obs_norm.mean),
                            "var": np.asarray(policy.obs_norm.var),
                            "count": np.asarray(policy.obs_norm.count)}
    return tree, {**policy_meta(method, env, config), **extra_meta}


def save_trained(path, method: str, env, config, policy: Policy, **extra_meta) -> Path:
    """Write ``policy`` (a :class:`dax_algos.learner.Policy` of one seed, NumPy or JAX
    arrays)."""
    return policy_io.save_policy(path, *trained_record(method, env, config, policy,
                                                       **extra_meta))


def load_trained(path, env, method: str | None = None, config=None):
    """``(act, policy)`` of a saved policy for ``env``: ``act(policy, feats) -> z`` the
    deterministic normalised action. Refused (``ValueError`` naming the file and the
    difference) when the file was made for another task or task spec, another method (if
    ``method`` is given) or another config (if ``config`` is given), or when its
    parameters are not finite (:func:`policy_io.load_policy`) or not shaped as the
    method's network for ``env`` and the config expects (the observation normaliser's
    ``mean`` and ``var`` of the policy's ``feature_dim(env)`` entries, ``var >= 0`` and a
    positive ``count``), before anything uses them."""
    meta = policy_io.read_meta(path)
    method = method or meta.get("method")
    m = _learner_method(path, method)
    expect = {"task": env.spec.name, "task_fingerprint": env.spec.fingerprint(),
              "method": method}
    if config is not None:
        expect["config"] = _config_json(config)
    tree, meta = policy_io.load_policy(path, expect)
    try:
        config = config or _config_from_json(m.config_cls, meta["config"])
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"{path}: its config does not build a {method} config ({err})"
                         ) from None
    if not isinstance(tree.get("policy"), dict):
        raise ValueError(f"{path}: holds no policy parameters")
    try:
        params = m.learner.network(env, config).from_tree(tree["policy"])
    except ValueError as err:
        raise ValueError(f"{path}: {err} (for {method} on {env.spec.name} with this "
                         f"config)") from None
    on = tree.get("obs_norm")
    norm = None if on is None else _obs_norm(path, on, feature_dim(env))
    return m.learner.make_act(env, config), Policy(params, norm)


def _obs_norm(path, on, dim: int) -> ObsNorm:
    """The observation normaliser stored as ``on`` (``mean`` and ``var`` of ``dim``
    entries, ``var >= 0``, a positive scalar ``count``), checked."""
    if not isinstance(on, dict) or set(on) != {"mean", "var", "count"}:
        raise ValueError(f"{path}: obs_norm must hold mean, var and count")
    shapes = {"mean": (dim,), "var": (dim,), "count": ()}
    arrays = {k: np.asarray(on[k]) for k in shapes}
    for k, shape in shapes.items():
        if arrays[k].shape != shape:
            raise ValueError(f"{path}: obs_norm/{k} has shape {arrays[k].shape}, expected "
                             f"{shape} (the policy's {dim} input features)")
    if np.any(arrays["var"] < 0) or not arrays["count"] > 0:
        raise ValueError(f"{path}: obs_norm has a negative variance or a count <= 0")
    return ObsNorm(*(jnp.asarray(arrays[k]) for k in ("mean", "var", "count")))


def _learner_method(path, method: str) -> LearnerMethod:
    m = registry.get(method)
    if not isinstance(m, LearnerMethod):
        raise ValueError(f"{path}: method {method!r} is not a learning method")
    return m


def saved_config(path, method: str):
    """The ``method`` config the policy file ``path`` was trained with (its metadata's;
    ``ValueError`` naming the file if ``method`` does not learn)."""
    m = _learner_method(path, method)
    return _config_from_json(m.config_cls, policy_io.read_meta(path)["config"])


def evaluate_trained(path, env, method: str, seed: int) -> dict:
    """Evaluate the policy file ``path`` of ``method`` on ``env`` as the runner evaluated it
    for ``seed`` (the same key, ``config.n_eval`` rollouts, one program per seed), one score
    per rollout: ``{task, method, seed, n_rollouts, mean, se, min, max, finite, scores}``."""
    task = env.spec.name
    m = _learner_method(path, method)
    config = saved_config(path, method)
    act, policy = load_trained(path, env, method, config)
    evaluate = m.learner.make_evaluate(env, config, act, per_rollout=True)
    key = jax.random.fold_in(jax.random.PRNGKey(seed), 0)
    # not under vmap, as the runner evaluates (one seed at a time): the same program shape,
    # so the same round-off (an argmax policy's pick can flip on it)
    out = jax.device_get(jax.jit(evaluate)(policy, key, env.default_params))
    scores = np.asarray(out.score, np.float64)
    n = scores.size
    return dict(task=task, method=method, seed=seed, n_rollouts=n,
                mean=float(scores.mean()),
                se=float(scores.std(ddof=1) / math.sqrt(n)) if n > 1 else float("nan"),
                min=float(scores.min()), max=float(scores.max()),
                finite=bool(np.all(out.finite)), scores=[round(float(x), 5) for x in scores])
