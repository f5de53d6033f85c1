"""Feathering a map's seams through its blend layer, for exemplars whose records mix like their functions.

A cut between two copied regions is a step in radiance wherever the two sides do not continue each other.  On a
grainy exemplar the step hides among the exemplar's own edges; on a smooth one (soft bumps, a leaf's shading) it
shows.  Feathering cross-fades the two sides over ``band`` texels on either side of a seam edge: each texel
there keeps its own source and takes as its blend partner the source across the edge continued to it, so the
texels from one side's last unblended texel to the other's read as a linear ramp from one continued image to the
other in ``2 * band + 1`` equal steps.  Every texel keeps its own source as the heavier one, so the map's seams
(and everything measured from its dominant sources) stay where they were.  Only the seams whose step is larger
than the exemplar's own steps around the two sources are feathered (:data:`FEATHER_STEP`).

How wide a band is depends on the exemplar around the seam (:func:`smooth_bands`): up to ``band`` texels where it
is flat there, so a cut between smooth areas fades over a long ramp, down to one texel where its own steps are as
large as its mean step, so grain and fibres are not averaged with another piece of grain over a wide strip (a
wide cross-fade there blurs the grain, and the patch statistics move away from the exemplar's).

The blend layer replays on buffers whose records mix, directly or through their ``mixing_form``: radiance (a
stack), linear PTM and SH coefficients, which mix as radiance does, and sRGB PTM, SH and HSH coefficients (an lrgb
PTM through the rgb PTM of the same functions), which mix the display values, a cross-fade of what a screen shows
over a band of one to three texels.  On the others (Lafortune lobes, neural codes) ``remap`` would keep each texel's
heavier source and the output would be the unfeathered one, so those maps are left without a blend layer.
``synth.score`` measures a blended map's seams over
the blended band (:func:`.visibility.seam_visibility`), so a feathered step counts with its sharpest part.
"""
from __future__ import annotations

import numpy as np

from btforge.buffers import CoordMap

from .features import appearance_variance
from .visibility import dominant_source, seam_masks

#: The widest band by default, in texels on either side of a seam edge (:func:`smooth_bands`).  Against one texel
#: everywhere, the bumps' seams fall by 0.01-0.03 and their straight seams by 0.04-0.07, with SWD within +0.07 on
#: 36 crops; three texels everywhere lowered them a little more but blurred grain (quilting's SWD on the fibres
#: 1.42 -> 1.60, Benchmarks, "Cross-fades as wide as the exemplar is flat").
FEATHER = 3
#: Seam edges are feathered where their appearance step is over this many times the exemplar's own steps around
#: the two sources: the steps that stand out from their surroundings.  Cross-fading the others, which look like the
#: exemplar's own edges there (grain, fibres), hides nothing and lays two patterns over each other (Benchmarks).
FEATHER_STEP = 1.5
#: The widest band the ``feather`` param allows.
MAX_FEATHER = 8


def feather_weight(distance, band):
    """The blend partner's weight of a texel ``distance`` texels from a seam edge (1: beside it) in a band of
    ``band``: the linear cross-fade over ``2 * band + 1`` steps, below one half at every distance (ints, or arrays
    of them)."""
    return (band + 1 - distance) / (2 * band + 1)


def records_mix(exemplar) -> bool:
    """Whether a blend layer on ``exemplar`` replays as a cross-fade: its records mix, directly or through its
    ``mixing_form`` (only then is that form built)."""
    return exemplar.mixes_records or exemplar.mixing_form() is not None


