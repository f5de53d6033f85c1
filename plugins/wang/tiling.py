"""Stochastic Wang tilings: of a ``rows x cols`` plane, and of the quad cells of a mesh's UV grid.

Both are one problem.  Every cell has four edge slots (N, E, S, W); slots that are the same edge of the surface
are *glued* and must carry one colour.  The glued slots form classes (union-find); each class draws its colour at
random, and each cell then takes a random variant of the tile with its four colours, which a complete set always
has.  A class that joins a horizontal and a vertical slot (where a surface turns the UV grid by 90 degrees, as at
some cube edges) needs a colour both kinds have: such a set must have ``colors_h == colors_v``.

Tiles are never rotated (a BTF has an orientation): each cell shows its tile in the cell's own UV frame.  Among
draws, the first (up to ``TILING_ATTEMPTS``) that uses every tile is kept when the surface has at least as many
cells as the set has tiles; a plane tiling is therefore random, valid and, with overwhelming probability, not
periodic.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from btforge.buffers import CoordMap
from btforge.errors import BtforgeInputError

N, E, S, W = range(4)
HORIZONTAL_SIDES = (N, S)
TILING_ATTEMPTS = 64
NEAREST_UV = 0.02  # UV distance within which a grid corner outside every triangle takes the nearest corner
CONSISTENT = {(E, W), (W, E), (S, N), (N, S)}


@dataclasses.dataclass
class Glue:
    """Two glued slots ``(cell, side)`` and whether the cells keep one orientation across the edge."""

    a: tuple[int, int]
    b: tuple[int, int]
    consistent: bool
    reversed: bool = False   # the two slots run along the edge in opposite directions


def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def colour_cells(n_cells: int, glues: list[Glue], colors_h: int, colors_v: int, rng: np.random.Generator,
                 where: str = "wang.tiling") -> np.ndarray:
    """Edge colours ``[n_cells, 4]`` (N, E, S, W) with every glued pair of slots equal."""
    parent = np.arange(n_cells * 4)
    for g in glues:
        ra, rb = _find(parent, g.a[0] * 4 + g.a[1]), _find(parent, g.b[0] * 4 + g.b[1])
        parent[ra] = rb
    roots = np.array([_find(parent, i) for i in range(n_cells * 4)])
    horizontal = np.isin(np.arange(n_cells * 4) % 4, HORIZONTAL_SIDES)
    classes, inverse = np.unique(roots, return_inverse=True)
    has_h = np.bincount(inverse, weights=horizontal, minlength=len(classes)) > 0
    has_v = np.bincount(inverse, weights=~horizontal, minlength=len(classes)) > 0
    mixed = has_h & has_v
    if mixed.any() and colors_h != colors_v:
        raise BtforgeInputError(where, f"the surface glues horizontal to vertical tile edges ({int(mixed.sum())} "
                                f"edges), which needs as many horizontal as vertical colours, found "
                                f"{colors_h} and {colors_v}", "build the tile set with colors [k, k]")
    count = np.where(has_h, colors_h, colors_v)
    colour = (rng.random(len(classes)) * count).astype(np.int64)
    return colour[inverse].reshape(n_cells, 4).astype(np.int32)


def choose_tiles(colors: np.ndarray, tile_colors: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random tile (among the variants) for each cell's colours ``[n, 4]``."""
    keys = [tuple(c) for c in tile_colors.tolist()]
    by_key: dict = {}
    for index, key in enumerate(keys):
        by_key.setdefault(key, []).append(index)
    out = np.empty(len(colors), np.int64)
    for i, key in enumerate(map(tuple, colors.tolist())):
        options = by_key.get(key)
        if options is None:
            raise BtforgeInputError("wang.tiling", f"the tile set has no tile with colours N, E, S, W = {key}",
                                    "build a complete set with wang.tiles")
        out[i] = options[int(rng.integers(len(options)))]
    return out


def tile_surface(n_cells: int, glues: list[Glue], tiles, rng: np.random.Generator, where: str = "wang.tiling"):
    """``(tile index per cell, colours [n, 4])``: a valid tiling, every tile used where there is room."""
    best = None
    for _ in range(TILING_ATTEMPTS):
        colors = colour_cells(n_cells, glues, tiles.colors_h, tiles.colors_v, rng, where)
        ids = choose_tiles(colors, tiles.tile_colors, rng)
        used = len(np.unique(ids))
        if best is None or used > best[2]:
            best = (ids, colors, used)
        if used == min(tiles.n_tiles, n_cells):
            break
    return best[0], best[1]


