"""Closed triangle-mesh primitives for procedural scenes (world frame z up, metres).

Every builder returns ``(vertices [V, 3] float64, triangles [F, 3] int32)`` with outward,
counter-clockwise faces. Flat faces get their own vertices, so per-vertex normals averaged
from adjacent faces are exact on flat faces and smooth on curved ones. All shapes are closed,
which lets the ground truth test whether a point lies inside a part.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]


def _frame_from_axis(axis: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] whose third column is the unit ``axis``."""
    z = np.asarray(axis, float)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_x(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def transform(mesh: Mesh, R: Optional[np.ndarray] = None,
              t: Sequence[float] = (0.0, 0.0, 0.0)) -> Mesh:
    """``R @ v + t`` for every vertex (faces keep their orientation for proper rotations)."""
    v, f = mesh
    if R is not None:
        v = v @ np.asarray(R, float).T
    return v + np.asarray(t, float), f


def merge(meshes: Sequence[Mesh]) -> Mesh:
    """One mesh holding all of ``meshes`` (no welding)."""
    vs, fs, n = [], [], 0
    for v, f in meshes:
        vs.append(v)
        fs.append(f + n)
        n += v.shape[0]
    if not vs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32)
    return np.concatenate(vs), np.concatenate(fs).astype(np.int32)


