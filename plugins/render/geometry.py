"""Meshes for rendering: built-in primitives with UVs, PLY/OBJ files (see .meshfile), transforms, tangent frames.

Every mesh ends up as world-space triangles with per-corner attributes (``[F, 3, ...]``): UV, shading normal,
tangent and bitangent.  Tangents come from the parameterization - ``T`` along dP/du, ``B`` toward dP/dv - so a
light expressed in the frame ``(T, B, N)`` is in the texture's own frame: x along the texture's columns, y toward
its top row, z out of the surface, the frame an RTI capture (and the model fitted to it) uses.

UV convention: ``u`` runs along a model's columns (u = 0 at the left edge, 1 at the right), ``v`` up its rows
(v = 1 at row 0, the top of the image).  The primitives are parameterized so that, seen from outside, ``T x B``
is the outward normal:

* plane: in the local xy plane, normal +z, u along +x, v along +y, UV (0, 0)-(1, 1) across the plane;
* sphere: poles on the local y axis, u = longitude (0.5 faces +z, increasing toward +x), v = latitude (1 at +y);
* torus: around the local z axis, u around the ring (counter-clockwise seen from +z), v around the tube (0 at the
  outer equator, increasing upward);
* cube: every face carries the whole texture, upright (v toward +y, or toward -z / +z on the top / bottom faces).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from btforge.errors import BtforgeInputError

from .o3d import open3d
from .scene import MeshSpec, Scene

DEFAULT_SEGMENTS = {"plane": (1, 1), "sphere": (128, 64), "torus": (96, 48)}
WELD_TOLERANCE = 1e-6  # positions closer than this fraction of the mesh's bounding-box diagonal are one vertex


@dataclasses.dataclass
class BuiltMesh:
    """A mesh in world space, ready to ray-cast and shade."""

    spec: MeshSpec
    positions: np.ndarray   # [V, 3] float32
    triangles: np.ndarray   # [F, 3] int32
    corner_uv: np.ndarray   # [F, 3, 2] float32 (zeros when the mesh has none)
    corner_n: np.ndarray    # [F, 3, 3] float32 unit shading normals
    corner_t: np.ndarray    # [F, 3, 3] float32 unit tangents (dP/du)
    corner_b: np.ndarray    # [F, 3, 3] float32 unit bitangents (toward dP/dv, perpendicular to T and N)
    welded: np.ndarray      # [F, 3] int32 triangles with coincident positions merged (see :func:`weld`)
    closed: bool
    convex: bool

    @property
    def name(self) -> str:
        return self.spec.name


# ----------------------------------------------------------------------------------------------- primitives


def _grid(nu: int, nv: int):
    i, j = np.meshgrid(np.arange(nu + 1), np.arange(nv + 1))
    return (i / nu).ravel(), (j / nv).ravel()


def _quads(nu: int, nv: int, drop_first_row_lower: bool = False, drop_last_row_upper: bool = False) -> np.ndarray:
    stride = nu + 1
    j, i = np.meshgrid(np.arange(nv), np.arange(nu), indexing="ij")
    a = (j * stride + i).ravel()
    b, c, d = a + 1, a + stride + 1, a + stride
    jj = j.ravel()
    lower = np.stack([a, b, c], 1)
    upper = np.stack([a, c, d], 1)
    if drop_first_row_lower:  # at the south pole a and b coincide
        lower = lower[jj != 0]
    if drop_last_row_upper:   # at the north pole c and d coincide
        upper = upper[jj != nv - 1]
    return np.concatenate([lower, upper]).astype(np.int32)


def make_primitive(spec: MeshSpec):
    """``(positions [V, 3], triangles [F, 3], uv [V, 2], normals [V, 3])`` of a primitive, in its local frame."""
    if spec.primitive != "cube":  # a cube is six flat quads: the scene refuses segments for it
        nu, nv = spec.segments or DEFAULT_SEGMENTS[spec.primitive]
    if spec.primitive == "plane":
        u, v = _grid(nu, nv)
        sx, sy = spec.size
        pos = np.stack([(u - 0.5) * sx, (v - 0.5) * sy, np.zeros_like(u)], 1)
        normals = np.tile([0.0, 0.0, 1.0], (len(u), 1))
        return pos, _quads(nu, nv), np.stack([u, v], 1), normals
    if spec.primitive == "sphere":
        u, v = _grid(nu, nv)
        lon = 2 * np.pi * (u - 0.5)
        lat = np.pi * (v - 0.5)
        n = np.stack([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)], 1)
        return n * spec.radius, _quads(nu, nv, True, True), np.stack([u, v], 1), n
    if spec.primitive == "torus":
        u, v = _grid(nu, nv)
        a, b = 2 * np.pi * u, 2 * np.pi * v
        big, small = spec.major_radius, spec.minor_radius
        ring = big + small * np.cos(b)
        pos = np.stack([ring * np.cos(a), ring * np.sin(a), small * np.sin(b)], 1)
        n = np.stack([np.cos(b) * np.cos(a), np.cos(b) * np.sin(a), np.sin(b)], 1)
        return pos, _quads(nu, nv), np.stack([u, v], 1), n
    # cube: (normal, u axis, v axis) with u x v = normal
    faces = [((0, 0, 1), (1, 0, 0), (0, 1, 0)), ((0, 0, -1), (-1, 0, 0), (0, 1, 0)),
             ((1, 0, 0), (0, 0, -1), (0, 1, 0)), ((-1, 0, 0), (0, 0, 1), (0, 1, 0)),
             ((0, 1, 0), (1, 0, 0), (0, 0, -1)), ((0, -1, 0), (1, 0, 0), (0, 0, 1))]
    half = spec.size[0] / 2
    pos, tris, uv, normals = [], [], [], []
    for k, (n, au, av) in enumerate(faces):
        n, au, av = (np.asarray(x, float) for x in (n, au, av))
        for cu, cv in ((0, 0), (1, 0), (1, 1), (0, 1)):
            pos.append(n * half + (2 * cu - 1) * half * au + (2 * cv - 1) * half * av)
            uv.append((cu, cv))
            normals.append(n)
        tris += [(4 * k, 4 * k + 1, 4 * k + 2), (4 * k, 4 * k + 2, 4 * k + 3)]
    return np.asarray(pos), np.asarray(tris, np.int32), np.asarray(uv, float), np.asarray(normals)


# ----------------------------------------------------------------------------------------------- files

def read_mesh_file(path: str, where: str = "") -> dict[str, np.ndarray]:
    """Read a PLY/OBJ triangle mesh: ``positions [V, 3]``, ``triangles [F, 3]``, ``corner_uv [F, 3, 2]``
    (``[0, 3, 2]`` when the file has no texture coordinates).  The file is parsed and checked in NumPy
    (:mod:`.meshfile`), so a damaged file is refused before any array reaches open3d."""
    from .meshfile import read_mesh
    try:
        return read_mesh(path)
    except BtforgeInputError as exc:
        raise exc.located(where) if where else exc


# ----------------------------------------------------------------------------------------------- frames


def _normalize(v: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    out = v / np.where(n > 1e-20, n, 1.0)
    if fallback is not None:
        out = np.where(n > 1e-20, out, fallback)
    return out


def _any_perpendicular(n: np.ndarray) -> np.ndarray:
    axis = np.where(np.abs(n[..., :1]) < 0.9, np.array([1.0, 0, 0]), np.array([0, 1.0, 0]))
    return _normalize(np.cross(np.cross(n, axis), n))


def vertex_normals(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals."""
    p = positions[triangles]
    face = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # length = 2 x area
    acc = np.zeros_like(positions, dtype=np.float64)
    for k in range(3):
        np.add.at(acc, triangles[:, k], face)
    return _normalize(acc, np.array([0.0, 0.0, 1.0]))


