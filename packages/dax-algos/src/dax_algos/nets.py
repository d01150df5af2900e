"""The learning methods' networks, in Flax NNX (the API Flax's documentation recommends
since Flax 0.10), used through its functional API so that a whole training run stays one
pure, jittable, vmappable function:

* a network is built once per shape (:class:`Network`), its *graph definition* kept, and
  its parameters are an ``nnx.State`` (a pytree) from :meth:`Network.init`, which works
  under ``jit`` and ``vmap`` (one initialisation per seed);
* :meth:`Network.apply` merges the definition with a state and calls the module; gradients
  (``jax.grad``) and optax updates act on the state like on any pytree;
* :func:`to_tree` / :meth:`Network.from_tree` convert a state to a plain nested dict with
  string keys (what :mod:`dax_algos.bench.policy_io` stores) and back.

Modules: :class:`MLP` (hidden layers with an activation, a linear output), and
:class:`GaussianPolicy` (an MLP for the mean of a diagonal Gaussian over normalised
actions, plus a state-independent log standard deviation).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
from flax import nnx

from .checks import check_choice

ACTIVATIONS: dict[str, Callable] = {"swish": nnx.swish, "tanh": jnp.tanh, "relu": nnx.relu,
                                    "elu": nnx.elu}


def _check_activation(name: str) -> Callable:
    check_choice("activation", name, ACTIVATIONS)
    return ACTIVATIONS[name]


class MLP(nnx.Module):
    """``in_dim -> hidden... -> out_dim``; the activation after every hidden layer,
    optionally LayerNorm before it (SHAC's networks use it); the last layer's weights are
    scaled by ``out_scale`` (a small first policy, as PPO implementations do)."""

    def __init__(self, in_dim: int, hidden: tuple, out_dim: int, activation: str,
                 rngs: nnx.Rngs, layer_norm: bool = False, out_scale: float = 1.0):
        sizes = (in_dim, *hidden, out_dim)
        self.act = _check_activation(activation)
        self.layers = nnx.List([nnx.Linear(a, b, rngs=rngs)
                                for a, b in zip(sizes[:-1], sizes[1:], strict=True)])
        self.norms = nnx.List([nnx.LayerNorm(h, rngs=rngs) for h in hidden]
                              if layer_norm else [])
        if out_scale != 1.0:
            last = self.layers[-1]
            last.kernel[...] = last.kernel[...] * out_scale

    def __call__(self, x):
        for i, layer in enumerate(self.layers[:-1]):
            x = layer(x)
            if len(self.norms):
                x = self.norms[i](x)
            x = self.act(x)
        return self.layers[-1](x)


class GaussianPolicy(nnx.Module):
    """``obs -> (mean, log_std)`` of a diagonal Gaussian over pre-squash actions; the
    executed normalised action is ``tanh`` of a sample (in [-1, 1])."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple, activation: str,
                 rngs: nnx.Rngs, init_log_std: float = -0.5, layer_norm: bool = False):
        self.mean = MLP(obs_dim, hidden, act_dim, activation, rngs, layer_norm=layer_norm,
                        out_scale=0.01)
        self.log_std = nnx.Param(jnp.full((act_dim,), init_log_std, jnp.float32))

    def __call__(self, obs):
        return self.mean(obs), jnp.broadcast_to(self.log_std[...], self.log_std[...].shape)


@dataclasses.dataclass(frozen=True)
class Network:
    """A network of one shape: ``make(rngs) -> nnx.Module`` builds it. ``init(key)`` gives
    a parameter state; ``apply(state, *args)`` calls the module. Hashable and cheap to
    copy; the graph definition is built once, on first use."""

    make: Callable[[nnx.Rngs], nnx.Module]
    name: str = "network"

    @property
    def graphdef(self):
        cached = self.__dict__.get("_graphdef")
        if cached is None:
            cached = nnx.graphdef(nnx.eval_shape(lambda: self.make(nnx.Rngs(0))))
            object.__setattr__(self, "_graphdef", cached)
        return cached

    def init(self, key):
        """A fresh parameter state (an ``nnx.State`` pytree) from ``key``."""
        return nnx.state(self.make(nnx.Rngs(params=key)))

    def apply(self, state, *args):
        return nnx.merge(self.graphdef, state)(*args)

    def abstract(self):
        return nnx.state(nnx.eval_shape(lambda: self.make(nnx.Rngs(0))))

    def from_tree(self, tree: dict):
        """The state of a nested dict written by :func:`to_tree` (shapes checked)."""
        state = self.abstract()
        want = to_tree(jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), state))
        _check_same_tree(want, tree, self.name)
        nnx.replace_by_pure_dict(state, _int_keys(tree))
        return state


def policy_network(obs_dim: int, act_dim: int, hidden: tuple, activation: str = "swish",
                   init_log_std: float = -0.5, layer_norm: bool = False) -> Network:
    """A :class:`GaussianPolicy` ``obs_dim -> (mean, log_std)`` of ``act_dim`` actions."""
    return Network(lambda rngs: GaussianPolicy(obs_dim, act_dim, tuple(hidden), activation,
                                               rngs, init_log_std, layer_norm),
                   name=f"policy {obs_dim}->{tuple(hidden)}->{act_dim}")


def value_network(obs_dim: int, hidden: tuple, activation: str = "swish",
                  layer_norm: bool = False) -> Network:
    """An :class:`MLP` ``obs_dim -> 1`` (a value function)."""

    def make(rngs):
        return MLP(obs_dim, tuple(hidden), 1, activation, rngs, layer_norm=layer_norm)

    return Network(make, name=f"critic {obs_dim}->{tuple(hidden)}->1")


def to_tree(state) -> dict:
    """An ``nnx.State`` as a nested dict of arrays with string keys."""
    return _str_keys(nnx.to_pure_dict(state))


def _str_keys(d):
    if isinstance(d, dict):
        return {str(k): _str_keys(v) for k, v in d.items()}
    return d


def _int_keys(d):
    if isinstance(d, dict):
        return {(int(k) if isinstance(k, str) and k.isdigit() else k): _int_keys(v)
                for k, v in d.items()}
    return d


def _check_same_tree(want: dict, got: dict, name: str, path: str = "") -> None:
    if not isinstance(got, dict):
        raise ValueError(f"{name}: expected a dict at {path or '/'}, got {type(got).__name__}")
    if set(want) != set(got):
        raise ValueError(f"{name}: parameters at {path or '/'} have keys {sorted(got)}, "
                         f"expected {sorted(want)}")
    for k, w in want.items():
        if isinstance(w, dict):
            _check_same_tree(w, got[k], name, f"{path}/{k}")
        elif tuple(jnp.shape(got[k])) != tuple(w.shape):
            raise ValueError(f"{name}: parameter {path}/{k} has shape {jnp.shape(got[k])}, "
                             f"expected {w.shape}")