def hexahedron(corners: np.ndarray) -> Mesh:
    """A closed six-faced solid from 8 corners: bottom face 0-3, top face 4-7 (same order).

    Corners 0-3 must run counter-clockwise seen from above the top face (outward = +normal of
    face 4-7). Used for boxes, tapered swept wings, fins, pylons.
    """
    c = np.asarray(corners, float).reshape(8, 3)
    quads = [(3, 2, 1, 0), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    vs, fs = [], []
    for k, q in enumerate(quads):
        vs.append(c[list(q)])
        b = 4 * k
        fs += [(b, b + 1, b + 2), (b, b + 2, b + 3)]
    v = np.concatenate(vs)
    f = np.array(fs, np.int32)
    # make faces point away from the centroid whatever order the caller used
    centre = c.mean(0)
    tri = v[f]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", nrm, tri.mean(1) - centre) < 0
    f[flip] = f[flip][:, ::-1]
    return v, f


def box(size: Sequence[float], center: Sequence[float] = (0, 0, 0),
        R: Optional[np.ndarray] = None) -> Mesh:
    """Axis-aligned box of ``size`` (sx, sy, sz) centred at ``center`` (then rotated by R)."""
    sx, sy, sz = np.asarray(size, float) / 2
    c = np.array([[-sx, -sy, -sz], [sx, -sy, -sz], [sx, sy, -sz], [-sx, sy, -sz],
                  [-sx, -sy, sz], [sx, -sy, sz], [sx, sy, sz], [-sx, sy, sz]])
    if R is not None:
        c = c @ np.asarray(R, float).T
    return hexahedron(c + np.asarray(center, float))


def lathe(profile: Sequence[tuple[float, float]], segments: int = 24) -> Mesh:
    """Solid of revolution about +z of the (radius, z) ``profile`` (z increasing).

    An end with non-zero radius is closed by a flat cap; an end with radius 0 is a pole.
    """
    prof = np.asarray(profile, float)
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ca, sa = np.cos(a), np.sin(a)
    rings = [np.stack([r * ca, r * sa, np.full(segments, z)], 1) for r, z in prof]
    v = np.concatenate(rings)
    fs = []
    m = len(prof)
    for i in range(m - 1):
        for j in range(segments):
            a0, a1 = i * segments + j, i * segments + (j + 1) % segments
            b0, b1 = a0 + segments, a1 + segments
            if prof[i, 0] > 0:
                fs.append((a0, a1, b1))
            if prof[i + 1, 0] > 0:
                fs.append((a0, b1, b0))
    vs = [v]
    n = v.shape[0]
    for end, sign in ((0, -1.0), (m - 1, 1.0)):
        r, z = prof[end]
        if r <= 0:
            continue
        rim = np.stack([r * ca, r * sa, np.full(segments, z)], 1)
        cap = np.concatenate([[[0.0, 0.0, z]], rim])
        vs.append(cap)
        for j in range(segments):
            i0, i1 = n + 1 + j, n + 1 + (j + 1) % segments
            fs.append((n, i0, i1) if sign > 0 else (n, i1, i0))
        n += cap.shape[0]
    f = np.array(fs, np.int32)
    return np.concatenate(vs), f


def cylinder(p0: Sequence[float], p1: Sequence[float], radius: float,
             segments: int = 16, radius1: Optional[float] = None) -> Mesh:
    """Closed cylinder (or truncated cone with ``radius1`` at p1) from p0 to p1."""
    p0 = np.asarray(p0, float)
    p1 = np.asarray(p1, float)
    length = float(np.linalg.norm(p1 - p0))
    r1 = radius if radius1 is None else radius1
    mesh = lathe([(radius, 0.0), (r1, length)], segments)
    return transform(mesh, _frame_from_axis(p1 - p0), p0)


def sphere(center: Sequence[float], radius: float, segments: int = 24,
           scale: Sequence[float] = (1.0, 1.0, 1.0)) -> Mesh:
    """UV sphere (an ellipsoid with per-axis ``scale``)."""
    rings = max(segments // 2, 4)
    th = np.linspace(0, np.pi, rings + 1)
    prof = [(radius * np.sin(t) if 0 < k < rings else 0.0, -radius * np.cos(t))
            for k, t in enumerate(th)]
    v, f = lathe(prof, segments)
    return v * np.asarray(scale, float) + np.asarray(center, float), f


def torus(center: Sequence[float], axis: Sequence[float], major: float, minor: float,
          segments: int = 48, tube_segments: int = 10) -> Mesh:
    """Closed torus (a wheel tyre or rim) around ``axis`` through ``center``."""
    u = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    w = np.linspace(0, 2 * np.pi, tube_segments, endpoint=False)
    uu, ww = np.meshgrid(u, w, indexing="ij")
    rr = major + minor * np.cos(ww)
    v = np.stack([rr * np.cos(uu), rr * np.sin(uu), minor * np.sin(ww)], -1).reshape(-1, 3)
    fs = []
    for i in range(segments):
        for j in range(tube_segments):
            a = i * tube_segments + j
            b = ((i + 1) % segments) * tube_segments + j
            c = ((i + 1) % segments) * tube_segments + (j + 1) % tube_segments
            d = i * tube_segments + (j + 1) % tube_segments
            fs += [(a, b, c), (a, c, d)]
    mesh = (v, np.array(fs, np.int32))
    return transform(mesh, _frame_from_axis(axis), center)


def blob(center: Sequence[float], radius: float, rng: np.random.Generator,
         roughness: float = 0.25, scale: Sequence[float] = (1.0, 1.0, 1.0),
         segments: int = 20) -> Mesh:
    """A lumpy closed shape (bush, canopy, stone): a sphere displaced by random harmonics."""
    v, f = sphere((0, 0, 0), 1.0, segments)
    d = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
    disp = np.zeros(len(v))
    for k in range(6):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        freq = rng.uniform(1.5, 4.5)
        phase = rng.uniform(0, 2 * np.pi)
        disp += rng.uniform(0.3, 1.0) / (k + 1) * np.sin(freq * (d @ axis) * np.pi + phase)
    disp = 1.0 + roughness * disp / max(np.abs(disp).max(), 1e-9)
    v = d * disp[:, None] * radius * np.asarray(scale, float)
    return v + np.asarray(center, float), f


def panel(corners: np.ndarray, thickness: float) -> Mesh:
    """A slab of ``thickness`` behind the planar quad ``corners`` [4, 3] (counter-clockwise)."""
    c = np.asarray(corners, float).reshape(4, 3)
    n = np.cross(c[1] - c[0], c[2] - c[0])
    n /= np.linalg.norm(n)
    return hexahedron(np.concatenate([c - n * thickness, c]))


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted per-vertex normals [V, 3] (unit; zero where a vertex has no face)."""
    tri = vertices[triangles]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, triangles[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.where(norm > 0, vn / np.maximum(norm, 1e-30), 0.0)
