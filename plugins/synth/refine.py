"""Refinement of any synthesizer's coordinate map: texture optimisation in appearance space with an occurrence
term, then coherence corrections that break straight seams.

A map names, per output texel, the exemplar texel it copies; its output is the exemplar's appearance vectors
gathered through it.  :func:`refine_map` improves the map where the eye looks first, in two alternating steps:

1. *Texture optimisation* (Kwatra et al. 2005) with an *occurrence* term (Kaspar et al. 2015): the output is cut
   into overlapping ``patch x patch`` windows (half a window apart, the grid at a random offset each iteration
   and each window shifted by its own 0 .. stride - 1 texels, so that cuts along window sides do not line up); each
   window is matched to the exemplar window whose appearance is nearest (an approximate k-d tree search on
   PCA-reduced windows; the window it copies now is always a candidate; candidates ranked by their full distance)
   plus a penalty for exemplar windows already used more than their fair share.  A window that copies a whole
   exemplar window used within its share matches exactly and skips the search.  The vote is a labelling: every output texel takes,
   among the sources its covering windows propose and its current source, the one that keeps the cost low of the
   proposing window's match error plus the seam cost against its neighbours (zero where two sources continue
   each other), by a few sweeps of iterated conditional modes.  Whole well-matched windows win and the cuts
   between them run where the appearance agrees.  (A per-texel vote, each texel taking the proposal nearest the
   proposals' average, scatters 4 x 4 fragments of different windows: the texture's structures break up and
   its patch statistics drift away from the exemplar's.)
2. *Corrections* (as in Lefebvre & Hoppe 2005): each texel, in a random half of the texels per pass, may take
   the continuation of a 4-neighbour's source (or keep its own), whichever makes its neighbourhood (itself and
   its 4-neighbours) most like the exemplar's around that source.  Seams then follow the content instead of a grid.

3. *Re-cutting* (:mod:`.recut`, after the finest scale): seams left in straight runs, where no single-texel move
   pays, are re-cut by minimum cuts between the continuations of their two sides (Kwatra et al. 2003).

With ``scales`` > 0 the first two steps run first on half-resolution versions of the map and the exemplar (recursively),
so that an 8 x 8 window also spans 16 and 32 texels and structures larger than a fine window are matched whole.
With ``coarse_keep`` a coarser scale runs only while its averaged exemplar keeps that share of the exemplar's
appearance variance (:func:`keeps_structure`): where grain or thin lines carry the rest, its windows all look alike.

The window index (PCA of the windows, a SciPy k-d tree), the tree query and the vote's bookkeeping run in NumPy on
the host; the hot loops run as OpenCL kernels (``refine.cl``): the candidates' full distances (``rf_rank``), the
vote's half-sweeps (``rf_sweep``; a texel whose neighbours kept their labels keeps its own) and the corrections'
candidates (``rf_correct``).  Each has a NumPy twin here (``_rank_numpy``, ``_sweeps_numpy``, ``_correct_numpy``),
run instead with the environment variable ``BTFORGE_REFINE_ENGINE=numpy``; kernels and twins sum in the same
float32 order, so both give the same maps.  The re-cut (:mod:`.recut`) runs on the host with scipy's maximum flow.
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from btforge.buffers import CoordMap

from .features import appearance_variance, beside, edge_padded, pca_reduce, window_sums
from .recut import BAND as RECUT_BAND
from .recut import PASSES as RECUT_PASSES
from .recut import recut_straight_seams
from .search import ContentCache, content_key
from .search_base import cores, leading_eigenpairs

#: Appearance dimensions each texel keeps in the refinement (PCA of the synthesizer's features).
TEXEL_DIMS = 6
#: Dimensions of the PCA-reduced windows searched in the k-d tree.
WINDOW_DIMS = 12
#: Nearest exemplar windows found per output window before the occurrence term re-ranks them.
CANDIDATES = 8
#: Approximation of the k-d tree search: a found window is at most (1 + SEARCH_EPS) x as far as the true k-th
#: nearest (the candidates are re-ranked by their full distance afterwards).
SEARCH_EPS = 2.0
#: Correction passes after each optimisation step.
CORRECTIONS = 1
#: Default weight of the seam cost against the window match cost in the vote (``refine_map(seam_weight=...)``).
SEAM_WEIGHT = 1.0
#: A coarser scale is refined first only while its exemplar and output are at least this many windows across.
COARSE_FIT = 4
#: Checkerboard sweeps of the vote's labelling.
SWEEPS = 4
#: Side of the windows of the final polish rounds (``refine_map(polish=...)``).
POLISH_WINDOW = 8
#: Window positions sampled to fit the window PCA.
PCA_SAMPLE = 4000

#: The kernels of the hot loops (candidate re-ranking, the vote's sweeps, the corrections' candidates).
KERNELS = Path(__file__).with_name("refine.cl")
#: Where the hot loops run: OpenCL kernels, or their NumPy twins (environment variable :data:`ENGINE_VARIABLE`).
ENGINES = ("opencl", "numpy")
ENGINE_VARIABLE = "BTFORGE_REFINE_ENGINE"

#: Window indices kept: one per exemplar, patch and scale (three scales of four exemplars).
_analyses = ContentCache(12)
APPEARANCE_CLASSES = 16   # k-means classes of the exemplar's texels that the balance term counts


def engine() -> str:
    """Where the refinement's hot loops run: ``opencl`` (default) or ``numpy`` (the twins), from the environment
    variable :data:`ENGINE_VARIABLE`."""
    chosen = os.environ.get(ENGINE_VARIABLE, "").strip().lower() or ENGINES[0]
    if chosen not in ENGINES:
        from btforge.errors import BtforgeInputError
        raise BtforgeInputError(f"environment variable {ENGINE_VARIABLE}", f"expected one of {ENGINES}, found "
                                f"{os.environ[ENGINE_VARIABLE]!r}", "unset it (OpenCL), or set it to 'numpy' to run "
                                "the refinement's NumPy twins")
    return chosen


def _backend():
    from btforge.backend import get_backend
    return get_backend()


@dataclasses.dataclass(frozen=True)
class WindowIndex:
    """The exemplar's windows of one size, PCA-reduced, in a k-d tree (made once per exemplar and size)."""

    texels: np.ndarray      # [eh, ew, d] reduced appearance per exemplar texel
    patch: int
    mean: np.ndarray        # [p * p * d]
    basis: np.ndarray       # [p * p * d, WINDOW_DIMS]
    reduced: np.ndarray     # [gh * gw, WINDOW_DIMS]
    tree: object            # scipy.spatial.cKDTree over ``reduced``
    spread: float           # mean squared distance between two random windows (the occurrence term's unit)
    energy: np.ndarray      # [gh * gw] float32, each window's variation (:func:`window_energy`)

    @property
    def grid(self) -> tuple[int, int]:
        return self.texels.shape[0] - self.patch + 1, self.texels.shape[1] - self.patch + 1


