"""Texture optimisation of the tiles' interiors with their borders pinned.

Graph-cut filling leaves cuts where patches only roughly agree, most of them along the frame a tile's interior
was filled against.  The finished tiles then go through the shared refinement
(:func:`btforge.plugins.synth.refine.refine_map`: overlapping windows matched to the exemplar with an occurrence
term and a contrast term, whole windows kept where they match best and cut where the appearance agrees, then
corrections), laid side by side in one map so that the occurrence term spreads the whole set over the exemplar; the
straight seams left are re-cut with bridging pieces (:mod:`btforge.plugins.synth.bridging`) as quilting's are.  A ring of ``pin`` texels
along every tile border is held: those texels are the halves of the edge strips that every tile of the same edge
colour shares, so the tiles stay valid Wang tiles whatever happens inside.

The set is laid as one periodic tiling in which every tile meets neighbours of its own edge colours
(:func:`packing`), so a window across a tile border sees what a tiling will show there; laid in index order, a
tile's neighbours in the map would be unrelated tiles, and the windows along its borders would match a mix of two
textures.  With that context one held texel is enough: the interiors meet the held ring along a straight cut, and
a second held texel only moves that cut one texel inwards where it is as visible (against two held texels in index
order: a 4 x 4 tiling of 2 + 2 colours, seven 192 x 192 crops, seeds 0-1, straight-seam visibility 1.43 -> 1.26 at
the medians, seams lower on all 14 outputs).
"""
from __future__ import annotations

import math

import numpy as np

from btforge.buffers import CoordMap

