"""Dressing meshes with a Wang tile set (``tiles: true``): the renderer's lookup from a surface point to an
exemplar texel.

Each chart of a mesh's UV layout (the whole UV square of a plane, torus or sphere; each face of the cube) is
divided into ``uv_scale`` cells per unit of UV, tiled once per render by :func:`tiling.mesh_tiling` (seed
``TILING_SEED``) so that colours match across every shared edge, cube faces and wraps included.  A sample at
UV ``(u, v)`` in chart ``k`` reads the texel grid of ``nv * w`` rows and ``nu * w`` columns spanning the chart
(texel centres as :func:`lookup.texel_corners` places them), and each texel goes tile index -> BTFel index ->
exemplar texel: the model is evaluated at the table's texels, so a surface costs the tile set, not a texture.
Bilinear lookups that cross a cell border read the neighbouring cell's tile; on a chart's border they clamp
(multi-chart meshes) or follow the mesh's ``wrap`` (one chart).
"""
from __future__ import annotations

import numpy as np

from btforge.errors import BtforgeInputError

from btforge.plugins.wang.tileset import TileSet
from btforge.plugins.wang.tiling import MeshTiling, mesh_tiling

from .lookup import texel_corners

TILING_SEED = 0


def cells_of(spec) -> tuple[int, int]:
    return int(round(spec.uv_scale[0])), int(round(spec.uv_scale[1]))


def tiling_of(built, mesh_index: int, tiles: TileSet) -> MeshTiling:
    """The mesh's tiling, made on first use and kept on the built scene (one per render, whatever the bands)."""
    key = (mesh_index, tiles.content_key)
    if key not in built.tilings:
        mesh = built.meshes[mesh_index]
        built.tilings[key] = mesh_tiling(mesh.positions, mesh.triangles, mesh.corner_uv, cells_of(mesh.spec), tiles,
                                         TILING_SEED, where=f"render, mesh '{mesh.name}'")
    return built.tilings[key]


def tiled_texels(built, mesh_index: int, tiles: TileSet, triangles: np.ndarray, uv: np.ndarray, blend: bool = True):
    """``(rows, cols, weights)`` ``[4, N]`` of the exemplar texels around each sample (the renderer's bilinear
    corners), read through the mesh's tiling; ``[8, N]`` where the set has a blend layer and the model blends
    (``blend``): each corner's partner with its share of the corner's weight (else each corner's heavier texel)."""
    mesh = built.meshes[mesh_index]
    tiling = tiling_of(built, mesh_index, tiles)
    nu, nv = cells_of(mesh.spec)
    w = tiles.tile
    grids = np.stack(tiling.grids)                                   # [charts, nv, nu]
    wrap = "clamp" if len(grids) > 1 else mesh.spec.wrap
    rows, cols, weights = texel_corners(uv, nv * w, nu * w, wrap)
    chart = np.broadcast_to(tiling.charts[triangles], rows.shape)
    tile = grids[chart, rows // w, cols // w]
    at = (tile, rows % w, cols % w)
    btfel = tiles.indices[at]
    if tiles.blends:
        share = tiles.blend_weight[at].astype(np.float64)
        if blend:
            btfel = np.concatenate([btfel, tiles.blend_indices[at]])
            weights = np.concatenate([weights * (1 - share), weights * share])
        else:
            btfel = np.where(share > 0.5, tiles.blend_indices[at], btfel)
    texels = tiles.table[btfel]
    return texels[..., 0].astype(np.int64), texels[..., 1].astype(np.int64), weights


def check_tiles(name: str, model, tiles) -> None:
    if not isinstance(tiles, TileSet):
        raise BtforgeInputError(f"render, material '{name}'", f"a mesh sets tiles: true but no TileSet is wired to "
                                f"'{name}_tiles'", f"wire a tile set (wang.tiles or wang.read_tiles) to '{name}_tiles'")
    if (model.height, model.width) != tiles.source_size:
        raise BtforgeInputError(f"render, material '{name}'", f"the tile set indexes a {tiles.source_size[0]} x "
                                f"{tiles.source_size[1]} exemplar, but the model is {model.height} x {model.width}",
                                "wire the tile set synthesized from this model's exemplar")
