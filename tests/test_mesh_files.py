"""PLY and OBJ meshes are parsed and checked in NumPy: valid files read as open3d reads them, damaged ones are
refused with the file, the line or element, and what was wrong."""
import numpy as np
import pytest

from btforge.errors import BtforgeInputError
from btforge.plugins.height.io import height_mesh_ply
from btforge.plugins.render.meshfile import read_mesh

QUAD_PLY_HEADER = ("ply\nformat {fmt} 1.0\ncomment a unit quad\nelement vertex 4\nproperty float x\nproperty float y\n"
                   "property float z\nproperty float s\nproperty float t\nelement face {faces}\n"
                   "property list uchar int vertex_indices\nend_header\n")
ASCII_QUAD = QUAD_PLY_HEADER.format(fmt="ascii", faces=1)
QUAD = np.array([[-1, -1, 0, 0, 0], [1, -1, 0, 1, 0], [1, 1, 0, 1, 1], [-1, 1, 0, 0, 1]], np.float32)


def binary_quad(order: str, faces: list[list[int]]) -> bytes:
    fmt = {"<": "binary_little_endian", ">": "binary_big_endian"}[order]
    body = QUAD.astype(order + "f4").tobytes()
    for face in faces:
        body += np.uint8(len(face)).tobytes() + np.asarray(face, order + "i4").tobytes()
    return QUAD_PLY_HEADER.format(fmt=fmt, faces=len(faces)).encode() + body


@pytest.mark.parametrize("order", ["<", ">"])
def test_binary_ply_of_either_byte_order_with_a_quad_and_a_triangle(tmp_path, order):
    path = tmp_path / "q.ply"
    path.write_bytes(binary_quad(order, [[0, 1, 2, 3], [0, 2, 1]]))
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh["positions"], QUAD[:, :3])
    np.testing.assert_array_equal(mesh["triangles"], [[0, 1, 2], [0, 2, 3], [0, 2, 1]])   # the quad fanned
    np.testing.assert_array_equal(mesh["corner_uv"][1], QUAD[[0, 2, 3], 3:])


def test_ascii_ply_and_obj_read_the_same_quad(tmp_path):
    rows = "".join(" ".join(f"{v:g}" for v in row) + "\n" for row in QUAD)
    (tmp_path / "q.ply").write_text(QUAD_PLY_HEADER.format(fmt="ascii", faces=1) + rows + "4 0 1 2 3\n")
    obj = "".join(f"v {x:g} {y:g} {z:g}\nvt {u:g} {v:g}\n" for x, y, z, u, v in QUAD) + "f -4/-4 -3/-3 -2/-2 -1/-1\n"
    (tmp_path / "q.obj").write_text(obj)
    ply, from_obj = read_mesh(tmp_path / "q.ply"), read_mesh(tmp_path / "q.obj")
    for name in ("positions", "triangles", "corner_uv"):
        np.testing.assert_array_equal(ply[name], from_obj[name])


def test_height_mesh_reads_as_open3d_reads_it(tmp_path):
    from btforge.plugins.render.o3d import open3d
    heights = np.random.default_rng(0).normal(0, 1, (7, 9)).astype(np.float32)
    path = tmp_path / "h.ply"
    path.write_bytes(height_mesh_ply(heights))
    ours = read_mesh(path)
    theirs = open3d().io.read_triangle_mesh(str(path), enable_post_processing=False)
    np.testing.assert_array_equal(ours["positions"], np.asarray(theirs.vertices, np.float32))
    np.testing.assert_array_equal(ours["triangles"], np.asarray(theirs.triangles))


def test_obj_vertex_with_two_texture_coordinates_is_split(tmp_path):
    (tmp_path / "t.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\nvt 0.5 0.5\n"
                                    "f 1/1 2/2 3/3\nf 2/5 4/4 3/3\n")
    mesh = read_mesh(tmp_path / "t.obj")
    assert len(mesh["positions"]) == 5     # vertex 2 carries two texture coordinates
    np.testing.assert_array_equal(mesh["corner_uv"][1, 0], [0.5, 0.5])


@pytest.mark.parametrize("name, content, message", [
    ("index.ply", binary_quad("<", [[0, 1, 7]]), r"indices must be integers in \[0, 4\), found 0 to 7"),
    ("count.ply", binary_quad("<", [[0, 1, 2]]).replace(b"element vertex 4", b"element vertex 400000000"),
     "declares 400000000 rows of at least 20 bytes, but only"),
    ("short.ply", binary_quad("<", [[0, 1, 2]])[:-5], "element 'face' runs past the end of the file"),
    ("nan.ply", ASCII_QUAD + "nan 0 0 0 0\n1 0 0 0 0\n0 1 0 0 0\n0 0 1 0 0\n3 0 1 2\n", "NaN/Inf vertex positions"),
    ("text.ply", ASCII_QUAD + "0 0 0 0 0\n1 0 0 0 0\n0 one 0 0 0\n0 0 1 0 0\n3 0 1 2\n",
     r"line 15: expected numbers, found b?'0 one 0 0 0'"),
    ("header.ply", "ply\nformat ascii 1.0\nelement vertex -4\nend_header\n", "line 3: unreadable PLY header line"),
    ("nothing.ply", b"\x00\x01garbage", "is not a PLY file"),
    ("range.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "line 4: vertex index 4 is out of range: 3 vertexs"),
    ("zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "line 4: vertex index 0 is out of range"),
    ("points.obj", "v 0 0 0\nv 1 0 0\n", "has no faces"),
    ("huge.obj", "v 0 0 1e300\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "coordinates up to 1e\\+300"),
])
def test_damaged_meshes_are_refused_with_the_place_and_the_problem(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(BtforgeInputError, match=message) as info:
        read_mesh(path)
    assert name in str(info.value)