def feathered(coords: CoordMap, band: int, mixes: bool = True, features: np.ndarray | None = None,
              step: float = FEATHER_STEP, steps: np.ndarray | None = None) -> CoordMap:
    """``coords`` with the texels within ``band`` of a seam edge blended with the source across that edge,
    continued to them (the nearest edge where several are in reach; columns' edges before rows' on a tie).  The map
    is returned as it is where ``band`` is 0, the exemplar's records cannot mix (``mixes``), or the map has a blend layer.
    With the exemplar's appearance vectors ``features [h, w, D]``, only the seam edges whose step between the two
    sources' vectors is over ``step`` x the exemplar's steps around them are feathered, each over the band
    :func:`smooth_bands` gives it (without: every one over ``band``); ``steps``: :func:`local_steps` of
    ``features``, where the caller feathers many maps of one exemplar."""
    if band <= 0 or not mixes or coords.blend_weight.size:
        return coords
    src = dominant_source(coords)
    h, w = src.shape[:2]
    across_columns, across_rows = seam_masks(src[..., 0], src[..., 1], coords.wrap)
    bands = [np.where(across_columns, band, 0), np.where(across_rows, band, 0)]
    if features is not None and step > 0:
        if steps is None:
            steps = local_steps(np.asarray(features, np.float32))
        across_columns, across_rows = _visible(features, steps, src, across_columns, across_rows, step)
        bands = [smooth_bands(steps, src, edges, axis, band) for axis, edges in ((1, across_columns), (0, across_rows))]
    nearest = np.full((h, w), band + 1, np.int64)
    partner = src.copy()
    weight = np.zeros((h, w), np.float32)
    for distance in range(1, band + 1):
        for axis, edge_band in ((1, bands[0]), (0, bands[1])):
            for side in (-1, 1):
                texels, continued, reach = _across(src, edge_band >= distance, axis, side, distance, coords, edge_band)
                closer = nearest[texels] > distance
                chosen = tuple(t[closer] for t in texels)
                nearest[chosen] = distance
                partner[chosen] = continued[closer]
                weight[chosen] = feather_weight(distance, reach[closer])
    return CoordMap(coords.coords, coords.source_size, partner.astype(np.int32), weight, coords.wrap, coords.tile)


def _across(src: np.ndarray, edges: np.ndarray, axis: int, side: int, distance: int, coords: CoordMap,
            edge_band: np.ndarray):
    """For every seam edge of ``edges`` (along ``axis``), the texel ``distance`` texels from it on ``side`` (-1: the
    lower, 1: the higher), the source of the texel across the edge continued to it and the edge's band
    (``edge_band [H, W]``): ``(rows, cols)``, ``[n, 2]`` sources and ``[n]`` bands, left out where either texel
    falls outside the output (without wrap), the continued source outside the exemplar, or the texel outside the
    piece beside the edge (another seam lies between them: the band stops there)."""
    h, w = src.shape[:2]
    rows, cols = np.nonzero(edges)
    low = np.stack([rows, cols], axis=1)
    offset = np.zeros(2, np.int64)
    offset[0 if axis == 0 else 1] = 1
    high = low + offset
    texel = low - (distance - 1) * offset if side < 0 else high + (distance - 1) * offset
    near, other = (low, high) if side < 0 else (high, low)
    if coords.wrap:
        texel, near, other = texel % (h, w), near % (h, w), other % (h, w)
    inside = (texel >= 0).all(axis=1) & (texel < (h, w)).all(axis=1) & (other < (h, w)).all(axis=1)
    texel, near, other, reach = texel[inside], near[inside], other[inside], edge_band[rows, cols][inside]
    same_piece = (src[texel[:, 0], texel[:, 1]] == src[near[:, 0], near[:, 1]] + side * (distance - 1) * offset).all(axis=1)
    continued = src[other[:, 0], other[:, 1]] + side * distance * offset
    keep = same_piece & (continued >= 0).all(axis=1) & (continued < coords.source_size).all(axis=1)
    return (texel[keep, 0], texel[keep, 1]), continued[keep], reach[keep]


