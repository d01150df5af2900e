"""Eager input checks at the boundary between a user's data and the pure core.

The pure core cannot look at values without a host sync, so it never refuses a value:
under ``jit`` a NaN/inf action, parameter or state propagates and turns
``info["finite"]`` and ``state.finite`` false (sticky for the episode), and a finite but
out-of-range parameter (a negative friction, a too stiff material) runs as given. What
the core does refuse at trace time is what is static: a wrong action shape, an action
that is not real numbers (complex, strings, objects), a goal or ``lam`` of the wrong
shape (:meth:`dax_tasks.Env.step`, :meth:`dax_tasks.Env.reset`). Called eagerly (no
``jit``) with concrete params other than the defaults, ``step`` and ``reset`` run
:func:`check_params` on them first. Code that holds concrete
values (the Gymnasium adapter, dax-data, a user's loop) calls these checks first and gets
a ``ValueError`` that names the problem: a wrong shape, a NaN/inf, a complex or
non-numeric action, an unknown field, a parameter out of its range or one that makes the
time step unstable.

Sizes are checked before work too (:func:`check_spec`, :func:`check_run_memory`): a
spec whose numbers do not fit the float32 / int32 the programs use, a substep below
:data:`MIN_DT`, or a scene, batch or picture size whose memory exceeds what the machine
has is one ``ValueError`` before anything is built, allocated or written.
"""

from __future__ import annotations

import dataclasses
import math
import os

import jax
import numpy as np

#: The smallest substep [s] a scene may ask for: float32 coordinates of order 1 m are
#: about 6e-8 m apart, so at 1e-6 s a point moving at 0.1 m/s still moves more than one
#: spacing per substep; below it substeps lose motion to rounding, and the substep counts
#: derived from durations (a settling time / dt) leave int32.
MIN_DT = 1e-6
#: Memory [bytes] per object point while a task runs, an upper bound over the tasks: the
#: state, a step's temporaries and a cloth's self-collision neighbour lists.
BYTES_PER_POINT = 2048
#: Memory [bytes] per MPM grid cell while a task runs (grid fields and the transfer's
#: temporaries), an upper bound.
BYTES_PER_CELL = 256
#: Memory [bytes] per object point while a scene is built on the host (NumPy sampling
#: and meshing), an upper bound.
BUILD_BYTES_PER_POINT = 256
#: Memory [bytes] per pixel while one picture is rendered (height map, top point index,
#: colour in float32 and the uint8 result).
BYTES_PER_PIXEL = 64
#: Bytes per stored pixel of a recorded step: a float32 height and three uint8 channels.
STORED_BYTES_PER_PIXEL = 7
_INT32 = (-(2**31), 2**31 - 1)
_FLOAT32 = np.finfo(np.float32)


def check_action(env, action, batch_shape: tuple = ()) -> np.ndarray:
    """``action`` as a float32 NumPy array of shape ``batch_shape + (action_dim,)``, clipped
    to the spec's bounds; ``ValueError`` naming the task and the problem if it is not real
    numbers, has another shape, or holds NaN/inf. Out-of-bound values are allowed and
    clipped as the env clips them; the check and the clip happen in float64, before the
    cast to float32, so a finite action beyond float32's range (1e39) is clipped, not
    turned into inf."""
    spec = env.spec
    try:
        raw = np.asarray(action)
        if raw.dtype.kind not in "fiu":  # complex (0.1+5j would act as 0.1), text, objects
            raise TypeError(f"dtype {raw.dtype}")
        a = raw.astype(np.float64)
    except (TypeError, ValueError, OverflowError) as err:
        raise ValueError(f"{spec.name}: action is not an array of numbers (real ones; "
                         f"{err})") from None
    shape = tuple(batch_shape) + (spec.action_dim,)
    if a.shape != shape:
        raise ValueError(f"{spec.name}: expected a {spec.action_kind} action of shape "
                         f"{shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{spec.name}: action contains NaN or inf: {a.tolist()}")
    low = np.asarray(spec.action_low, np.float64)
    high = np.asarray(spec.action_high, np.float64)
    return np.clip(a, low, high).astype(np.float32)


def check_key(key, batch_size: int | None = None):
    """A ``PRNGKey`` of shape (2,) (or ``(batch_size, 2)``); ``ValueError`` otherwise."""
    shape = np.shape(key)
    want = (2,) if batch_size is None else (batch_size, 2)
    if shape != want:
        raise ValueError(f"expected a PRNGKey of shape {want}, got {shape}")
    return key


