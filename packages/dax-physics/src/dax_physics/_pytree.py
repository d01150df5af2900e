"""A tiny helper for immutable pytree dataclasses.

Fields are array data unless declared with ``static_field()``, in which case they are
hashable metadata (part of the jit cache key).
"""

from __future__ import annotations

import dataclasses

import jax


def static_field(**kwargs):
    """A dataclass field that is pytree metadata (static under ``jax.jit``)."""
    return dataclasses.field(metadata={"static": True}, **kwargs)


def pytree_dataclass(cls):
    """Make ``cls`` a frozen dataclass registered as a JAX pytree, with a ``replace(**changes)``
    method (``dataclasses.replace``) unless the class defines its own."""
    own_replace = "replace" in cls.__dict__
    cls = dataclasses.dataclass(frozen=True)(cls)
    data, meta = [], []
    for f in dataclasses.fields(cls):
        (meta if f.metadata.get("static", False) else data).append(f.name)
    jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)
    if not own_replace:
        cls.replace = lambda self, **changes: dataclasses.replace(self, **changes)
    return cls
