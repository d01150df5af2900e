"""A small physics demo: water, an elastic (tofu) cube and a dough cube share one MPM grid;
a box collider presses the dough and lifts off again.

    python -m benchmarks.physics_demo --out demo_out

Prints its figures as one JSON object (throughput, mass conservation, the dough's permanent
flattening versus the tofu's recovery) and writes ``demo_out/mpm_demo.png`` (side views at
several times; matplotlib if installed, otherwise a plain PNG written with zlib).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import struct
import time
import zlib

import jax
import jax.numpy as jnp
import numpy as np

from dax_physics import mpm, sampling
from dax_physics.colliders import ColliderSpec, ColliderState
from dax_physics.materials import dough, tofu, water

COLORS = np.array([[0.15, 0.45, 0.95], [0.95, 0.85, 0.35], [0.85, 0.45, 0.25]])
NAMES = ("water", "tofu", "dough")


def build(grid: int = 32):
    """The demo scene in a 0.2 m box: water (left), tofu (middle), dough (right, under the
    press)."""
    size = 0.2
    dx = size / grid
    floor = 3 * dx
    parts = [
        sampling.box([0.02, 0.06, floor], [0.05, 0.14, floor + 0.04], dx, seed=0),
        sampling.box([0.085, 0.08, floor], [0.115, 0.11, floor + 0.03], dx, seed=1),
        sampling.box([0.135, 0.08, floor], [0.165, 0.11, floor + 0.03], dx, seed=2),
    ]
    x = np.concatenate([p[0] for p in parts])
    vol = np.concatenate([np.full(len(p[0]), p[1]) for p in parts])
    mat = np.concatenate([np.full(len(p[0]), i, np.int32) for i, p in enumerate(parts)])
    # A soft dough that holds its shape under its weight but yields under the 1 cm press;
    # moduli lowered so dt stays practical; a little viscosity keeps the coarse water calm.
    mats = (water(bulk_modulus=2.0e4, viscosity=0.05), tofu(youngs_modulus=2.0e4),
            dough(youngs_modulus=2.0e4, yield_stress=1500.0))
    press = ColliderSpec("box", (0.025, 0.025, 0.01), mode="separate", friction=0.5)
    cfg = mpm.MPMConfig(materials=mats, dx=dx, dt=1e-4, domain=(grid,) * 3,
                        gravity=(0.0, 0.0, -9.81), walls="slip", colliders=(press,),
                        max_speed=1.0)
    cstate = ColliderState.create([[0.15, 0.095, floor + 0.03 + 0.012]])
    return cfg, mpm.init_state(cfg, x, vol=vol, mat=mat, colliders=cstate), floor


def run(cfg, state, phases):
    """Run ``phases`` = [(substeps, press velocity z [m/s]), ...]; returns snapshots."""
    params = cfg.params
    snaps = [np.asarray(state.x)]
    for n, vz in phases:
        state = mpm.set_collider_velocity(state, 0, jnp.asarray([0.0, 0.0, vz]))
        state = mpm.rollout(cfg, params, state, n)
        snaps.append(np.asarray(state.x))
    return state, snaps


def _png(path: pathlib.Path, rgb: np.ndarray):
    """Write an (H, W, 3) float image in [0, 1] as PNG without extra dependencies."""
    h, w, _ = rgb.shape
    raw = (np.clip(rgb, 0, 1) * 255).astype(np.uint8)
    data = b"".join(b"\x00" + raw[i].tobytes() for i in range(h))

    def chunk(tag, payload):
        c = struct.pack(">I", len(payload)) + tag + payload
        return c + struct.pack(">I", zlib.crc32(tag + payload) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(data, 6)) + chunk(b"IEND", b""))
    tmp = path.with_suffix(".tmp")
    tmp.write_bytes(png)
    tmp.replace(path)


def draw(path: pathlib.Path, snaps, mat, titles, size):
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        panels = []
        for x in snaps:
            img = np.ones((160, 160, 3))
            px = np.clip((x[:, 0] / size * 159).astype(int), 0, 159)
            pz = np.clip(159 - (x[:, 2] / size * 159).astype(int), 0, 159)
            img[pz, px] = COLORS[mat]
            panels.append(img)
        _png(path, np.concatenate(panels, axis=1))
        return
    fig, axes = plt.subplots(1, len(snaps), figsize=(3 * len(snaps), 3.2))
    for ax, x, title in zip(axes, snaps, titles, strict=True):
        ax.scatter(x[:, 0], x[:, 2], s=1, c=COLORS[mat])
        ax.set_xlim(0, size)
        ax.set_ylim(0, size * 0.6)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x [m]")
    axes[0].set_ylabel("z [m]")
    fig.tight_layout()
    tmp = path.with_name(path.stem + ".tmp.png")
    fig.savefig(tmp, dpi=110)
    tmp.replace(path)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m benchmarks.physics_demo", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="demo_out", help="directory for the picture")
    ap.add_argument("--grid", type=int, default=32)
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    cfg, state, floor = build(args.grid)
    params = cfg.params
    mat = np.asarray(state.mat)
    # settle 0.1 s, press down 1 cm in 0.05 s, hold 0.05 s, lift 0.05 s, settle 0.15 s
    phases = [(1000, 0.0), (500, -0.2), (500, 0.0), (500, 0.6), (1500, 0.0)]
    t0 = time.perf_counter()
    final, snaps = run(cfg, state, phases)
    wall = time.perf_counter() - t0
    mpm.check_state(final)

    def height(x, k):
        return float(np.max(x[mat == k, 2]) - floor)

    m0 = float(mpm.total_mass(params, state))
    m1 = float(mpm.total_mass(params, final))
    n_sub = sum(n for n, _ in phases)
    figures = dict(
        particles={name: int((mat == k).sum()) for k, name in enumerate(NAMES)},
        grid=list(cfg.window), dt_s=cfg.dt, substeps=n_sub,
        max_stable_dt_s=mpm.max_stable_dt(cfg),
        wall_s_including_compile=round(wall, 2), substeps_per_s=round(n_sub / wall, 1),
        mass_kg=m0, mass_change_kg=m1 - m0,
        dough_height_m=dict(before=height(snaps[1], 2), after=height(snaps[-1], 2)),
        tofu_height_m=dict(before=height(snaps[1], 1), after=height(snaps[-1], 1)),
        water_mean_z_m=float(final.x[mat == 0, 2].mean()),
        finite=bool(final.finite), backend=jax.default_backend())
    titles = ["start", "settled", "pressing", "held", "lifted", "final"]
    draw(out / "mpm_demo.png", snaps, mat, titles, 0.2)
    figures["picture"] = str(out / "mpm_demo.png")
    print(json.dumps(figures, indent=1))


if __name__ == "__main__":
    main()