def window_index(features: np.ndarray, patch: int) -> WindowIndex:
    """The :class:`WindowIndex` of ``features [eh, ew, D]`` (cached by content)."""
    return _analyses.get_or_make(content_key(features, extra=("refine", patch)), lambda: _index(features, patch))


def _index(features: np.ndarray, patch: int) -> WindowIndex:
    from numpy.lib.stride_tricks import sliding_window_view
    from scipy.spatial import cKDTree
    texels = pca_reduce(features, TEXEL_DIMS) if features.shape[2] > TEXEL_DIMS else features.astype(np.float32)
    texels = np.ascontiguousarray(texels / max(float(texels.std()), 1e-12), dtype=np.float32)
    windows = sliding_window_view(texels, (patch, patch), axis=(0, 1)).transpose(0, 1, 3, 4, 2)
    gy, gx = windows.shape[:2]
    rng = np.random.default_rng(0)
    picked = np.divmod(rng.choice(gy * gx, min(PCA_SAMPLE, gy * gx), replace=False), gx)
    sample = windows[picked].reshape(len(picked[0]), -1).astype(np.float64)
    mean = sample.mean(axis=0)
    _, axes = leading_eigenpairs((sample - mean).T @ (sample - mean), WINDOW_DIMS)
    basis = np.ascontiguousarray(axes, dtype=np.float32)
    reduced = np.empty((gy * gx, WINDOW_DIMS), np.float32)
    for top in range(0, gy, 8):  # a few window rows at a time: the flattened windows stay in cache
        rows = windows[top:top + 8].reshape(-1, basis.shape[0])
        reduced[top * gx:top * gx + len(rows)] = (rows - mean.astype(np.float32)) @ basis
    spread = 2.0 * float(reduced.var(axis=0).sum())
    return WindowIndex(texels, patch, mean.astype(np.float32), basis, reduced, cKDTree(reduced), max(spread, 1e-12),
                       exemplar_window_energy(texels, patch))


def window_energy(windows: np.ndarray, d: int) -> np.ndarray:
    """Per window (``[n, p * p * d]``, texel-major), its variation: the summed squared deviation of its texels from
    their mean, over every dimension (float32)."""
    values = windows.reshape(len(windows), -1, d).astype(np.float64)
    return ((values - values.mean(axis=1, keepdims=True)) ** 2).sum(axis=(1, 2)).astype(np.float32)


def exemplar_window_energy(texels: np.ndarray, patch: int) -> np.ndarray:
    """:func:`window_energy` of every ``patch x patch`` window of ``texels [eh, ew, d]``, flat in the window grid
    (by box sums: sum of squares minus square of sums over the count, of values centred on their mean first, so
    that a flat exemplar's windows come out exactly 0 rather than as the difference of two large sums)."""
    values = texels.astype(np.float64)
    values -= values.mean(axis=(0, 1))
    window = (patch, patch)
    energy = (window_sums(values ** 2, window) - window_sums(values, window) ** 2 / (patch * patch)).sum(axis=2)
    return np.maximum(energy, 0.0).ravel().astype(np.float32)


