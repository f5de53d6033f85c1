"""Files of a height field: normal maps (PNG, EXR), height images (EXR) and height meshes (PLY with UVs)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from btforge.atomic import atomic_output_path, atomic_write_bytes
from btforge.errors import BtforgeInputError

from .field import HeightField

NORMAL_FORMATS = (".png", ".exr")
HEIGHT_FORMATS = (".exr", ".ply")


def suffix_of(path: str, allowed: tuple[str, ...], where: str) -> str:
    suffix = Path(path).suffix.lower()
    if suffix not in allowed:
        raise BtforgeInputError(where, f"expected a path ending in {' or '.join(allowed)}, found '{Path(path).name}'",
                                f"name the file e.g. 'out{allowed[0]}'")
    return suffix


def normal_map_rgb8(field: HeightField) -> np.ndarray:
    """``[H, W, 3]`` uint8 ``round((n + 1) / 2 * 255)``: the OpenGL-style normal map (green = +y, up the image)."""
    return np.round((field.normals.astype(np.float64) + 1) * 0.5 * 255).clip(0, 255).astype(np.uint8)


def write_exr(path: Path, planes: dict[str, np.ndarray], attributes: dict | None = None) -> None:
    import OpenEXR
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(attributes or {})}
    channels = {name: np.ascontiguousarray(plane, np.float32) for name, plane in planes.items()}
    with atomic_output_path(path) as temporary:
        OpenEXR.File(header, channels).write(str(temporary))


def write_normals(field: HeightField, path: Path) -> None:
    if path.suffix.lower() == ".png":
        from PIL import Image
        with atomic_output_path(path) as temporary:
            Image.fromarray(normal_map_rgb8(field), "RGB").save(temporary, format="PNG")
    else:
        n = field.normals
        write_exr(path, {"R": n[..., 0], "G": n[..., 1], "B": n[..., 2]})


def write_height(field: HeightField, path: Path) -> None:
    if path.suffix.lower() == ".exr":
        write_exr(path, {"Y": field.heights}, {"btforgeUnits": "texels"})
    else:
        atomic_write_bytes(path, height_mesh_ply(field.heights))


def height_mesh_ply(heights: np.ndarray) -> bytes:
    """A binary PLY triangle mesh of ``heights``: one vertex per texel centre, two triangles per 2 x 2 texels.

    Vertex ``(x, y, z) = (col - (W-1)/2, (H-1)/2 - row, height)`` in texel widths (the texture frame, centred),
    with UVs ``u = (col + 0.5) / W``, ``v = 1 - (row + 0.5) / H`` (render's convention: v = 1 at the top row).
    Triangles wind counter-clockwise seen from above, so their normals point up.
    """
    H, W = heights.shape
    if H < 2 or W < 2:
        raise BtforgeInputError("height.write", f"a mesh needs at least 2 x 2 texels, found {H} x {W}",
                                "write an .exr instead")
    rows, cols = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    vertex = np.zeros(H * W, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("u", "<f4"), ("v", "<f4")])
    vertex["x"] = (cols - (W - 1) / 2).ravel()
    vertex["y"] = ((H - 1) / 2 - rows).ravel()
    vertex["z"] = heights.ravel()
    vertex["u"] = ((cols + 0.5) / W).ravel()
    vertex["v"] = (1 - (rows + 0.5) / H).ravel()
    a = (rows[:-1, :-1] * W + cols[:-1, :-1]).ravel()
    b, c, d = a + W, a + W + 1, a + 1        # below, below-right, right: counter-clockwise seen from +z
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    face = np.zeros(len(tris), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = tris
    header = ("ply\nformat binary_little_endian 1.0\ncomment btforge height field, texel units\n"
              f"element vertex {len(vertex)}\nproperty float x\nproperty float y\nproperty float z\n"
              "property float u\nproperty float v\n"
              f"element face {len(face)}\nproperty list uchar int vertex_indices\nend_header\n")
    return header.encode("ascii") + vertex.tobytes() + face.tobytes()


def describe_ply(path) -> dict:
    """``btforge info`` of a PLY mesh: counts, UVs, and the height (z) range it spans."""
    from btforge.plugins.render.geometry import read_mesh_file
    content = read_mesh_file(str(path))
    z = content["positions"][:, 2]
    return {"kind": "PLY triangle mesh", "vertices": int(len(content["positions"])),
            "triangles": int(len(content["triangles"])), "uv": bool(content["corner_uv"].size),
            "z_min": float(z.min()), "z_max": float(z.max()), "z_std": float(z.std())}