#: Texture-optimisation rounds, and the weight of the refinement's contrast term (a candidate window with less
#: variation than the output window it would replace costs that weight x the shortfall).  The first round raises the
#: set's patch statistics' distance most: on the held-out procedural exemplar (seeds 0-3) SWD over the shuffled
#: blocks goes from 1.05 unrefined to 1.45 after one round and 1.58 after four, while seams fall from 3.63 to 1.27:
#: the rounds replace much of the filling, and nearest windows under a squared distance favour the exemplar's flatter
#: ones.  With the term at 8 and eight rounds, which bring the seams back down, SWD over the seven stationary 192 x 192
#: crops of the synthesis bench falls 1.13 -> 1.07 at the median (the procedural exemplar 1.58 -> 1.31, the fibres
#: 1.58 -> 1.16), seams rise 1.15 -> 1.19, and the single outputs missing a target fall from 9 to 5 of 28.  The term at
#: 8 with four rounds left seams of 1.35-1.37 on the procedural exemplar; at 16 more (Benchmarks).
ITERATIONS = 8
CONTRAST = 8.0
#: Weight of the refinement's occurrence term, and final rounds of the shared polish (8 x 8 windows matched for
#: their fit alone, :func:`btforge.plugins.synth.refine.refine_map`).  At 0.1 and no polish, the tiles' cuts were
#: the set's weak point: seam visibility over the seven stationary 192 x 192 crops of the synthesis bench (seeds 0-3)
#: reached 1.31-1.35 on three.  The stronger term spreads the set over more of the exemplar, and the polish moves the
#: cuts the weighted rounds left to where the content agrees: seams drop on all 21 crops of the bench (the relief
#: 1.37 -> 1.29, the tablet 1.30 -> 1.23) and the single outputs missing a target from 14 to 9 of 28.  Either alone
#: kept more misses (the term: 10 outputs, seams on the relief; the polish: straight seams on the procedural
#: exemplar); a weight of 0.3 missed as often, 1.0 raised the fibres' SWD to 1.54 (Benchmarks).
OCCURRENCE = 0.5
POLISH = 1
#: Weight of the refinement's balance term (:func:`btforge.plugins.synth.refine.appearance_excess`): windows of
#: appearance classes the set holds more of than the exemplar cost more.  The rounds drift towards an exemplar's
#: commonest, flattest areas, and a set of 16 tiles holds a few dozen exemplar places: on the bumps (192 x 192,
#: seeds 0-3) three of four sets held a third fewer shadows than the exemplar, SWD over the shuffled blocks 1.78 at the
#: median; at 16 it is 1.46, seams 1.21 -> 1.23 (Benchmarks).  Histogram matching as Kopf et al. 2007 weigh votes.
BALANCE = 16.0
PIN = 1            # texels along each tile border that keep their source
#: Weight of the seam cost in the refinement's vote, four times the shared default: the cuts inside the tiles run
#: where the two sides continue each other more closely.  On the 21 main crops of the synthesis bench (seeds 0-1) seams
#: fall on all 21 (the icon crop 1.33 -> 1.29 and the SynthRTI relief 1.30 -> 1.27, which then pass) and the targets
#: missed go from 13 to 11; SWD over the shuffled blocks rises by 0.02 at the median.  At 2: 13 (Benchmarks).
SEAM_WEIGHT = 4.0
#: Passes of the re-cut of straight seams after the refinement (the shared default is two; quilting, k-coherence
#: and the jump map run three).  The held border ring leaves straight runs along and across it that one pass only
#: shortens or joins to others, and the next finds them again; the re-cut stops early once a pass changes nothing.
#: On the 21 crops of the synthesis bench (seeds 0-1) six passes lower the straight seams' share of the seam edges
#: on 19 (median 1.3 % -> 0.9 %; the icon crop 2.9 % -> 1.0 %, the held-out procedural exemplar 3.8 % -> 1.8 %),
#: move seam visibility and evenness by 0.01 and SWD by 0.04 at most, and take the targets missed from 18 to 11
#: (four passes: 14).  The straight seams left are the costlier ones: on 16 crops their visibility rises.
RECUT_PASSES = 6
#: Texels on either side of a straight run that the re-cut may give a continuation of either side, in the edge
#: strips (:func:`.synthesis.refined_strip`) and in the interiors (the shared default is 8).  The runs left along the
#: held border ring and around the pieces laid at the tiles' centres cut through colour areas and bumps whose far
#: side lies beyond 8 texels; with 12 the cut can go round them.  On the 21 main crops of the synthesis bench (seeds
#: 0-1) the bumps' seams pass (1.31 -> 1.29) and their straight seams fall (1.45 -> 1.30 at 5.6 % of the seam edges,
#: still over 1.2), and the stucco's SWD passes (1.54 -> 0.99); 12 in the strips alone or in the interiors alone
#: left the bumps as they were, and 16 took their seams back to 1.32 (Benchmarks).
RECUT_BAND = 12


def border_ring(w: int, pin: int) -> np.ndarray:
    """``[w, w]`` mask of the ``pin`` outermost rows and columns of a tile."""
    ring = np.ones((w, w), bool)
    if 0 < 2 * pin < w:
        ring[pin:w - pin, pin:w - pin] = False
    return ring