def refine_map(features: np.ndarray, coords: CoordMap, *, iterations: int, occurrence: float, patch: int = 8,
               seed: int = 0, pinned: np.ndarray | None = None, scales: int = 0, recut: bool = True,
               recut_passes: int = RECUT_PASSES, bridges: int = 0,
               coarse_iterations: int | None = None, contrast: float = 0.0, polish: int = 0,
               seam_weight: float = SEAM_WEIGHT, balance: float = 0.0, recut_band: int = RECUT_BAND,
               coarse_keep: float = 0.0) -> CoordMap:
    """``coords`` (a map into the exemplar whose appearance vectors are ``features [eh, ew, D]``) after ``iterations``
    rounds of texture optimisation with an occurrence weight ``occurrence`` and corrections. A blended texel is refined
    from its heavier source and keeps its blend where that source stays; the result has the input's wrap and tile.  A
    map or exemplar smaller than a window is returned as it is. ``pinned`` (boolean ``[H, W]``, optional) marks output
    texels that keep their sources (and blends): they still serve as context for their neighbours' windows, seams and
    corrections.  ``scales`` coarser scales (each at half the resolution of the next) are refined first,
    ``coarse_iterations`` rounds each (by default ``iterations``), while their exemplar and output stay
    :data:`COARSE_FIT` windows across (:func:`_coarse_first`), and while a coarse exemplar keeps at least
    ``coarse_keep`` of the finest one's appearance variance (:func:`keeps_structure`; 0: always).  With ``recut`` the
    straight seams left are then re-cut by minimum cuts (:func:`.recut.recut_straight_seams`, up to ``recut_passes``
    passes, with ``bridges`` bridging patches per run and pass, in bands of ``recut_band`` texels on either side of a
    run).  ``contrast`` > 0 makes a candidate window with less variation than the output window it would replace cost
    ``contrast`` x the shortfall (:func:`_best_windows`); ``balance`` > 0 makes it cost ``balance`` x (the mean squared
    distance of two random windows) x how far its appearance classes are over-represented in the output
    (:func:`appearance_excess`). ``polish`` rounds at the finest scale follow, before the re-cut, with
    :data:`POLISH_WINDOW` x :data:`POLISH_WINDOW` windows and neither term (:func:`_polished`).  ``seam_weight`` weighs
    the vote's seam cost against the windows' match cost at every scale and in the polish (:func:`_vote`)."""
    pinned = _pinned_mask(pinned, coords)
    if iterations <= 0 or min(coords.source_size) < patch or min(coords.height, coords.width) < patch:
        return coords  # no whole window fits: nothing to match
    if pinned is not None and pinned.all():
        return coords
    eh, ew = coords.source_size
    src = coords.coords[..., 0].astype(np.int64) * ew + coords.coords[..., 1]
    if coords.blend_weight.size:
        partner = coords.blend_coords[..., 0].astype(np.int64) * ew + coords.blend_coords[..., 1]
        src = np.where(coords.blend_weight > 0.5, partner, src)
    rng = np.random.default_rng([seed, 7])
    rounds = (iterations, iterations if coarse_iterations is None else coarse_iterations)
    weights = (occurrence, contrast, seam_weight, balance)
    src = _refine_sources(features, src, coords.wrap, rounds, weights, patch, rng, pinned, scales, coarse_keep)
    if polish > 0 and min(*coords.source_size, coords.height, coords.width) >= POLISH_WINDOW:
        src = _polished(features, src, coords.wrap, polish, rng, pinned, seam_weight)
    if recut:
        src = recut_straight_seams(window_index(features, patch).texels, src, coords.wrap, pinned, recut_passes,
                                   bridges, band=recut_band)
    return _with_kept_blends(coords, src)


def halved(features: np.ndarray) -> np.ndarray:
    """``features [eh, ew, D]`` at half resolution: the mean of each 2 x 2 block (an odd last row or column dropped)."""
    ch, cw = features.shape[0] // 2, features.shape[1] // 2
    return features[:2 * ch, :2 * cw].reshape(ch, 2, cw, 2, -1).mean(axis=(1, 3))


def keeps_structure(coarse: np.ndarray, finest_variance: float, share: float) -> bool:
    """Whether a coarse exemplar ``coarse`` keeps at least ``share`` of the finest exemplar's appearance variance
    (``finest_variance``).  Where most of it lies in finer detail (thin cracks, grain, fine fibres), the coarse
    windows all look alike: matched there, the map is re-arranged by what the texture does not show, and the cuts
    it leaves can break what it does show (quilting's blocks keep the demo's cracks whole; re-arranged at the
    quarter scale, which keeps 0.50 of their variance, the cracks end in mid-cell: see ``synth.quilt``)."""
    return appearance_variance(coarse) >= share * finest_variance