def check_params(env, params):
    """``ValueError`` naming the problem if ``params`` (an
    :class:`~dax_tasks.core.env.EnvParams`) cannot drive ``env``: not of the class of
    ``env.default_params``, a goal of the wrong shape, a non-finite or non-positive λ, a
    negative or non-finite auxiliary weight, or physics numbers the task refuses (for the
    MPM and cloth tasks: wrong shapes, NaN, non-positive densities or moduli, and any
    value that makes the substep unstable). Returns ``params``."""
    name = env.spec.name
    # the class of the env's own params, so this module does not import the env module
    # (which calls this one in its eager checks)
    if not isinstance(params, type(env.default_params)):
        raise ValueError(f"{name}: params must be an EnvParams, got {type(params).__name__}")
    goal = np.asarray(params.goal)
    want = env.default_params.goal.shape
    if goal.shape != want:
        raise ValueError(f"{name}: params.goal must have shape {want}, got {goal.shape}")
    if not np.all(np.isfinite(goal)):
        raise ValueError(f"{name}: params.goal contains NaN or inf")
    lam = np.asarray(params.lam)
    if lam.shape != () or not (np.isfinite(lam) and lam > 0):
        raise ValueError(f"{name}: params.lam must be a positive number in 1/m, got "
                         f"{lam.tolist()}")
    aux = np.asarray(params.aux_weight)
    if aux.shape != () or not (np.isfinite(aux) and aux >= 0):
        raise ValueError(f"{name}: params.aux_weight must be a number >= 0, got "
                         f"{aux.tolist()}")
    default = jax.tree_util.tree_structure(env.default_params.physics)
    if jax.tree_util.tree_structure(params.physics) != default:
        raise ValueError(f"{name}: params.physics must have the structure of "
                         f"env.default_params.physics ({default}), got "
                         f"{jax.tree_util.tree_structure(params.physics)}")
    try:
        env.check_physics_params(params.physics)
    except ValueError as err:
        raise ValueError(f"{name}: {err}") from None
    return params


# ----------------------------------------------------------------------------- sizes

def _gib(nbytes: float) -> str:
    return f"{nbytes / 2**30:.3g} GiB"


def host_memory() -> int | None:
    """This machine's physical memory [bytes] (``None`` where the OS does not say)."""
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return None


def device_memory() -> int | None:
    """The default JAX device's memory [bytes] when it is an accelerator that reports it
    (``None`` on CPU, whose arrays live in :func:`host_memory`). Initialises JAX's
    backend."""
    device = jax.devices()[0]
    if device.platform == "cpu":
        return None
    try:
        stats = device.memory_stats() or {}
    except (RuntimeError, NotImplementedError):  # pragma: no cover - backend dependent
        return None
    limit = stats.get("bytes_limit")
    return int(limit) if limit else None


def check_memory(nbytes: float, what: str, device: bool = False) -> None:
    """``ValueError`` if ``nbytes`` [bytes] (an estimate of what ``what`` needs) exceed
    the machine's physical memory, or with ``device`` the default accelerator's memory
    (:func:`device_memory`); nothing is allocated."""
    limits = [(host_memory(), "physical memory")]
    if device:
        limits.append((device_memory(), f"{jax.devices()[0].platform.upper()} memory"))
    for limit, where in limits:
        if limit is not None and nbytes > limit:
            raise ValueError(f"{what} needs about {_gib(nbytes)} of memory, more than this "
                             f"machine's {_gib(limit)} of {where}; ask for less")


