"""Triangle meshes for cloth: procedural square cloth and T-shirt, meshio loading,
validation, and the spring network derived from the mesh.

All functions here are numpy (host side, run once when a cloth is built). Lengths are in
metres; the cloth lies in the z = ``height`` plane (z up).
"""

from __future__ import annotations

import numpy as np


class MeshError(ValueError):
    """A triangle mesh that cannot be simulated (degenerate or non-manifold)."""


# ----------------------------------------------------------------------------- generators

def square_mesh(n: int, m: int | None = None, size=(1.0, 1.0), origin=(0.0, 0.0),
                height: float = 0.0):
    """A rectangular cloth of ``n x m`` vertices spanning ``size = (sx, sy)`` [m] from
    ``origin`` [m] at height ``height`` [m]. Vertex ``i*m + j`` is at
    ``origin + (i sx/(n-1), j sy/(m-1))``. Quads are split along alternating diagonals
    (a "union-jack" pattern, so the cloth has no preferred shear direction).

    Returns ``(vertices (n*m, 3) float64, faces (F, 3) int32)``.
    """
    m = n if m is None else m
    if n < 2 or m < 2:
        raise ValueError(f"a square cloth needs at least 2 x 2 vertices, got {n} x {m}")
    sx, sy = float(size[0]), float(size[1])
    if not (sx > 0 and sy > 0):
        raise ValueError(f"cloth size must be > 0 m, got {size}")
    u = np.linspace(0.0, sx, n) + origin[0]
    w = np.linspace(0.0, sy, m) + origin[1]
    ii, jj = np.meshgrid(u, w, indexing="ij")
    verts = np.stack([ii, jj, np.full_like(ii, float(height))], -1).reshape(-1, 3)
    a, b = np.meshgrid(np.arange(n - 1), np.arange(m - 1), indexing="ij")
    a, b = a.ravel(), b.ravel()
    v00, v10, v01, v11 = a * m + b, (a + 1) * m + b, a * m + b + 1, (a + 1) * m + b + 1
    alt = (a + b) % 2 == 0
    t1 = np.where(alt[:, None], np.stack([v00, v10, v11], 1), np.stack([v00, v10, v01], 1))
    t2 = np.where(alt[:, None], np.stack([v00, v11, v01], 1), np.stack([v10, v11, v01], 1))
    faces = np.concatenate([t1, t2]).astype(np.int32)
    return verts, faces


def tshirt_outline(width: float = 0.5, length: float = 0.6, sleeve: float = 0.2,
                   sleeve_width: float = 0.16, neck: float = 0.16, neck_depth: float = 0.05):
    """Closed outline polygon (K, 2) [m] of a flat T-shirt, centred on x = 0, hem at y = 0,
    counter-clockwise: body ``width x length``, two sleeves of length ``sleeve`` pointing
    outwards and slightly down, and a neck opening ``neck`` wide and ``neck_depth`` deep."""
    hw = width / 2
    sh = length  # shoulder height
    arm = length - sleeve_width  # armpit height
    drop = 0.35 * sleeve  # sleeves slope down
    return np.array([
        (-hw, 0.0), (hw, 0.0), (hw, arm),
        (hw + sleeve, arm - drop), (hw + sleeve + 0.02, arm - drop + sleeve_width), (hw, sh),
        (neck / 2, sh), (0.0, sh - neck_depth), (-neck / 2, sh),
        (-hw, sh), (-hw - sleeve - 0.02, arm - drop + sleeve_width), (-hw - sleeve, arm - drop),
        (-hw, arm),
    ])


def _inside_polygon(pts, poly):
    """Even-odd point-in-polygon test, pts (N, 2), poly (K, 2)."""
    x, y = pts[:, 0:1], pts[:, 1:2]
    x0, y0 = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    cond = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.sum(cond & (x < xc), axis=1) % 2 == 1


