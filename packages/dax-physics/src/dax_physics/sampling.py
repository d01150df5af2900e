"""Particle sampling helpers (NumPy, host side; positions in m, z up).

Every sampler takes the grid cell size ``dx`` [m] and a density ``ppc`` (particles per
cell, 8 is the usual MPM choice) and returns ``(x, vol)``: positions (N, 3) float32 and the
rest volume per particle [m^3] such that ``N * vol`` equals the shape's volume. Sampling is
stratified (one jittered sample per sub-cell of side ``dx / ppc^(1/3)``) and seeded, so the
same arguments give the same particles.
"""

from __future__ import annotations

import numpy as np


def _lattice(lo, hi, dx, ppc, seed, jitter):
    if ppc <= 0:
        raise ValueError(f"particles per cell must be > 0, got {ppc}")
    lo = np.asarray(lo, np.float64)
    hi = np.asarray(hi, np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or np.any(hi <= lo):
        raise ValueError(f"need a non-empty box lo < hi with 3 coordinates, got {lo}, {hi}")
    h = dx / ppc ** (1.0 / 3.0)
    counts = np.maximum(np.round((hi - lo) / h).astype(int), 1)
    step = (hi - lo) / counts
    grids = np.meshgrid(*[np.arange(c) for c in counts], indexing="ij")
    cells = np.stack([g.reshape(-1) for g in grids], axis=1).astype(np.float64)
    rng = np.random.default_rng(seed)
    offs = 0.5 + (rng.random(cells.shape) - 0.5) * jitter
    return lo + (cells + offs) * step, float(np.prod(step))


def box(lo, hi, dx, ppc=8, seed=0, jitter=1.0):
    """Fill the axis-aligned box [lo, hi] [m]."""
    x, vol = _lattice(lo, hi, dx, ppc, seed, jitter)
    return x.astype(np.float32), vol


def cylinder(center, radius, height, dx, ppc=8, seed=0, jitter=1.0):
    """Fill a vertical cylinder: base centre ``center`` [m], ``radius`` [m], ``height`` [m]."""
    c = np.asarray(center, np.float64)
    lo = c - np.array([radius, radius, 0.0])
    hi = c + np.array([radius, radius, height])
    x, vol = _lattice(lo, hi, dx, ppc, seed, jitter)
    keep = np.sum((x[:, :2] - c[:2]) ** 2, axis=1) <= radius ** 2
    return x[keep].astype(np.float32), vol


def capsule_chain(points, radius, dx, ppc=8, seed=0, jitter=1.0):
    """Fill the union of capsules of ``radius`` [m] around the polyline ``points`` (P, 3):
    a rope along any curve."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
        raise ValueError(f"a capsule chain needs a polyline of shape (P >= 2, 3), got {pts.shape}")
    lo = pts.min(0) - radius
    hi = pts.max(0) + radius
    x, vol = _lattice(lo, hi, dx, ppc, seed, jitter)
    a, b = pts[:-1], pts[1:]
    ab = b - a
    t = np.einsum("nsk,sk->ns", x[:, None, :] - a[None], ab) / np.maximum(
        np.sum(ab * ab, axis=1), 1e-30)
    t = np.clip(t, 0.0, 1.0)
    closest = a[None] + t[..., None] * ab[None]
    d = np.min(np.linalg.norm(x[:, None, :] - closest, axis=-1), axis=1)
    return x[d <= radius].astype(np.float32), vol