def grid_glues(rows: int, cols: int, periodic: bool) -> list[Glue]:
    """The glued slots of a ``rows x cols`` grid of cells (cell ``i * cols + j``), wrapping when periodic."""
    glues = []
    for i in range(rows):
        for j in range(cols):
            cell = i * cols + j
            if j + 1 < cols or periodic:
                glues.append(Glue((cell, E), (i * cols + (j + 1) % cols, W), True))
            if i + 1 < rows or periodic:
                glues.append(Glue((cell, S), (((i + 1) % rows) * cols + j, N), True))
    return glues


def plane_tiling(tiles, rows: int, cols: int, periodic: bool, seed: int) -> np.ndarray:
    """Tile indices ``[rows, cols]`` of a stochastic Wang tiling of the plane."""
    rng = np.random.default_rng(seed)
    ids, _ = tile_surface(rows * cols, grid_glues(rows, cols, periodic), tiles, rng)
    return ids.reshape(rows, cols)


def tiling_coords(tiles, ids: np.ndarray) -> np.ndarray:
    """The coordinate map ``[rows * w, cols * w, 2]`` of a tiling: tile (i, j) at rows i*w.., columns j*w.."""
    return _laid(tiles.tile_coords[ids])


def tiling_map(tiles, ids: np.ndarray, wrap: bool = False) -> CoordMap:
    """The tiling's coordinate map, with the tiles' blend layer laid out the same way where the set has one."""
    blend = {}
    if tiles.blends:
        blend = {"blend_coords": _laid(tiles.tile_blend_coords()[ids]), "blend_weight": _laid(tiles.blend_weight[ids])}
    return CoordMap(tiling_coords(tiles, ids), tiles.source_size, wrap=wrap, tile=tiles.tile, **blend)


def _laid(per_tile: np.ndarray) -> np.ndarray:
    """``[rows, cols, w, w, ...]`` per-tile arrays laid out as one ``[rows * w, cols * w, ...]`` grid."""
    rows, cols, w = per_tile.shape[:3]
    grid = per_tile.transpose(0, 2, 1, 3, *range(4, per_tile.ndim))
    return np.ascontiguousarray(grid.reshape(rows * w, cols * w, *per_tile.shape[4:]))