def _check_number(where: str, value) -> None:
    """An int within int32, a float finite and within float32's normal range (or 0)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        return
    if isinstance(value, (int, np.integer)):
        if not _INT32[0] <= int(value) <= _INT32[1]:
            raise ValueError(f"{where} = {value} does not fit in int32 "
                             f"({_INT32[0]} .. {_INT32[1]})")
        return
    x = float(value)
    if math.isfinite(x) and x != 0 and not _FLOAT32.tiny <= abs(x) <= _FLOAT32.max:
        raise ValueError(f"{where} = {value!r} is not representable in float32 (magnitudes "
                         f"{float(_FLOAT32.tiny):.3g} .. {float(_FLOAT32.max):.3g}, or 0)")


def check_representable(obj, prefix: str = "") -> None:
    """``ValueError`` naming the field if a number in the dataclass ``obj`` (a spec, a
    scene; tuples and nested dataclasses included) does not fit the type the programs
    compute in: an int outside int32, a non-zero float outside float32's normal range
    (1e-300 would become 0, 1e39 inf). Non-finite floats are left to the field checks
    (a yield stress may be inf)."""
    def visit(where, value):
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            for f in dataclasses.fields(value):
                visit(f"{where}.{f.name}" if where else f.name, getattr(value, f.name))
        elif isinstance(value, (tuple, list)):
            for i, v in enumerate(value):
                visit(f"{where}[{i}]", v)
        else:
            _check_number(where, value)

    visit(prefix, obj)


def object_points_bound(scene) -> int:
    """An upper bound of the object points ``scene`` builds, from the fields that set its
    resolution (0 for a scene with none of them): an MPM grid (``domain`` cells per axis,
    ``ppc`` particles per cell): ``ppc * prod(domain)``; a square cloth (``shape ==
    "square"``, ``n`` vertices per side): ``n * n``; a cloth cut from an outline
    (``spacing`` [m], ``outline`` of ``(name, length [m])`` pairs): ``(sum of the lengths
    / spacing + 1) ** 2``."""
    if scene is None:
        return 0
    if hasattr(scene, "domain") and hasattr(scene, "ppc"):
        return int(scene.ppc) * math.prod(int(d) for d in scene.domain)
    if getattr(scene, "shape", None) == "square" and hasattr(scene, "n"):
        return int(scene.n) ** 2
    if hasattr(scene, "spacing") and hasattr(scene, "outline") and scene.spacing > 0:
        extent = sum(abs(float(v)) for _, v in scene.outline)
        return int((extent / scene.spacing + 1) ** 2)
    return 0


def grid_cells(scene) -> int:
    """The MPM grid cells of ``scene`` (``prod(domain)``; 0 without a grid)."""
    domain = getattr(scene, "domain", None)
    return math.prod(int(d) for d in domain) if domain else 0


def check_spec(spec, image_size: int | None = None) -> None:
    """Refuse, before the task is built, a spec it cannot run (``ValueError`` naming the
    field or the size): numbers outside int32 / float32 (:func:`check_representable`), a
    scene ``dt`` below :data:`MIN_DT` (the upper, stable bound is the physics' check when
    the task is built), and a scene whose build (:data:`BUILD_BYTES_PER_POINT` per point
    of :func:`object_points_bound`) or run (:data:`BYTES_PER_CELL` per grid cell; without
    a grid, whose bound is exact, :data:`BYTES_PER_POINT` per point) or, with
    ``image_size``, whose pictures (:data:`BYTES_PER_PIXEL`) need more memory than the
    machine has (:func:`check_memory`). An MPM scene's particles are checked exactly once
    it is built (:func:`check_run_memory`)."""
    try:
        check_representable(spec)
    except ValueError as err:
        raise ValueError(f"{spec.name}: {err}") from None
    scene = spec.scene
    dt = getattr(scene, "dt", None)
    if isinstance(dt, (int, float)) and not isinstance(dt, bool) and dt < MIN_DT:
        raise ValueError(f"{spec.name}: scene.dt = {dt!r} s is below {MIN_DT:g} s, the "
                         f"smallest substep float32 positions resolve")
    points, cells = object_points_bound(scene), grid_cells(scene)
    check_memory(points * BUILD_BYTES_PER_POINT, f"{spec.name}: building a scene of up to "
                 f"{points} object points")
    if cells:
        check_memory(cells * BYTES_PER_CELL, f"{spec.name}: a grid of {cells} cells")
    else:
        check_memory(points * BYTES_PER_POINT, f"{spec.name}: a scene of {points} object "
                     f"points")
    if image_size is not None:
        check_memory(float(image_size) ** 2 * BYTES_PER_PIXEL,
                     f"{spec.name}: a {image_size} x {image_size} picture")


def check_run_memory(env, batch: int = 1, image_size: int | None = None,
                     frames: int = 0) -> None:
    """Refuse (``ValueError``, nothing allocated) a run of ``batch`` environments of the
    built ``env`` whose memory exceeds the machine's (host and accelerator,
    :func:`check_memory`): its object points (exact, ``env.n_object_points``) and grid
    cells, and with ``image_size`` one picture per environment being rendered plus
    ``frames`` stored pictures (height and RGB) per environment."""
    spec = env.spec
    points, cells = env.n_object_points, grid_cells(spec.scene)
    per_env = points * BYTES_PER_POINT + cells * BYTES_PER_CELL
    what = f"{spec.name}: {batch} environment(s) of {points} object points"
    if image_size is not None:
        pixels = float(image_size) ** 2
        per_env += pixels * (BYTES_PER_PIXEL + frames * STORED_BYTES_PER_PIXEL)
        what += f" with {image_size} x {image_size} pictures"
        if frames:
            what += f" ({frames} stored per episode)"
    check_memory(batch * per_env, what, device=True)
