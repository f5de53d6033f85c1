"""Mesh files are read split at UV seams (open3d splits vertices by position and UV); the renderer must still see
one closed, smooth surface: welded for closedness, inside tests and normals, per split vertex for UVs."""

import numpy as np
import pytest

from btforge.errors import BtforgeInputError
from btforge.plugins.render.geometry import build_mesh
from btforge.plugins.render.loader import load_scene
from btforge.stages import RunPaths

# a 2-unit cube, 8 positions, every face carrying the whole texture (4 texture coordinates), outward winding
CUBE_OBJ = "".join(f"v {x} {y} {z}\n" for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)) + \
    "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n" + "".join(
        f"f {a}/1 {b}/2 {c}/3\nf {a}/1 {c}/3 {d}/4\n"
        for a, b, c, d in ((1, 2, 4, 3), (5, 7, 8, 6), (1, 5, 6, 2), (3, 4, 8, 7), (1, 3, 7, 5), (2, 6, 8, 4)))


def uv_sphere_obj(nu: int = 24, nv: int = 12) -> str:
    """A unit UV sphere as an exporter writes it: each position once (shared across the seam and at the poles),
    a texture coordinate per grid point, so the seam and pole corners reference one 'v' with different 'vt'."""
    i, j = np.meshgrid(np.arange(nu + 1), np.arange(nv + 1))
    u, v = (i / nu).ravel(), (j / nv).ravel()
    lon, lat = 2 * np.pi * (u - 0.5), np.pi * (v - 0.5)
    grid = np.stack([np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon)], 1)
    positions, vertex_of = np.unique(np.round(grid, 9), axis=0, return_inverse=True)
    vertex_of = vertex_of.ravel()
    lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in positions] + [f"vt {a:.9f} {b:.9f}" for a, b in zip(u, v)]
    stride = nu + 1
    for jj in range(nv):
        for ii in range(nu):
            a = jj * stride + ii
            for tri in ((a, a + 1, a + stride + 1), (a, a + stride + 1, a + stride)):
                if len({vertex_of[k] for k in tri}) == 3:           # the pole rows have one collapsed triangle
                    lines.append("f " + " ".join(f"{vertex_of[k] + 1}/{k + 1}" for k in tri))
    return "\n".join(lines) + "\n"


def scene_with(mesh: dict, lights=()) -> dict:
    return {"camera": {"type": "orthographic", "width": 8, "height": 8, "position": [0, 0, 5], "extent": 3.0},
            "meshes": {"shape": mesh}, "lights": list(lights)}


def test_point_light_inside_a_textured_cube_file_is_refused(tmp_path):
    (tmp_path / "cube.obj").write_text(CUBE_OBJ)
    paths = RunPaths(tmp_path, tmp_path)
    mesh = {"file": "cube.obj", "material": "stone"}
    with pytest.raises(BtforgeInputError, match=r"lights\[0\].position: point light at \[0.2, 0.1, -0.3\] is inside "
                                                r"the closed mesh 'shape'"):
        load_scene(scene_with(mesh, [{"type": "point", "position": [0.2, 0.1, -0.3]}]), paths)
    scene = load_scene(scene_with(mesh, [{"type": "point", "position": [0.2, 0.1, 3.0]}]), paths)   # outside: fine
    built = build_mesh(scene.spec.meshes[0], scene)
    assert built.closed and len(built.positions) > 8                 # closed although read split at the seams
    assert len(np.unique(built.welded)) == 8


def test_open_mesh_file_is_not_closed(tmp_path):
    (tmp_path / "box.obj").write_text(CUBE_OBJ.rsplit("f ", 2)[0])  # the last face's two triangles removed
    scene = load_scene(scene_with({"file": "box.obj", "material": "stone"},
                                  [{"type": "point", "position": [0, 0, 0]}]), RunPaths(tmp_path, tmp_path))
    assert not build_mesh(scene.spec.meshes[0], scene).closed      # a light in an open box is allowed


def test_normals_of_a_sphere_file_are_continuous_across_its_uv_seam(tmp_path):
    (tmp_path / "ball.obj").write_text(uv_sphere_obj())
    scene = load_scene(scene_with({"file": "ball.obj", "material": "stone"}), RunPaths(tmp_path, tmp_path))
    built = build_mesh(scene.spec.meshes[0], scene)
    assert built.closed
    corners = built.positions[built.triangles].reshape(-1, 3)
    normals = built.corner_n.reshape(-1, 3).astype(np.float64)
    _, vertex = np.unique(np.round(corners, 5), axis=0, return_inverse=True)
    vertex = vertex.ravel()
    on_seam = np.abs(corners[:, 0]) < 1e-6                          # the seam (and the poles) lie in x = 0
    first = np.zeros((vertex.max() + 1, 3))
    first[vertex] = normals
    spread = np.linalg.norm(normals - first[vertex], axis=1)
    assert on_seam.sum() > 20 and spread.max() < 1e-6               # every corner at a position: one normal
    radial = np.degrees(np.arccos(np.clip(np.sum(normals * corners / np.linalg.norm(corners, axis=1)[:, None], 1),
                                          -1, 1)))
    # and it is the sphere's: by symmetry about the poles every vertex of a row leans off the radial direction
    # alike (area weighting leans toward the poles), the seam's as much as any
    rows = np.round(corners[:, 1], 5)
    for y in np.unique(rows):
        lean = radial[rows == y]
        assert lean.max() - lean.min() < 0.05, (y, lean.min(), lean.max())   # float32 arccos noise: 0.013
    # UVs stay per split vertex: seam corners carry u = 0 on one side and u = 1 on the other
    seam_u = built.corner_uv.reshape(-1, 2)[on_seam & (np.abs(corners[:, 1]) < 0.99), 0]
    assert {0.0, 1.0} <= set(np.round(seam_u, 6).tolist())