def mosaic(tiles: np.ndarray, columns: int) -> np.ndarray:
    """``tiles [T, w, w, ...]`` laid row by row, ``columns`` across, into one array (empty cells zero)."""
    t, w = tiles.shape[:2]
    rows = -(-t // columns)
    padded = np.zeros((rows * columns, *tiles.shape[1:]), tiles.dtype)
    padded[:t] = tiles
    grid = padded.reshape(rows, columns, w, w, *tiles.shape[3:]).swapaxes(1, 2)
    return np.ascontiguousarray(grid.reshape(rows * w, columns * w, *tiles.shape[3:]))


def unmosaic(image: np.ndarray, t: int, w: int) -> np.ndarray:
    """The inverse of :func:`mosaic` for ``t`` tiles of ``w``."""
    rows, columns = image.shape[0] // w, image.shape[1] // w
    grid = image.reshape(rows, w, columns, w, *image.shape[2:]).swapaxes(1, 2)
    return np.ascontiguousarray(grid.reshape(rows * columns, w, w, *image.shape[2:])[:t])


def de_bruijn_pairs(k: int) -> list[int]:
    """A cyclic sequence over ``0 .. k - 1`` of length ``k * k`` in which every ordered pair of symbols follows
    each other exactly once: the de Bruijn sequence B(k, 2), the Lyndon words of length 1 and 2 (``i`` and ``i j``
    with ``i < j``) concatenated in lexicographic order."""
    sequence = []
    for first in range(k):
        sequence.append(first)
        for second in range(first + 1, k):
            sequence += [first, second]
    return sequence


def packing(colors: np.ndarray, n_h: int, n_v: int) -> np.ndarray | None:
    """``[rows, cols]`` tile indices laying a complete set (tile colours ``colors [T, 4]``: N, E, S, W) as one
    valid periodic tiling holding every tile once: row ``r`` has north colour ``a[r]`` and south ``a[r + 1]``,
    column ``c`` west ``b[c]`` and east ``b[c + 1]``, for de Bruijn sequences ``a`` and ``b``, so every (N, S) pair
    meets every (W, E) pair once; variants stack the pattern downwards.  None where the set is not complete."""
    by_combo: dict[tuple, list[int]] = {}
    for index, combo in enumerate(map(tuple, np.asarray(colors).tolist())):
        by_combo.setdefault(combo, []).append(index)
    variants = {len(v) for v in by_combo.values()}
    if len(by_combo) != n_h * n_h * n_v * n_v or len(variants) != 1:
        return None
    a, b = de_bruijn_pairs(n_h), de_bruijn_pairs(n_v)
    rows = [[by_combo[(a[r], b[(c + 1) % len(b)], a[(r + 1) % len(a)], b[c])][v] for c in range(len(b))]
            for v in range(variants.pop()) for r in range(len(a))]
    return np.array(rows, np.int64)


def optimise_tiles(features: np.ndarray, tile_coords: np.ndarray, *, iterations: int = ITERATIONS,
                   occurrence: float = OCCURRENCE, contrast: float = CONTRAST, polish: int = POLISH, pin: int = PIN,
                   seam_weight: float = SEAM_WEIGHT, balance: float = BALANCE,
                   seed: int = 0, colors: np.ndarray | None = None,
                   colour_counts: tuple[int, int] = (0, 0)) -> np.ndarray:
    """``tile_coords [T, w, w, 2]`` after ``iterations`` rounds of the shared refinement (occurrence and contrast
    weights ``occurrence``, ``contrast``) and ``polish`` rounds of its polish over appearance vectors
    ``features [H, W, D]``, every tile's ``pin``-texel border ring held (module docstring), the vote's seam cost
    weighted ``seam_weight``, the balance term ``balance``.  With the tiles' ``colors [T, 4]`` (N, E, S, W) and
    ``colour_counts`` (horizontal, vertical) of a complete set, the tiles are refined laid as one periodic valid tiling (:func:`packing`);
    otherwise row by row."""
    from btforge.plugins.synth.bridging import TRIES as BRIDGE_TRIES
    from btforge.plugins.synth.refine import refine_map
    if iterations <= 0:
        return tile_coords
    t, w = tile_coords.shape[:2]
    ring = border_ring(w, max(1, pin))
    grid = None if colors is None else packing(colors, *colour_counts)
    order = np.arange(t) if grid is None else grid.ravel()
    columns = math.ceil(math.sqrt(t)) if grid is None else grid.shape[1]
    pinned = mosaic(np.broadcast_to(ring, (t, w, w)), columns)
    pinned[mosaic(np.ones((t, w, w), bool), columns) == 0] = True   # empty cells of a last row laid row by row
    laid = CoordMap(mosaic(tile_coords[order], columns), features.shape[:2], wrap=grid is not None)
    src = refine_map(features, laid, iterations=iterations, occurrence=occurrence, contrast=contrast, seed=seed,
                     pinned=pinned, recut_passes=RECUT_PASSES, recut_band=RECUT_BAND, bridges=BRIDGE_TRIES,
                     polish=polish, seam_weight=seam_weight, balance=balance).coords
    out = np.empty_like(tile_coords)
    out[order] = unmosaic(src, t, w)
    return out