def _refine_sources(features, src, wrap, rounds, weights, patch, rng, pinned, scales, coarse_keep=0.0,
                    finest_variance=None):
    """The refinement of flat sources ``src [H, W]``: first, while ``scales`` > 0, a half-size exemplar and
    output still hold :data:`COARSE_FIT` windows across and the half-size exemplar keeps ``coarse_keep`` of the
    variance (:func:`keeps_structure` against ``finest_variance``, by default this exemplar's), at half resolution
    (:func:`_coarse_first`), then here; ``rounds``: (rounds here, rounds at each coarser scale); ``weights``:
    (occurrence, contrast, seam)."""
    iterations, coarse_iterations = rounds
    if scales > 0 and min(features.shape[0], features.shape[1], *src.shape) >= 2 * COARSE_FIT * patch:
        coarse = halved(features)
        if finest_variance is None and coarse_keep > 0:
            finest_variance = appearance_variance(features)
        if coarse_keep <= 0 or keeps_structure(coarse, finest_variance, coarse_keep):
            src = _coarse_first(features, coarse, src, wrap, coarse_iterations, weights, patch, rng, pinned,
                                scales - 1, coarse_keep, finest_variance)
    index = window_index(features, patch)
    keep = (lambda new: new) if pinned is None else (lambda new, start=src: np.where(pinned, start, new))
    for _ in range(iterations):
        src = keep(optimise_step(index, src, wrap, weights, rng, keep))
        for _ in range(CORRECTIONS):
            src = keep(correction_pass(index.texels, src, wrap, rng))
    return src


def _polished(features, src, wrap, rounds, rng, pinned, seam_weight=SEAM_WEIGHT):
    """``src`` after ``rounds`` rounds at the finest scale with :data:`POLISH_WINDOW` windows, without the occurrence
    and contrast terms.  A synthesizer that refines with larger windows (the jump map's 12) keeps its structures
    whole but leaves its cuts where those windows met; small windows matched for their fit alone move the cuts
    to where the content agrees, and leave alone which exemplar areas are used, which the terms had settled."""
    return _refine_sources(features, src, wrap, (rounds, rounds), (0.0, 0.0, seam_weight, 0.0), POLISH_WINDOW, rng,
                           pinned, 0)


