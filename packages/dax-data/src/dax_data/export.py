"""Export a recorded episode's object states for ParaView and Blender (meshio).

Each recorded frame (the ``points`` of the episode, at ``point_steps``) becomes one file:
``episode_<K>_<frame>.vtu`` (plus an ``episode_<K>.pvd`` time collection for ParaView),
``.xdmf`` (self-contained XML; ParaView groups the numbered files into a time series) or
``.ply`` (Blender). Cloth tasks are written as triangle meshes (the faces of the task's
rest mesh); particle tasks as point clouds (``vertex`` cells in VTU/XDMF, bare vertices in
PLY). Every frame carries the point data ``to_goal`` [m] (goal minus point, per point).
The goal itself is written as ``goal.<ext>``.
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from . import fileformat as ff

FORMATS = ("vtu", "xdmf", "ply")


def cloth_faces(meta: dict):
    """The triangle faces (F, 3) of the object of a file's task (the env's
    ``object_faces``: a cloth's mesh), or ``None`` for particles."""
    import dax_tasks

    spec = ff.spec_from_meta(meta)
    faces = dax_tasks.env_class(meta["task"])(spec).object_faces
    return None if faces is None else np.asarray(faces, np.int64)


def _mesh(points, faces, fmt, point_data):
    import meshio

    n = points.shape[0]
    if faces is not None:  # int32: PLY has no 64-bit integers
        cells = [("triangle", faces.astype(np.int32))]
    elif fmt == "ply":
        cells = []
    else:
        cells = [("vertex", np.arange(n, dtype=np.int32)[:, None])]
    return meshio.Mesh(points.astype(np.float64), cells, point_data=point_data)


def _write(mesh, path: Path, fmt: str) -> None:
    import meshio

    if fmt == "xdmf":
        meshio.xdmf.write(path, mesh, data_format="XML")
    elif fmt == "ply":
        meshio.write(path, mesh, file_format="ply", binary=True)
    else:
        meshio.write(path, mesh, file_format="vtu")


def export_episode(path, episode: int, fmt: str, out_dir) -> list:
    """Write episode ``episode`` of file ``path`` in format ``fmt`` into ``out_dir``;
    returns the written paths (goal first)."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; valid: {', '.join(FORMATS)}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with ff.DemoFile(path) as f:
        ep = f.episode(episode)
        goal = f.goal
        faces = cloth_faces(f.meta)
    if faces is not None and (faces.size == 0 or faces.max() >= goal.shape[0]):
        raise ff.DataFileError(f"{path}: the cloth mesh of this task has faces up to vertex "
                               f"{int(faces.max())} but the file has {goal.shape[0]} points")
    written = []
    goal_path = out_dir / f"goal.{fmt}"
    _write(_mesh(goal, faces, fmt, {}), goal_path, fmt)
    written.append(goal_path)
    frames = []
    for step, pts in zip(ep.point_steps.tolist(), ep.points, strict=True):
        p = out_dir / f"episode_{episode}_{step:04d}.{fmt}"
        data = {} if fmt == "ply" else {"to_goal": (goal - pts).astype(np.float64)}
        _write(_mesh(pts, faces, fmt, data), p, fmt)
        written.append(p)
        frames.append((step, p.name))
    if fmt == "vtu":
        pvd = out_dir / f"episode_{episode}.pvd"
        lines = ['<?xml version="1.0"?>',
                 '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
                 "  <Collection>"]
        lines += [f'    <DataSet timestep="{s}" part="0" file={quoteattr(n)}/>'
                  for s, n in frames]
        lines += ["  </Collection>", "</VTKFile>", ""]
        pvd.write_text("\n".join(lines))
        written.append(pvd)
    return written