def tangent_frames(positions: np.ndarray, triangles: np.ndarray, corner_uv: np.ndarray,
                   corner_normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-corner unit tangents (along dP/du) and bitangents (toward dP/dv), orthogonal to the corner normals.

    Each triangle's dP/du and dP/dv (from its edges and UV differences) are accumulated, weighted by the
    triangle's area, over the corners that share a vertex *and* a UV (so a UV seam keeps two frames), then
    Gram-Schmidt-orthogonalised against the normal.  The bitangent is ``+-N x T``, the sign following dP/dv, so a
    mirrored parameterization gives a mirrored (left-handed) frame, as the texture is then seen mirrored.
    """
    p = positions[triangles].astype(np.float64)
    uv = corner_uv.astype(np.float64)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(det) > 1e-14
    safe = np.where(ok, det, 1.0)[:, None]
    t = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / safe
    b = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) / safe
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)[:, None] * ok[:, None]
    t, b = _normalize(t) * area, _normalize(b) * area
    # corners sharing a vertex and a UV share a frame
    keys = np.concatenate([triangles.reshape(-1, 1).astype(np.float64), uv.reshape(-1, 2)], 1)
    _, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    acc_t = np.zeros((inverse.max() + 1, 3))
    acc_b = np.zeros_like(acc_t)
    np.add.at(acc_t, inverse, np.repeat(t, 3, axis=0))
    np.add.at(acc_b, inverse, np.repeat(b, 3, axis=0))
    n = corner_normals.reshape(-1, 3).astype(np.float64)
    ct, cb = complete_frame(n, acc_t[inverse], acc_b[inverse])
    return ct.reshape(-1, 3, 3), cb.reshape(-1, 3, 3)


def complete_frame(n: np.ndarray, t: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents and bitangents ``[N, 3]`` about the unit normals ``n``: ``t`` Gram-Schmidt-orthogonalised
    against ``n``, the bitangent ``+-n x t`` with the sign of ``b``'s side, so a mirrored parameterization keeps its
    mirrored (left-handed) frame while the frame stays exactly orthonormal."""
    t = _normalize(t - n * np.sum(n * t, axis=-1, keepdims=True))
    missing = np.linalg.norm(t, axis=-1) < 0.5
    if missing.any():  # no UV gradient there (or one along the normal): any frame about n lights it consistently
        t[missing] = _any_perpendicular(n[missing])
    sign = np.where(np.sum(np.cross(n, t) * b, axis=-1) < 0, -1.0, 1.0)[..., None]
    return t, sign * np.cross(n, t)


def _rotation(degrees) -> np.ndarray:
    rx, ry, rz = np.radians(degrees)
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    mx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    my = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    mz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return mz @ my @ mx


def build_mesh(spec: MeshSpec, scene: Scene | None = None) -> BuiltMesh:
    """The world-space mesh of ``spec`` (primitive, or a file whose contents ``scene`` holds)."""
    if spec.primitive:
        pos, tris, uv, normals = make_primitive(spec)
        welded = weld(pos, tris)
        corner_uv = uv[tris]
        corner_n = normals[tris]
        closed = spec.closed
    else:
        content = scene.file_arrays(spec.file)
        pos = content["positions"].astype(np.float64)
        tris = content["triangles"].astype(np.int64)
        welded = weld(pos, tris)
        has_uv = content["corner_uv"].shape[0] == len(tris)
        corner_uv = content["corner_uv"].astype(np.float64) if has_uv else np.zeros((len(tris), 3, 2))
        corner_n = vertex_normals(pos, welded)[welded]   # smooth across UV seams, as the surface is
        closed = is_closed(welded)
    corner_t, corner_b = tangent_frames(pos, tris, corner_uv, corner_n)

    linear = _rotation(spec.rotate) @ np.diag(spec.scale)
    normal_matrix = np.linalg.inv(linear).T
    pos = pos @ linear.T + np.asarray(spec.position)
    corner_n = _normalize(corner_n @ normal_matrix.T)
    corner_t = _normalize(corner_t @ linear.T)
    corner_b = _normalize(corner_b @ linear.T)
    if np.linalg.det(linear) < 0:  # a mirroring transform flips the winding; keep faces pointing outward
        order = [0, 2, 1]
        tris, welded, corner_uv, corner_n = tris[:, order], welded[:, order], corner_uv[:, order], corner_n[:, order]
        corner_t, corner_b = corner_t[:, order], corner_b[:, order]
    return BuiltMesh(spec, pos.astype(np.float32), tris.astype(np.int32), corner_uv.astype(np.float32),
                     corner_n.astype(np.float32), corner_t.astype(np.float32), corner_b.astype(np.float32),
                     welded.astype(np.int32), closed, spec.convex)


def weld(positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``triangles`` re-indexed so that vertices at one position share one index (the first of them).

    A mesh file's vertices are split wherever texture coordinates differ (an OBJ vertex used with several
    texture coordinates is read as one vertex per coordinate), which cuts the surface open along its UV seams;
    closedness, inside tests and smooth normals need the surface's own connectivity.  Positions within
    :data:`WELD_TOLERANCE` of the mesh's size are one vertex, so float noise from an exporter does not reopen a
    seam.
    """
    pos = np.asarray(positions, np.float64)
    low = pos.min(0)
    step = max(float(np.linalg.norm(pos.max(0) - low)), 1e-30) * WELD_TOLERANCE
    keys = np.round((pos - low) / step).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    return first[inverse.ravel()][triangles]


def is_closed(triangles: np.ndarray) -> bool:
    """Whether every edge of the (welded) ``triangles`` is shared by exactly two triangles (a watertight surface).

    Triangles that welding collapsed (two corners at one position, e.g. at a pole) enclose nothing and are left out.
    """
    t = triangles[(triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2])
                  & (triangles[:, 2] != triangles[:, 0])]
    edges = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(len(counts) and np.all(counts == 2))


def point_inside(mesh: BuiltMesh, point: np.ndarray) -> bool:
    """Whether ``point`` lies inside the closed ``mesh`` (odd crossings along most of three rays).

    The welded triangles are cast so a ray through a UV seam meets the surface once, not zero or two times.
    """
    o3d = open3d()

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(mesh.positions, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(mesh.welded, np.uint32)))
    dirs = np.array([[0.5773, 0.5774, 0.5773], [-0.2673, 0.5345, -0.8018], [0.8729, -0.2182, 0.4364]])
    rays = np.concatenate([np.tile(point, (3, 1)), dirs], 1).astype(np.float32)
    counts = scene.count_intersections(o3d.core.Tensor(rays)).numpy()
    return int(np.sum(counts % 2 == 1)) >= 2