def _visible(features: np.ndarray, steps: np.ndarray, src: np.ndarray, across_columns: np.ndarray,
             across_rows: np.ndarray, step: float) -> list[np.ndarray]:
    """``across_columns, across_rows`` without the seam edges whose step between the two sources' appearance
    vectors is at most ``step`` x the mean of the two sources' local steps (``steps``, :func:`local_steps`)."""
    here = np.asarray(features, np.float32)[src[..., 0], src[..., 1]]
    kept = []
    for axis, edges in ((1, across_columns), (0, across_rows)):
        jump = np.linalg.norm(np.roll(here, -1, axis=axis) - here, axis=2)
        kept.append(edges & (jump > step * steps_around(steps, src, axis)))
    return kept


def steps_around(steps: np.ndarray, src: np.ndarray, axis: int) -> np.ndarray:
    """``[H, W]``: for the edge after each texel along ``axis``, the mean of its two sources' local steps
    (``steps``: :func:`local_steps`)."""
    local = steps[src[..., 0], src[..., 1]]
    return 0.5 * (local + np.roll(local, -1, axis=axis))


def smooth_bands(steps: np.ndarray, src: np.ndarray, edges: np.ndarray, axis: int, widest: int) -> np.ndarray:
    """``[H, W]`` band of each seam edge of ``edges`` (along ``axis``; 0 elsewhere) of a map with exemplar sources
    ``src [H, W, 2]``: ``widest`` where the exemplar is flat around the edge's two sources (:func:`steps_around`),
    1 where their steps reach the exemplar's mean local step, rounded linearly between."""
    mean = max(float(steps.mean()), np.finfo(np.float32).tiny)
    flatness = np.clip(1 - steps_around(steps, src, axis) / mean, 0, 1)
    return np.where(edges, 1 + np.rint((widest - 1) * flatness), 0).astype(np.int64)


#: The :func:`grain` up to which an exemplar counts as smooth, and from which as grainy (:func:`by_grain`): the
#: smooth exemplars measured score 0.11-0.25 (the bumps, leaves, a knit, paintings, the held-out procedural exemplar),
#: the grainy ones 0.49-0.88 (the stucco, stones, fibres, plaster), the cobbles, item2 and the tablet between
#: (0.31-0.46).
GRAIN_SMOOTH, GRAIN_GRAINY = 0.25, 0.5


def by_grain(grain_ratio: float, smooth: float, grainy: float) -> float:
    """A setting for an exemplar of ``grain_ratio`` (:func:`grain`): ``smooth`` up to :data:`GRAIN_SMOOTH`,
    ``grainy`` from :data:`GRAIN_GRAINY`, linearly between."""
    t = min(max((grain_ratio - GRAIN_SMOOTH) / (GRAIN_GRAINY - GRAIN_SMOOTH), 0.0), 1.0)
    return smooth + (grainy - smooth) * t


def grain(features: np.ndarray, steps: np.ndarray | None = None) -> float:
    """How grainy an exemplar is: its mean local step (:func:`local_steps`, or ``steps``) over the spread of its
    appearance vectors ``features [h, w, D]`` (the root mean squared distance from their mean).  Smooth shading
    (soft bumps, a leaf, a painting) scores 0.1-0.2, a plaster or fibres whose every texel differs from its
    neighbours about as much as from any other 0.8-0.9; 0 for a constant exemplar."""
    spread = float(np.sqrt(appearance_variance(features)))
    if steps is None:
        steps = local_steps(np.asarray(features, np.float64))
    return float(steps.mean()) / spread if spread > 0 else 0.0


def local_steps(features: np.ndarray) -> np.ndarray:
    """``[h, w]``: each exemplar texel's mean step to its 4-neighbours (3 or 2 along the border) in appearance."""
    rows = np.linalg.norm(np.diff(features, axis=0), axis=2)
    cols = np.linalg.norm(np.diff(features, axis=1), axis=2)
    total, count = np.zeros(features.shape[:2]), np.zeros(features.shape[:2])
    for steps, axis in ((rows, 0), (cols, 1)):
        for part in (slice(1, None), slice(None, -1)):
            at = (part, slice(None)) if axis == 0 else (slice(None), part)
            total[at] += steps
            count[at] += 1
    return total / np.maximum(count, 1)