def is_periodic(ids: np.ndarray) -> bool:
    """Whether some shift of less than half the grid maps the tile IDs onto themselves where they overlap."""
    rows, cols = ids.shape
    for dy in range(0, (rows + 1) // 2):
        for dx in range(-(cols // 2), (cols + 1) // 2):
            if dy == 0 and dx <= 0:
                continue
            a = ids[dy:, max(0, dx):cols + min(0, dx)]
            b = ids[:rows - dy, max(0, -dx):cols - max(0, dx)]
            if a.size and np.array_equal(a, b):
                return True
    return False


# ----------------------------------------------------------------------------------------------- meshes


@dataclasses.dataclass
class MeshTiling:
    """A tiling of one mesh's UV grid: per chart (a connected piece of the UV layout) a grid of cells."""

    charts: np.ndarray          # [F] chart of each triangle
    grids: list                 # per chart: tile indices [rows, cols]
    colors: list                # per chart: colours [rows, cols, 4]
    glues: list                 # every glue, cells numbered chart by chart
    cells: int

    @property
    def rotated_glues(self) -> int:
        return sum(not g.consistent for g in self.glues)


def triangle_charts(triangles: np.ndarray) -> np.ndarray:
    """Connected components of triangles sharing vertex indices (a cube's faces are six charts)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    f = len(triangles)
    rows = np.repeat(np.arange(f), 3)
    incidence = coo_matrix((np.ones(3 * f), (rows, triangles.ravel())), shape=(f, int(triangles.max()) + 1)).tocsr()
    _, labels = connected_components(incidence @ incidence.T, directed=False)
    return labels


def _uv_to_position(points: np.ndarray, corner_uv: np.ndarray, corner_pos: np.ndarray) -> np.ndarray:
    """3D positions of UV ``points [M, 2]`` on the triangles ``corner_uv [F, 3, 2]`` (NaN where none holds it)."""
    a, b, c = corner_uv[:, 0], corner_uv[:, 1], corner_uv[:, 2]
    v0, v1 = b - a, c - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    ok = np.abs(den) > 1e-14
    out = np.full((len(points), 3), np.nan)
    d = points[:, None, :] - a[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        l1 = (d[..., 0] * v1[None, :, 1] - v1[None, :, 0] * d[..., 1]) / den[None]
        l2 = (v0[None, :, 0] * d[..., 1] - d[..., 0] * v0[None, :, 1]) / den[None]
    tol = 1e-7
    inside = ok[None] & (l1 >= -tol) & (l2 >= -tol) & (l1 + l2 <= 1 + tol)
    found = inside.any(axis=1)
    first = np.argmax(inside, axis=1)
    m = np.nonzero(found)[0]
    f = first[m]
    w1, w2 = l1[m, f], l2[m, f]
    out[m] = ((1 - w1 - w2)[:, None] * corner_pos[f, 0] + w1[:, None] * corner_pos[f, 1]
              + w2[:, None] * corner_pos[f, 2])
    # A point no triangle holds (a sphere's pole corner, whose triangle degenerates and is dropped) takes the
    # nearest triangle corner when that is close in UV.
    lost = np.nonzero(~found)[0]
    if len(lost):
        flat_uv, flat_pos = corner_uv.reshape(-1, 2), corner_pos.reshape(-1, 3)
        gap = np.linalg.norm(points[lost, None, :] - flat_uv[None], axis=-1)
        nearest = np.argmin(gap, axis=1)
        close = gap[np.arange(len(lost)), nearest] <= NEAREST_UV
        out[lost[close]] = flat_pos[nearest[close]]
    return out


def mesh_tiling(positions: np.ndarray, triangles: np.ndarray, corner_uv: np.ndarray, cells: tuple[int, int],
                tiles, seed: int = 0, where: str = "render") -> MeshTiling:
    """Tile the UV grid of a mesh: ``cells = (across u, across v)`` per chart, UV in [0, 1] per chart.

    Cell (i, j) of a chart covers ``u in [j / nu, (j + 1) / nu]``, ``v in [1 - (i + 1) / nv, 1 - i / nv]`` (row 0 at
    the top, as texels are).  Slots are glued where two cell edges have the same 3D end points (within a
    millionth of the mesh's size); an edge of zero length (a sphere's pole) joins nothing.
    """
    nu, nv = cells
    charts = triangle_charts(triangles)
    corner_pos = positions[triangles].astype(np.float64)
    size = float(np.linalg.norm(positions.max(0) - positions.min(0))) or 1.0
    tol = 1e-6 * size
    ju, iv = np.meshgrid(np.arange(nu + 1), np.arange(nv + 1))
    grid_uv = np.stack([ju.ravel() / nu, 1 - iv.ravel() / nv], 1)
    slots: dict = {}
    glues: list[Glue] = []
    n_charts = int(charts.max()) + 1
    sides = {N: ((0, 0), (0, 1)), E: ((0, 1), (1, 1)), S: ((1, 0), (1, 1)), W: ((0, 0), (1, 0))}
    for chart in range(n_charts):
        mine = charts == chart
        corners = _uv_to_position(grid_uv, corner_uv[mine].astype(np.float64), corner_pos[mine])
        if np.isnan(corners).any():
            raise BtforgeInputError(where, f"chart {chart} of the mesh does not cover UV [0, 1]^2 (found "
                                    f"{int(np.isnan(corners).any(1).sum())} grid corners outside it)",
                                    "tiles need each piece of the UV layout to span the unit square")
        corners = corners.reshape(nv + 1, nu + 1, 3)
        for i in range(nv):
            for j in range(nu):
                cell = chart * nu * nv + i * nu + j
                for side, ((r0, c0), (r1, c1)) in sides.items():
                    p0, p1 = corners[i + r0, j + c0], corners[i + r1, j + c1]
                    if np.linalg.norm(p1 - p0) < tol:
                        continue
                    k0, k1 = tuple(np.round(p0 / tol).astype(np.int64)), tuple(np.round(p1 / tol).astype(np.int64))
                    key = (min(k0, k1), max(k0, k1))
                    if key in slots:
                        other, other_side, forward = slots.pop(key)
                        same_direction = forward == (k0 <= k1)
                        glues.append(Glue((other, other_side), (cell, side),
                                          (other_side, side) in CONSISTENT and same_direction, not same_direction))
                    else:
                        slots[key] = (cell, side, k0 <= k1)
    rng = np.random.default_rng(seed)
    n_cells = n_charts * nu * nv
    ids, colors = tile_surface(n_cells, glues, tiles, rng, where)
    grids = [ids[c * nu * nv:(c + 1) * nu * nv].reshape(nv, nu) for c in range(n_charts)]
    cols = [colors[c * nu * nv:(c + 1) * nu * nv].reshape(nv, nu, 4) for c in range(n_charts)]
    return MeshTiling(charts, grids, cols, glues, n_cells)


def glue_mismatches(tiling: MeshTiling) -> int:
    """Glued slots whose colours differ (0 for a valid tiling)."""
    flat = np.concatenate([c.reshape(-1, 4) for c in tiling.colors])
    return sum(int(flat[g.a[0], g.a[1]] != flat[g.b[0], g.b[1]]) for g in tiling.glues)