def polygon_mesh(outline, spacing: float, height: float = 0.0):
    """Triangulate the inside of a simple polygon ``outline`` (K, 2) [m] with a regular
    grid of ``spacing`` [m]: every grid square whose centre lies inside the outline is split
    into two triangles, then the vertices of the outline-crossing squares are snapped onto
    the outline so the boundary follows it. Keeps the largest edge-connected piece.

    Returns ``(vertices (V, 3), faces (F, 3) int32)``.
    """
    outline = np.asarray(outline, float)
    if spacing <= 0:
        raise ValueError(f"spacing must be > 0 m, got {spacing}")
    lo, hi = outline.min(0), outline.max(0)
    nx = int(np.ceil((hi[0] - lo[0]) / spacing)) + 1
    ny = int(np.ceil((hi[1] - lo[1]) / spacing)) + 1
    gx = lo[0] + spacing * np.arange(nx)
    gy = lo[1] + spacing * np.arange(ny)
    a, b = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), indexing="ij")
    centres = np.stack([gx[a.ravel()] + spacing / 2, gy[b.ravel()] + spacing / 2], 1)
    keep = _inside_polygon(centres, outline)
    a, b = a.ravel()[keep], b.ravel()[keep]
    v00, v10, v01, v11 = a * ny + b, (a + 1) * ny + b, a * ny + b + 1, (a + 1) * ny + b + 1
    alt = (a + b) % 2 == 0
    t1 = np.where(alt[:, None], np.stack([v00, v10, v11], 1), np.stack([v00, v10, v01], 1))
    t2 = np.where(alt[:, None], np.stack([v00, v11, v01], 1), np.stack([v10, v11, v01], 1))
    faces = np.concatenate([t1, t2])
    ii, jj = np.meshgrid(gx, gy, indexing="ij")
    verts = np.stack([ii.ravel(), jj.ravel()], 1)
    # snap vertices that lie outside the outline onto its nearest point (at most half a cell)
    out = ~_inside_polygon(verts, outline)
    if np.any(out):
        p = verts[out]
        s0, s1 = outline, np.roll(outline, -1, axis=0)
        seg = s1 - s0
        t = np.clip(np.einsum("nkd,kd->nk", p[:, None] - s0[None], seg)
                    / np.sum(seg * seg, 1)[None], 0.0, 1.0)
        q = s0[None] + t[..., None] * seg[None]
        k = np.argmin(np.sum((q - p[:, None]) ** 2, -1), 1)
        snapped = q[np.arange(len(p)), k]
        moved = np.linalg.norm(snapped - p, axis=1) <= 0.75 * spacing
        verts[np.flatnonzero(out)[moved]] = snapped[moved]
    faces = _largest_component(faces)
    verts3 = np.concatenate([verts, np.full((len(verts), 1), float(height))], 1)
    verts3, faces = compact(verts3, faces)
    # drop triangles that snapping made degenerate
    area = _tri_areas(verts3, faces)
    faces = faces[area > 1e-3 * spacing * spacing]
    return compact(verts3, faces)


def tshirt_mesh(spacing: float = 0.025, height: float = 0.0, **outline_kwargs):
    """A flat T-shirt (body and sleeves, one layer) triangulated from
    :func:`tshirt_outline` with grid ``spacing`` [m]. Returns ``(vertices, faces)``."""
    return polygon_mesh(tshirt_outline(**outline_kwargs), spacing, height)


def load_mesh(path):
    """Read a triangle mesh (.obj, .ply, .vtu, ... anything meshio reads) and return
    ``(vertices (V, 3) float64, faces (F, 3) int32)``. Needs the optional ``mesh`` extra
    (``pip install dax-physics[mesh]``)."""
    try:
        import meshio
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("reading cloth meshes needs meshio: pip install 'dax-physics[mesh]'"
                          ) from e
    mesh = meshio.read(path)
    tris = [c.data for c in mesh.cells if c.type == "triangle"]
    if not tris:
        kinds = sorted({c.type for c in mesh.cells})
        raise MeshError(f"{path}: no triangle cells (found {kinds})")
    pts = np.asarray(mesh.points, float)
    if pts.shape[1] == 2:
        pts = np.concatenate([pts, np.zeros((len(pts), 1))], 1)
    return compact(pts, np.concatenate(tris).astype(np.int32))


# ----------------------------------------------------------------------------- topology

def compact(vertices, faces):
    """Drop vertices that no face uses and renumber the faces."""
    faces = np.asarray(faces)
    used = np.unique(faces)
    remap = -np.ones(len(vertices), np.int64)
    remap[used] = np.arange(len(used))
    return np.asarray(vertices)[used], remap[faces].astype(np.int32)


def _largest_component(faces):
    nv = int(faces.max()) + 1
    parent = np.arange(nv)

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i
    for f in faces:
        r = [find(int(v)) for v in f]
        for x in r[1:]:
            parent[x] = r[0]
    roots = np.array([find(int(f[0])) for f in faces])
    vals, counts = np.unique(roots, return_counts=True)
    return faces[roots == vals[np.argmax(counts)]]


def _tri_areas(v, f):
    return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]),
                                axis=1)


