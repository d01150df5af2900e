"""Argument checks of the methods' frozen configs: each refuses a bad value at construction
with a ``ValueError`` naming the field and the value."""

from __future__ import annotations

import dataclasses

import numpy as np

#: Field metadata (``dataclasses.field(metadata=OMIT_DEFAULT)``) marking a config field
#: added after rows were measured, whose default leaves the method as it was: at that
#: default it is left out of the config's digest (:func:`dax_algos.bench.provenance.
#: config_digest`), so adding the field does not make the earlier rows stale.
OMIT_DEFAULT = {"digest": "omit_default"}


def check_choice(name: str, value, valid) -> None:
    """``value`` is one of ``valid``; else ``ValueError("unknown NAME VALUE; valid: ...")``
    listing them."""
    if value not in valid:
        raise ValueError(f"unknown {name} {value!r}; valid: {', '.join(valid)}")


def check_positive_int(name: str, value) -> None:
    """``value`` is an ``int`` (not a ``bool``) greater than 0."""
    if not (isinstance(value, int) and not isinstance(value, bool) and value > 0):
        raise ValueError(f"{name} must be a positive int, got {value!r}")


def check_positive(name: str, value, allow_zero: bool = False) -> None:
    """``value`` is a finite number greater than 0 (``>= 0`` with ``allow_zero``)."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
    if not ok or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be a finite number {bound}, got {value!r}")


def check_fields(cfg, ints=(), positive=(), non_negative=(), fractions=(), optional_ints=(),
                 optional_positive=()) -> None:
    """Check a config's fields by name: positive ints (``ints``; ``optional_ints`` may also
    be ``None``), finite numbers > 0 (``positive``; ``optional_positive`` may be
    ``None``) or >= 0 (``non_negative``), and numbers in [0, 1] (``fractions``). Every
    field whose name ends in ``hidden`` must be a non-empty tuple of positive ints (layer
    widths)."""
    for name in ints:
        check_positive_int(name, getattr(cfg, name))
    for name in optional_ints:
        if getattr(cfg, name) is not None:
            check_positive_int(name, getattr(cfg, name))
    for name in positive:
        check_positive(name, getattr(cfg, name))
    for name in optional_positive:
        if getattr(cfg, name) is not None:
            check_positive(name, getattr(cfg, name))
    for name in non_negative:
        check_positive(name, getattr(cfg, name), allow_zero=True)
    for name in fractions:
        v = getattr(cfg, name)
        check_positive(name, v, allow_zero=True)
        if v > 1:
            raise ValueError(f"{name} must be in [0, 1], got {v!r}")
    hidden = [f.name for f in dataclasses.fields(cfg) if f.name.endswith("hidden")]
    for name in hidden:
        v = getattr(cfg, name)
        if not (isinstance(v, tuple) and v and all(isinstance(h, int) and h > 0 for h in v)):
            raise ValueError(f"{name} must be a non-empty tuple of positive ints, got {v!r}")