def _coarse_first(features, coarse_features, src, wrap, iterations, weights, patch, rng, pinned, scales,
                  coarse_keep, finest_variance):
    """``src`` after the refinement of its half-resolution version (2 x 2 averaged exemplar, every other output
    texel's source halved): where a coarse texel changed source, its 2 x 2 output texels take the new source's
    2 x 2 exemplar texels; elsewhere (and where pinned) the fine sources stay.  Windows of the same size cover
    twice the texture there, so structures larger than a window (colour areas, the sides of copied blocks) are
    matched and cut as a whole."""
    eh, ew = features.shape[:2]
    ch, cw = coarse_features.shape[:2]
    sy, sx = np.divmod(src[::2, ::2], ew)
    before = np.minimum(sy // 2, ch - 1) * cw + np.minimum(sx // 2, cw - 1)
    coarse_pinned = None if pinned is None else pinned[::2, ::2]
    after = _refine_sources(coarse_features, before, wrap and src.shape[0] % 2 == 0 and src.shape[1] % 2 == 0,
                            (iterations, iterations), weights, patch, rng, coarse_pinned, scales, coarse_keep,
                            finest_variance)
    h, w = src.shape
    rows, cols = np.arange(h) // 2, np.arange(w) // 2
    changed = (after != before)[np.ix_(rows, cols)]
    ay, ax = np.divmod(after[np.ix_(rows, cols)], cw)
    fine_y = np.minimum(2 * ay + (np.arange(h) % 2)[:, None], eh - 1)
    fine_x = np.minimum(2 * ax + (np.arange(w) % 2)[None, :], ew - 1)
    if pinned is not None:
        changed &= ~pinned
    return np.where(changed, fine_y * ew + fine_x, src)


def _pinned_mask(pinned, coords: CoordMap) -> np.ndarray | None:
    """``pinned`` as a boolean ``[H, W]`` array (None: nothing pinned); a clear error for another shape."""
    if pinned is None:
        return None
    mask = np.asarray(pinned)
    if mask.shape != (coords.height, coords.width) or mask.dtype.kind not in "bui":
        from btforge.errors import BtforgeInputError
        raise BtforgeInputError("refine_map argument 'pinned'",
                                f"expected a boolean mask of the map's shape {(coords.height, coords.width)}, found "
                                f"{mask.dtype} {mask.shape}", "pass one flag per output texel (True: keep its source)")
    return mask.astype(bool)


def _with_kept_blends(coords: CoordMap, src: np.ndarray) -> CoordMap:
    """The refined sources as a map; where a texel kept its (dominant) source, its blend record stays."""
    eh, ew = coords.source_size
    out = np.stack(np.divmod(src, ew), axis=-1).astype(np.int32)
    if not coords.blend_weight.size:
        return CoordMap(out, (eh, ew), wrap=coords.wrap, tile=coords.tile)
    heavier = coords.blend_weight > 0.5
    dominant = np.where(heavier[..., None], coords.blend_coords, coords.coords)
    kept = (dominant == out).all(axis=-1)
    first = np.where(kept[..., None], coords.coords, out)
    partner = np.where(kept[..., None], coords.blend_coords, out)
    weight = np.where(kept, coords.blend_weight, np.float32(0)).astype(np.float32)
    return CoordMap(np.ascontiguousarray(first), (eh, ew), np.ascontiguousarray(partner), np.ascontiguousarray(weight),
                    wrap=coords.wrap, tile=coords.tile)


def window_starts(length: int, patch: int, stride: int, offset: int, wrap: bool) -> np.ndarray:
    """Window origins along one output axis, ``stride`` apart from ``offset`` (wrapping, or clamped inside)."""
    if wrap:
        return np.arange(offset, offset + length, stride) % length
    starts = np.arange(offset - stride if offset else 0, length - patch + stride, stride)
    return np.unique(np.clip(starts, 0, max(0, length - patch)))


def optimise_step(index: WindowIndex, src: np.ndarray, wrap: bool, weights: tuple[float, float, float],
                  rng: np.random.Generator, keep=lambda labels: labels) -> np.ndarray:
    """One texture-optimisation round: every window matched (with the occurrence and contrast terms), then the
    coherent vote; ``weights``: (occurrence, contrast, seam)."""
    p = index.patch
    h, w = src.shape
    eh, ew = index.texels.shape[:2]
    rows, cols = jittered_windows(h, w, p, wrap, rng)                         # [ny, nx, p] each
    window_src = src[rows[..., :, None], cols[..., None, :]]                  # [ny, nx, p, p]
    ny, nx = rows.shape[:2]
    texels = index.texels.reshape(eh * ew, -1)
    query = texels[window_src].reshape(ny * nx, -1)
    occurrence, contrast, seam_weight, balance = weights
    origin, distance = _best_windows(index, query, window_src.reshape(-1, p, p), src, occurrence, contrast, balance)
    gy, gx = index.grid
    oy, ox = np.divmod(origin, gx)
    proposals = ((oy[:, None, None] + np.arange(p)[None, :, None]) * ew
                 + ox[:, None, None] + np.arange(p)[None, None, :]).reshape(ny, nx, p, p)
    cost = (distance / (p * p)).reshape(ny, nx)
    return _vote(index.texels, proposals, cost, rows, cols, src, wrap, rng, keep, seam_weight)


def jittered_windows(h: int, w: int, patch: int, wrap: bool, rng: np.random.Generator):
    """Rows and columns ``[ny, nx, patch]`` of the output windows of one round: a grid half a window apart at a
    random offset, each window then shifted by its own random 0 .. stride - 1 texels down and across (a window
    flush with an unwrapped border stays there).  Every texel stays covered (the window one grid step up and left
    of it reaches it whatever its shift), and the cuts the vote leaves along window sides no longer line up into
    long straight seams from window to window."""
    stride = max(1, patch // 2)
    ys = window_starts(h, patch, stride, int(rng.integers(stride)), wrap)
    xs = window_starts(w, patch, stride, int(rng.integers(stride)), wrap)
    shape = (len(ys), len(xs))
    top = ys[:, None] + rng.integers(0, stride, shape)
    left = xs[None, :] + rng.integers(0, stride, shape)
    if not wrap:
        top = np.where(ys[:, None] == 0, 0, np.minimum(top, max(0, h - patch)))
        left = np.where(xs[None, :] == 0, 0, np.minimum(left, max(0, w - patch)))
    steps = np.arange(patch)
    return (top[..., None] + steps) % h, (left[..., None] + steps) % w


def _best_windows(index: WindowIndex, query: np.ndarray, window_src: np.ndarray, src: np.ndarray,
                  occurrence: float, contrast: float = 0.0, balance: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Per query window (``[n, p * p * d]``, copied from ``window_src [n, p, p]``), the exemplar window origin
    (flat in the window grid) of least cost and its squared distance: the full squared distance plus
    ``occurrence`` x (the mean squared distance of two random windows) x how far its texels are used beyond
    their fair share, plus ``balance`` x that mean distance x how far its appearance classes are over-represented in
    the output (:func:`appearance_excess`), plus ``contrast`` x how much less variation it has than the query
    (:func:`window_energy`):
    nearest windows under a squared distance favour flat ones, which differ from a textured query by its own
    variation where another textured window differs by both, so texture optimisation alone drifts towards an
    exemplar's flat areas.  Candidates: the window copied now and, unless that is a whole exemplar window used no
    more than its share (it matches exactly and nothing can cost less), the approximately nearest windows in the
    reduced space."""
    ew = index.texels.shape[1]
    gy, gx = index.grid
    p = index.patch
    cy, cx = np.divmod(window_src[:, 0, 0], ew)
    current = np.minimum(cy, gy - 1) * gx + np.minimum(cx, gx - 1)
    offsets = np.arange(p)[:, None] * ew + np.arange(p)
    whole = (cy < gy) & (cx < gx) & (window_src == window_src[:, :1, :1] + offsets).all(axis=(1, 2))
    overuse = _overuse(src, index)
    searched = ~whole | (occurrence * overuse[current] > 0)
    penalty = occurrence * index.spread * overuse     # per exemplar window, in squared-distance units
    if balance > 0:
        excess = appearance_excess(src, index)
        searched |= excess[current] > 0
        penalty = penalty + balance * index.spread * excess
    k = min(CANDIDATES, len(index.reduced))
    cand = np.repeat(current[:, None], k + 1, axis=1)
    distance = np.zeros(len(query))
    if not searched.any():
        return current, distance
    rows = np.flatnonzero(searched)
    _, found = index.tree.query((query[rows] - index.mean) @ index.basis, k=k, eps=SEARCH_EPS, workers=cores())
    cand[rows, :k] = found.reshape(len(rows), k)
    rank = _rank_numpy if engine() == "numpy" else _rank_opencl
    extra = candidate_costs(index, query[rows], cand[rows], penalty, contrast)
    current[rows], distance[rows] = rank(index, query[rows], cand[rows], extra)
    return current, distance


def candidate_costs(index: WindowIndex, query: np.ndarray, cand: np.ndarray, penalty: np.ndarray,
                    contrast: float) -> np.ndarray:
    """``[n, c]`` float32 cost of each candidate besides its distance: its window's ``penalty`` (per origin) plus
    ``contrast`` x its shortfall in variation against the query (none where it varies as much or more)."""
    extra = penalty[cand].astype(np.float32)
    if contrast > 0:
        shortfall = np.maximum(window_energy(query, index.texels.shape[2])[:, None] - index.energy[cand], 0)
        extra = extra + np.float32(contrast) * shortfall.astype(np.float32)
    return extra


def _rank_numpy(index: WindowIndex, query: np.ndarray, cand: np.ndarray, extra: np.ndarray):
    """Per query window (``[n, p * p * d]``), of its candidate exemplar windows (``cand [n, c]``, origins flat in
    the window grid) the first of least squared distance plus ``extra`` (``[n, c]``, :func:`candidate_costs`): its
    origin and its squared distance (twin of ``rf_rank``: float32 sums over the window's values in row-major
    order)."""
    p = index.patch
    wy, wx = np.divmod(cand, index.grid[1])
    windows = index.texels[wy[..., None, None] + np.arange(p)[:, None], wx[..., None, None] + np.arange(p)[None, :]]
    windows = windows.reshape(len(cand), cand.shape[1], -1)
    dist = np.zeros(cand.shape, np.float32)
    for value in range(windows.shape[2]):  # one value at a time: the kernel's order of the sum
        diff = windows[:, :, value] - query[:, None, value]
        dist += diff * diff
    best = np.argmin(dist + np.asarray(extra, np.float32), axis=1)
    pick = np.arange(len(cand))
    return cand[pick, best], dist[pick, best].astype(np.float64)


def _rank_opencl(index: WindowIndex, query: np.ndarray, cand: np.ndarray, extra: np.ndarray):
    """:func:`_rank_numpy` by the kernel ``rf_rank`` (the same float32 sums in the same order)."""
    from .device import launch
    backend = _backend()
    n, width = cand.shape
    d = index.texels.shape[2]
    kernel = backend.kernel(KERNELS, "rf_rank", (f"-DD={d}", f"-DPATCH={index.patch}", f"-DCAND={width}"))
    origin, distance = np.empty(n, np.int32), np.empty(n, np.float32)
    buffers = [backend.to_device(index.texels), backend.to_device(np.ascontiguousarray(query, np.float32)),
               backend.to_device(cand.astype(np.int32)), backend.to_device(np.ascontiguousarray(extra, np.float32)),
               backend.host_output(origin), backend.host_output(distance)]
    texels, queries, candidates, extra_costs, origin_out, distance_out = buffers
    launch(backend, kernel, (n,), texels, np.int32(index.texels.shape[1]), np.int32(index.grid[1]), queries,
           candidates, extra_costs, np.int32(n), origin_out, distance_out)
    backend.finish_output(origin_out, origin)
    backend.finish_output(distance_out, distance)
    return origin.astype(np.int64), distance.astype(np.float64)


def _overuse(src: np.ndarray, index: WindowIndex) -> np.ndarray:
    """Per exemplar window, the mean use of its texels by ``src`` over their fair share, minus 1 (>= 0)."""
    eh, ew = index.texels.shape[:2]
    p = index.patch
    use = np.bincount(src.ravel(), minlength=eh * ew).reshape(eh, ew).astype(np.float64)
    fair = src.size / (eh * ew)
    return np.maximum(window_sums(use, (p, p)) / (p * p * fair) - 1.0, 0.0).ravel()


def appearance_classes(texels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each exemplar texel's class among :data:`APPEARANCE_CLASSES` k-means classes of its appearance
    (``texels [eh, ew, d]``; ``[eh * ew]`` labels), and each class's share of the exemplar (cached by content)."""
    def make():
        from scipy.cluster.vq import kmeans2
        flat = texels.reshape(-1, texels.shape[2]).astype(np.float64)
        k = min(APPEARANCE_CLASSES, len(flat))
        _, labels = kmeans2(flat, k, seed=0, minit="++", iter=10)
        return labels, np.bincount(labels, minlength=k) / len(labels)
    return _analyses.get_or_make(content_key(texels, extra=("classes", APPEARANCE_CLASSES)), make)


def appearance_excess(src: np.ndarray, index: WindowIndex) -> np.ndarray:
    """Per exemplar window, the mean over its texels of how far their appearance class is over-represented in
    ``src`` against the exemplar (the output's share of the class over the exemplar's, minus 1; >= 0)."""
    labels, shares = appearance_classes(index.texels)
    eh, ew = index.texels.shape[:2]
    p = index.patch
    used = np.bincount(labels[src.ravel()], minlength=len(shares)) / src.size
    excess = np.maximum(used / np.maximum(shares, 1e-12) - 1.0, 0.0)
    return (window_sums(excess[labels].reshape(eh, ew), (p, p)) / (p * p)).ravel()


def _vote(texels: np.ndarray, proposals: np.ndarray, cost: np.ndarray, rows: np.ndarray, cols: np.ndarray,
          src: np.ndarray, wrap: bool, rng: np.random.Generator, keep=lambda labels: labels,
          seam_weight: float = SEAM_WEIGHT) -> np.ndarray:
    """Each output texel's new source, among the sources its windows propose and its current one: a labelling
    of least data cost (the proposing window's match error per texel; the current source costs as much as the
    best proposal) plus ``seam_weight`` x seam cost (per 4-neighbour, 0 where the two sources continue each
    other, else the squared appearance difference between the neighbour's texel and the candidate's exemplar
    neighbour), found by :data:`SWEEPS` checkerboard sweeps of iterated conditional modes from the
    least-data-cost labels.  Whole windows win where they match best, and cuts between them run where the
    appearance agrees (a per-texel choice would scatter fragments of windows)."""
    h, w = src.shape
    n = h * w
    target = (rows[..., :, None] * w + cols[..., None, :]).ravel()
    per_texel = np.broadcast_to(cost[:, :, None, None], proposals.shape).ravel()
    order = np.argsort(target, kind="stable")
    target = target[order]
    count = np.bincount(target, minlength=n)
    slot = np.arange(len(target)) - (np.cumsum(count) - count)[target]
    slots = int(count.max()) + 1                                      # the last slot: the current source
    votes = np.full((n, slots), -1, np.int64)
    votes[target, slot] = proposals.ravel()[order]
    data = np.full((n, slots), np.inf, np.float32)
    data[target, slot] = per_texel[order]
    votes[:, -1] = src.ravel()
    data[:, -1] = np.minimum(data[:, :-1].min(axis=1), np.float32(1e30))  # a texel no window covers keeps its source
    start = np.argmin(data + np.float32(1e-6) * rng.random(data.shape, np.float32), axis=1)
    labels = keep(votes[np.arange(n), start].reshape(h, w))
    return _iterated_modes(texels, votes.reshape(h, w, slots), data.reshape(h, w, slots), labels, wrap, keep,
                           seam_weight)


def _iterated_modes(texels: np.ndarray, votes: np.ndarray, data: np.ndarray, labels: np.ndarray,
                    wrap: bool, keep=lambda labels: labels, seam_weight: float = SEAM_WEIGHT) -> np.ndarray:
    """:data:`SWEEPS` checkerboard sweeps: each texel takes the candidate (``votes [h, w, s]``, -1: none) of
    least ``data`` + ``seam_weight`` x seam cost against its 4-neighbours' current sources (without
    ``wrap``, none across the output's border)."""
    sweeps = _sweeps_numpy if engine() == "numpy" else _sweeps_opencl
    return sweeps(texels, votes, data, labels, wrap, keep, seam_weight)


def _sweeps_opencl(texels, votes, data, labels, wrap, keep, seam_weight=SEAM_WEIGHT):
    """:func:`_iterated_modes` by the kernel ``rf_sweep`` (one launch per half-sweep, from one labels buffer to
    the other; the same float32 sums in the same order as :func:`_sweeps_numpy`).  ``keep`` runs on the host
    after each half-sweep where it changes anything (pinned texels)."""
    from .device import launch
    backend = _backend()
    cl = backend.cl
    h, w, slots = votes.shape
    eh, ew, d = texels.shape
    kernel = backend.kernel(KERNELS, "rf_sweep", (f"-DD={d}",))
    labels = np.ascontiguousarray(labels, np.int32).reshape(h, w).copy()
    pinned = keep(labels) is not labels                  # the default keep hands its argument back
    inputs = [backend.to_device(np.asarray(texels, np.float32)), backend.to_device(votes.astype(np.int32)),
              backend.to_device(np.ascontiguousarray(data, np.float32))]
    flags = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
    current, following = (cl.Buffer(backend.context, flags, hostbuf=labels) for _ in range(2))
    # which labels the last two launches changed: at first, all (so every texel chooses)
    moved = [cl.Buffer(backend.context, flags, hostbuf=np.ones(h * w, np.uint8)) for _ in range(3)]
    for _ in range(SWEEPS):
        for part in (0, 1):
            launch(backend, kernel, (h, w), inputs[0], np.int32(eh), np.int32(ew), inputs[1], inputs[2],
                   np.int32(slots), current, following, np.int32(h), np.int32(w), np.int32(bool(wrap)),
                   np.int32(part), np.float32(seam_weight), moved[0], moved[1], moved[2])
            current, following = following, current
            moved = [moved[2], moved[0], moved[1]]
            if pinned:
                cl.enqueue_copy(backend.queue, labels, current)
                labels = np.ascontiguousarray(keep(labels), np.int32)
                cl.enqueue_copy(backend.queue, current, labels)
    cl.enqueue_copy(backend.queue, labels, current)
    return labels.astype(np.int64)


def _sweeps_numpy(texels, votes, data, labels, wrap, keep, seam_weight=SEAM_WEIGHT):
    """The twin of ``rf_sweep``: :func:`_iterated_modes` in NumPy."""
    h, w, _ = votes.shape
    flat = texels.reshape(-1, texels.shape[2])
    colour = (np.add.outer(np.arange(h), np.arange(w)) % 2).ravel()
    halves = [_half_sweep_terms(texels, votes, data, np.flatnonzero(colour == part), wrap) for part in (0, 1)]
    labels = labels.ravel().copy()
    for _ in range(SWEEPS):
        for active, choices, cost, sides in halves:
            total = cost.copy()
            for neighbour, continuation, continued, outside in sides:
                current = labels[neighbour]
                seam = ((continued - flat[current][:, None, :]) ** 2).sum(axis=2)
                seam[(continuation == current[:, None]) | outside[:, None]] = 0.0
                total += np.float32(seam_weight) * seam
            labels[active] = choices[np.arange(len(active)), np.argmin(total, axis=1)]
            labels = keep(labels.reshape(h, w)).ravel()
    return labels.reshape(h, w)


def _half_sweep_terms(texels: np.ndarray, votes: np.ndarray, data: np.ndarray, active: np.ndarray, wrap: bool):
    """What does not change between the sweeps for the ``active`` texels (flat indices): their candidates and
    data costs, and per 4-neighbour its flat index, the neighbour source that continues each candidate, the
    exemplar texel that continues each candidate there, and whether the neighbour lies outside the output."""
    eh, ew = texels.shape[:2]
    h, w, slots = votes.shape
    padded = edge_padded(texels)
    choices = votes.reshape(-1, slots)[active]
    vr, vc = np.divmod(np.maximum(choices, 0), ew)
    ay, ax = np.divmod(active, w)
    sides = []
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        ny, nx = ay + dy, ax + dx
        outside = np.zeros(len(active), bool) if wrap else (ny < 0) | (ny >= h) | (nx < 0) | (nx >= w)
        neighbour = (ny % h) * w + nx % w
        continued = beside(padded, (eh, ew), vr, vc, dy, dx)
        sides.append((neighbour, choices + dy * ew + dx, continued, outside))
    return active, choices, data.reshape(-1, slots)[active], sides


def correction_pass(texels: np.ndarray, src: np.ndarray, wrap: bool, rng: np.random.Generator) -> np.ndarray:
    """A random half of the texels each take, of its own source and the continuations of its 4-neighbours'
    sources, the one whose exemplar neighbourhood (the texel and its 4-neighbours) best matches the output's."""
    h, w = src.shape
    best = (_correct_numpy if engine() == "numpy" else _correct_opencl)(texels, src)
    if not wrap:  # the border rows and columns were compared against the far side: leave them as they are
        best[[0, -1], :] = src[[0, -1], :]
        best[:, [0, -1]] = src[:, [0, -1]]
    chosen = rng.random((h, w)) < 0.5
    return np.where(chosen, best, src)


def _correct_opencl(texels: np.ndarray, src: np.ndarray) -> np.ndarray:
    """:func:`_correct_numpy` by the kernel ``rf_correct`` (the same float32 sums in the same order)."""
    from .device import launch
    backend = _backend()
    eh, ew, d = texels.shape
    h, w = src.shape
    kernel = backend.kernel(KERNELS, "rf_correct", (f"-DD={d}",))
    best = np.empty((h, w), np.int32)
    inputs = [backend.to_device(np.asarray(texels, np.float32)), backend.to_device(src.astype(np.int32)),
              backend.host_output(best)]
    launch(backend, kernel, (h, w), inputs[0], np.int32(eh), np.int32(ew), inputs[1], np.int32(h), np.int32(w),
           inputs[2])
    backend.finish_output(inputs[2], best)
    return best.astype(np.int64)


def _correct_numpy(texels: np.ndarray, src: np.ndarray) -> np.ndarray:
    """Per output texel, of its own source and the continuations of its 4-neighbours' sources (wrapping around the
    output), the first whose exemplar neighbourhood best matches the output's (the twin of ``rf_correct``)."""
    eh, ew, d = texels.shape
    h, w = src.shape
    pad = edge_padded(texels)
    out = texels.reshape(-1, d)[src]                                     # [h, w, d]
    cross = [(0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)]
    seen = [np.roll(out, (-oy, -ox), axis=(0, 1)) for oy, ox in cross]
    sr, sc = np.divmod(src, ew)
    best_err = np.full((h, w), np.inf, np.float32)
    best = src.copy()
    for dy, dx in cross:
        # the neighbour at (y + dy, x + dx) proposes its source moved back by (dy, dx)
        nr = np.roll(sr, (-dy, -dx), axis=(0, 1)) - dy
        nc = np.roll(sc, (-dy, -dx), axis=(0, 1)) - dx
        ok = (nr >= 0) & (nr < eh) & (nc >= 0) & (nc < ew)
        centre = (np.clip(nr, 0, eh - 1) + 1) * (ew + 2) + np.clip(nc, 0, ew - 1) + 1
        err = np.zeros((h, w), np.float32)
        for (oy, ox), there in zip(cross, seen):
            err += ((pad[centre + oy * (ew + 2) + ox] - there) ** 2).sum(axis=2)
        better = ok & (err < best_err)
        best_err = np.where(better, err, best_err)
        best = np.where(better, (centre // (ew + 2) - 1) * ew + centre % (ew + 2) - 1, best)
    return best