def validate_mesh(vertices, faces, rel_area_tol: float = 1e-8):
    """Raise :class:`MeshError` for meshes the cloth solver cannot use: wrong shapes,
    non-finite vertices, out-of-range indices, triangles with repeated vertices or (near)
    zero area, edges shared by more than two triangles (non-manifold), unused vertices."""
    v = np.asarray(vertices, float)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise MeshError(f"faces must have shape (F, 3) with F >= 1, got {f.shape}")
    if not np.all(np.isfinite(v)):
        raise MeshError(f"vertices contain non-finite values at rows "
                        f"{np.flatnonzero(~np.isfinite(v).all(1))[:5].tolist()}")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"face indices must be in [0, {len(v)}), got [{f.min()}, {f.max()}]")
    rep = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    if np.any(rep):
        i = int(np.flatnonzero(rep)[0])
        raise MeshError(f"degenerate triangle {i}: repeated vertex {f[i].tolist()}")
    area = _tri_areas(v, f)
    e2 = np.max([np.sum((v[f[:, a]] - v[f[:, b]]) ** 2, 1) for a, b in ((0, 1), (1, 2), (2, 0))],
                axis=0)
    bad = area <= rel_area_tol * e2
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise MeshError(f"degenerate triangle {i} (vertices {f[i].tolist()}): area "
                        f"{area[i]:.3g} m^2 (expected > {rel_area_tol:g} x longest edge^2 = "
                        f"{rel_area_tol * e2[i]:.3g} m^2)")
    edges, counts = _edge_counts(f)
    if np.any(counts > 2):
        k = int(np.flatnonzero(counts > 2)[0])
        raise MeshError(f"non-manifold mesh: edge {edges[k].tolist()} is shared by "
                        f"{counts[k]} triangles (expected at most 2)")
    unused = np.setdiff1d(np.arange(len(v)), f.ravel())
    if len(unused):
        raise MeshError(f"{len(unused)} vertices are used by no triangle (first: "
                        f"{unused[:5].tolist()}); call mesh.compact(vertices, faces) first")


def _edge_counts(f):
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)


def mesh_springs(vertices, faces):
    """The spring network of a triangle mesh.

    * structural: every mesh edge;
    * shear: for each interior edge that is the longest edge of both its triangles (the
      diagonal of a triangulated quad), the pair of opposite vertices (the other diagonal);
    * bending: for every other interior edge, the pair of vertices opposite it.

    Returns ``(pairs (E, 2) int32, kind (E,) int8 in {0 struct, 1 shear, 2 bend},
    area (E,) float)`` where ``area`` [m^2] is the summed area of the triangles adjacent to
    the spring's edge (used to scale moduli into per-spring stiffness).
    """
    v = np.asarray(vertices, float)
    f = np.asarray(faces, np.int64)
    nf = len(f)
    area = _tri_areas(v, f)
    # half-edges: (a, b) with a<b, face, opposite vertex, whether it is the face's longest
    he = []
    for a_i, b_i, c_i in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
        he.append(np.stack([f[:, a_i], f[:, b_i], np.arange(nf), f[:, c_i]], 1))
    he = np.concatenate(he)
    lens = np.linalg.norm(v[he[:, 0]] - v[he[:, 1]], axis=1)
    face_max = np.zeros(nf)
    np.maximum.at(face_max, he[:, 2], lens)
    is_longest = lens >= face_max[he[:, 2]] * (1 - 1e-9)
    key = np.sort(he[:, :2], axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    key, he, is_longest = key[order], he[order], is_longest[order]
    uniq, start, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    pairs = [uniq]
    kinds = [np.zeros(len(uniq), np.int8)]
    e_area = np.zeros(len(uniq))
    np.add.at(e_area, np.repeat(np.arange(len(uniq)), counts), area[he[:, 2]])
    areas = [e_area]
    inner = counts == 2
    s = start[inner]
    o1, o2 = he[s, 3], he[s + 1, 3]
    shear = is_longest[s] & is_longest[s + 1]
    pairs.append(np.sort(np.stack([o1, o2], 1), axis=1))
    kinds.append(np.where(shear, 1, 2).astype(np.int8))
    areas.append(e_area[inner])
    return (np.concatenate(pairs).astype(np.int32), np.concatenate(kinds),
            np.concatenate(areas))


def vertex_areas(vertices, faces):
    """Lumped area [m^2] of each vertex (a third of each adjacent triangle)."""
    a = _tri_areas(np.asarray(vertices, float), np.asarray(faces))
    out = np.zeros(len(vertices))
    for k in range(3):
        np.add.at(out, np.asarray(faces)[:, k], a / 3)
    return out
