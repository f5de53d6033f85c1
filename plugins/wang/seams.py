"""Seam scores of a tile set and its tilings: how visible tile borders are, measured against the exemplar.

For every valid adjacency - tile ``A`` left of tile ``B`` wherever ``A``'s E colour equals ``B``'s W colour,
tile ``A`` above ``B`` wherever ``A``'s S equals ``B``'s N - the distance between each pair of texels facing each
other across the border, and for every valid 2 x 2 configuration (four tiles around a vertex whose four shared
edges match) the pairs across both borders within ``edge / 2`` texels of the vertex.  Distances are Euclidean in
the appearance features (:mod:`features`), the compressed-domain L2 distance of the reflectance functions.  The
reference is the distance between horizontally (for vertical borders) and vertically (for horizontal borders)
neighbouring texels inside the exemplar - at the same texels (:func:`seam_ratios`) and over the whole exemplar -
so a ratio of 1 means a border is as smooth as the exemplar itself.
"""
from __future__ import annotations

import numpy as np

from .synthesis import neighbour_distances


def _distances(feats: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances between the texels at exemplar coordinates ``a [..., 2]`` and ``b [..., 2]``."""
    fa = feats[a[..., 0], a[..., 1]].astype(np.float64)
    fb = feats[b[..., 0], b[..., 1]].astype(np.float64)
    return np.linalg.norm(fa - fb, axis=-1).ravel()


def _local_reference(feats: np.ndarray, a: np.ndarray, b: np.ndarray, step) -> np.ndarray:
    """For texel pairs ``a`` | ``b`` (``b`` one ``step`` after ``a`` in the tiling), the distance from each to its
    own neighbour in the exemplar in that direction, averaged over the two sides."""
    limit = np.array(feats.shape[:2]) - 1
    step = np.asarray(step)
    ahead = np.clip(a + step, 0, limit)
    behind = np.clip(b - step, 0, limit)
    return 0.5 * (_distances(feats, a, ahead) + _distances(feats, behind, b))


def exemplar_reference(feats: np.ndarray) -> dict:
    f = feats.astype(np.float64)
    across_columns = np.linalg.norm(f[:, 1:] - f[:, :-1], axis=-1).ravel()   # horizontal neighbours
    across_rows = np.linalg.norm(f[1:] - f[:-1], axis=-1).ravel()
    return {"h": across_columns, "v": across_rows, "all": neighbour_distances(feats)}


def adjacency_distances(coords: np.ndarray, colors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(left, right)`` and ``(top, bottom)`` of every valid adjacency of a tile set."""
    n, e, s, w = colors.T
    left, right = np.nonzero(e[:, None] == w[None, :])
    top, bottom = np.nonzero(s[:, None] == n[None, :])
    return np.stack([left, right], 1), np.stack([top, bottom], 1)


def corner_configurations(colors: np.ndarray) -> np.ndarray:
    """Every valid ``(top-left, top-right, bottom-left, bottom-right)`` quadruple of tile indices."""
    n, e, s, w = colors.T
    out = []
    for tl in range(len(colors)):
        for tr in np.nonzero(w == e[tl])[0]:
            for bl in np.nonzero(n == s[tl])[0]:
                for br in np.nonzero((n == s[tr]) & (w == e[bl]))[0]:
                    out.append((tl, tr, bl, br))
    return np.asarray(out, np.int64).reshape(-1, 4)


def tile_set_seams(tile_coords: np.ndarray, colors: np.ndarray, feats: np.ndarray, edge: int) -> dict:
    """Seam distances of a tile set: ``{"h": ..., "v": ..., "corner_h": ..., "corner_v": ...}`` arrays and the
    per tile edge mean (``edges [T, 4]``, N E S W, over every valid neighbour on that side)."""
    t, w = tile_coords.shape[:2]
    horizontal, vertical = adjacency_distances(tile_coords, colors)
    facing_h = (tile_coords[horizontal[:, 0], :, -1], tile_coords[horizontal[:, 1], :, 0])   # [pairs, w, 2] each
    facing_v = (tile_coords[vertical[:, 0], -1, :], tile_coords[vertical[:, 1], 0, :])
    d_h = _distances(feats, *facing_h).reshape(len(horizontal), w)
    d_v = _distances(feats, *facing_v).reshape(len(vertical), w)
    edges = np.zeros((t, 4))
    for side, (pairs, dist, column) in enumerate([(vertical, d_v, 1), (horizontal, d_h, 0),
                                                   (vertical, d_v, 0), (horizontal, d_h, 1)]):
        for tile in range(t):
            mine = pairs[:, column] == tile
            edges[tile, side] = dist[mine].mean() if mine.any() else np.nan
    q = max(1, edge // 2)
    quads = corner_configurations(colors)
    tl, tr, bl, br = quads.T
    # per configuration, the pairs across each border within q of the vertex: above it, then below (left, right)
    corner_h = (np.stack([tile_coords[tl, w - q:, -1], tile_coords[bl, :q, -1]], 1),
                np.stack([tile_coords[tr, w - q:, 0], tile_coords[br, :q, 0]], 1))
    corner_v = (np.stack([tile_coords[tl, -1, w - q:], tile_coords[tr, -1, :q]], 1),
                np.stack([tile_coords[bl, 0, w - q:], tile_coords[br, 0, :q]], 1))
    local = {"h": _local_reference(feats, *facing_h, (0, 1)), "v": _local_reference(feats, *facing_v, (1, 0)),
             "corner_h": _local_reference(feats, *corner_h, (0, 1)),
             "corner_v": _local_reference(feats, *corner_v, (1, 0))}
    return {"h": d_h.ravel(), "v": d_v.ravel(), "corner_h": _distances(feats, *corner_h),
            "corner_v": _distances(feats, *corner_v), "local": local, "edges": edges,
            "configurations": len(quads), "adjacencies": len(horizontal) + len(vertical)}


def seam_ratios(seams: dict, reference: dict) -> dict:
    """Mean and 99th-percentile ratios of seam distances to neighbouring-texel distances inside the exemplar.

    ``*_ratio`` (the ones tests bound): against the distances from the same texels to their own exemplar
    neighbours in the border's direction, so a border that continues the exemplar scores exactly 1 whatever
    content it crosses.  ``global_*``: against all of the exemplar's neighbouring texels in that direction, which
    also reflects whether tile borders cross busier or flatter content than the exemplar on average.
    """
    out = {}
    ref_mean = {k: float(np.mean(reference[k])) for k in ("h", "v")}
    ref_p99 = {k: float(np.percentile(reference[k], 99)) for k in ("h", "v")}
    for name, kind in (("h", "h"), ("v", "v"), ("corner_h", "h"), ("corner_v", "v")):
        values, local = seams[name], seams["local"][name]
        if not len(values):
            continue
        out[f"{name}_mean_ratio"] = float(np.mean(values)) / max(float(np.mean(local)), 1e-30)
        out[f"{name}_p99_ratio"] = float(np.percentile(values, 99)) / max(float(np.percentile(local, 99)), 1e-30)
        out[f"global_{name}_mean_ratio"] = float(np.mean(values)) / max(ref_mean[kind], 1e-30)
        out[f"global_{name}_p99_ratio"] = float(np.percentile(values, 99)) / max(ref_p99[kind], 1e-30)
    out["worst_mean_ratio"] = max(v for k, v in out.items() if k.endswith("_mean_ratio") and not k.startswith("global"))
    out["worst_p99_ratio"] = max(v for k, v in out.items() if k.endswith("_p99_ratio") and not k.startswith("global"))
    return out


def tiling_report(tile_ids: np.ndarray, colors: np.ndarray, n_tiles: int, periodic: bool) -> dict:
    """Colour mismatches on every shared edge of a rows x cols tiling, and how often each tile is used."""
    c = colors[tile_ids]
    mismatch_h = int((c[:, :-1, 1] != c[:, 1:, 3]).sum())
    mismatch_v = int((c[:-1, :, 2] != c[1:, :, 0]).sum())
    if periodic:
        mismatch_h += int((c[:, -1, 1] != c[:, 0, 3]).sum())
        mismatch_v += int((c[-1, :, 2] != c[0, :, 0]).sum())
    use = np.bincount(tile_ids.ravel(), minlength=n_tiles)
    return {"mismatches": mismatch_h + mismatch_v, "tiles_used": int((use > 0).sum()), "tiles": int(n_tiles),
            "least_use": int(use.min()), "most_use": int(use.max())}


def cut_distances(tile_coords: np.ndarray, feats: np.ndarray) -> dict:
    """Inside the tiles: distances of the neighbour pairs copied from different exemplar places (the cuts'
    seams), horizontally and vertically, with the same texels' distances to their own exemplar neighbours in that
    direction (``cut_*_local``, as :func:`seam_ratios` compares) and the cuts' share of all pairs."""
    out, total, cut = {}, 0, 0
    for name, a, b, step in (("h", tile_coords[:, :, :-1], tile_coords[:, :, 1:], (0, 1)),
                             ("v", tile_coords[:, :-1], tile_coords[:, 1:], (1, 0))):
        seam = np.any(b != a + np.array(step), axis=-1)
        out[f"cut_{name}"] = _distances(feats, a[seam], b[seam])
        out[f"cut_{name}_local"] = _local_reference(feats, a[seam], b[seam], step)
        total += seam.size
        cut += int(seam.sum())
    out["cut_share"] = cut / max(total, 1)
    return out


def _border(tile_coords: np.ndarray, tile: int, side: int) -> np.ndarray:
    """The texels of a tile along one side, in the side's direction (N, S left to right; E, W top to bottom)."""
    t = tile_coords[tile]
    return (t[0], t[:, -1], t[-1], t[:, 0])[side]


def mesh_seams(tiling, tile_coords: np.ndarray, feats: np.ndarray) -> dict:
    """Distances across every glued edge of a mesh tiling between different charts (a cube's face edges), split
    into glues that keep the orientation and glues that turn it, as ratios to the exemplar's mean
    neighbouring-texel distance."""
    ids = np.concatenate([g.ravel() for g in tiling.grids])
    cells_per_chart = tiling.grids[0].size
    reference = float(np.mean(neighbour_distances(feats)))
    parts: dict = {"consistent": [], "rotated": []}
    for g in tiling.glues:
        if g.a[0] // cells_per_chart == g.b[0] // cells_per_chart:
            continue
        a = _border(tile_coords, ids[g.a[0]], g.a[1])
        b = _border(tile_coords, ids[g.b[0]], g.b[1])
        parts["consistent" if g.consistent else "rotated"].append(_distances(feats, a, b[::-1] if g.reversed else b))
    out = {}
    for kind, values in parts.items():
        if values:
            v = np.concatenate(values)
            out[f"{kind}_edges"] = len(values)
            out[f"{kind}_mean_ratio"] = float(v.mean()) / max(reference, 1e-30)
            out[f"{kind}_p99_ratio"] = float(np.percentile(v, 99)) / max(float(np.percentile(
                neighbour_distances(feats), 99)), 1e-30)
    return out


def tiling_ids(tiles, coords) -> np.ndarray:
    """The tile index of every ``w x w`` block of a tiling's map (refuses blocks that are no tile)."""
    from btforge.errors import BtforgeInputError
    w = tiles.tile
    if coords.height % w or coords.width % w or coords.source_size != tiles.source_size:
        raise BtforgeInputError("score 'coords'", f"expected a map of whole {w} x {w} tiles into the "
                                f"{tiles.source_size[0]} x {tiles.source_size[1]} exemplar, found "
                                f"{coords.height} x {coords.width} into {coords.source_size}",
                                "wire the coords of a wang.tiling of the tile set wired to 'tiles'")
    known = {tiles.tile_coords[t].tobytes(): t for t in range(tiles.n_tiles)}
    rows, cols = coords.height // w, coords.width // w
    ids = np.empty((rows, cols), np.int64)
    for i in range(rows):
        for j in range(cols):
            block = np.ascontiguousarray(coords.coords[i * w:(i + 1) * w, j * w:(j + 1) * w]).tobytes()
            if block not in known:
                raise BtforgeInputError("score 'coords'", f"block ({i}, {j}) is not a tile of the set",
                                        "wire the coords of a wang.tiling of the tile set wired to 'tiles'")
            ids[i, j] = known[block]
    return ids


def tile_set_scores(tiles, exemplar, coords=None) -> dict:
    """What ``synth.score`` reports for a tile set: ``seam_*`` (:func:`seam_ratios` over every valid adjacency and
    2 x 2 configuration, in the exemplar's appearance features), ``btfel_share``, ``btfel_bytes``, ``tiles``, and
    with ``coords`` (a tiling of the set) ``tiling_*`` (:func:`tiling_report`) and ``tiling_periodic``."""
    from btforge.errors import BtforgeInputError

    from .features import appearance_features
    from .tiling import is_periodic
    if (exemplar.height, exemplar.width) != tiles.source_size:
        raise BtforgeInputError("score 'exemplar'", f"expected the {tiles.source_size[0]} x {tiles.source_size[1]} "
                                f"exemplar of the tile set, found {exemplar.height} x {exemplar.width}",
                                "wire the buffer the tile set was synthesized from")
    full = appearance_features(exemplar)
    ratios = seam_ratios(tile_set_seams(tiles.tile_coords, tiles.tile_colors, full, tiles.edge),
                         exemplar_reference(full))
    values = {f"seam_{k}": v for k, v in ratios.items()}
    stats = tiles.statistics()
    values.update({"btfel_share": stats["referenced_share"], "btfel_bytes": stats["total_bytes"],
                   "tiles": stats["tiles"]})
    if coords is not None:
        ids = tiling_ids(tiles, coords)
        values.update({f"tiling_{k}": v for k, v in tiling_report(ids, tiles.tile_colors, tiles.n_tiles,
                                                                  coords.wrap).items()})
        values["tiling_periodic"] = bool(is_periodic(ids))
    return values
