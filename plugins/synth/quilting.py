"""Image quilting of reflectance functions with an exact projection-kernel rejection search.

Blocks of the exemplar are laid down in raster order (Efros & Freeman 2001) on the per-texel appearance vectors
of :func:`~btforge.plugins.synth.features.texel_features` (for a PTM: orthonormal Legendre coefficients, where
vector distance is function distance - Hel-Or, Malzbender & Gelb 2003).  For each block position the overlap with
what is already synthesized is compared with the same overlap of every exemplar block, one is picked at random
among those within ``(1 + tolerance)`` of the best, and the blocks are joined by a minimum-error boundary cut or
by linear blending.

The search (:mod:`.quilt_search`: brute force, or the exact projection-kernel rejection of Hel-Or & Hel-Or
2002, which keeps the brute force's picks) is the costly part; its module says how it works.

Candidates are all block positions lying wholly inside the exemplar (the exemplar is not treated as periodic).
"""
from __future__ import annotations

import collections
import dataclasses
import math
import time

import numpy as np

from btforge import Param
from btforge.buffers import CoordMap
from btforge.errors import BtforgeInputError

from .feather import by_grain, feathered, grain, local_steps, records_mix
from .features import texel_features, window_sums
from .quilt_search import SEARCHES, QuiltSearch
from .quilt_seams import _region, _span, blend_alpha, cut_mask
from .synthesizer import (AUTO, BUDGET_AREA, SMALL_OUTPUT_BUDGET, auto_budget, declare_synthesizer,
                          refine_params, refined, within_copy_budget)


SEAMS = ("cut", "blend")
#: Copy budget where the output has more than :data:`BUDGET_AREA` x the exemplar's texels: no exemplar area copied
#: beyond 1.5 x its fair share (plus one copy).  At 2 the 192 x 192 crop of the painted icon came out mostly ground
#: (SWD 1.84 x the shuffled blocks, seeds 0-1; 0.93 at 1.5); the 192 x 192 stones, plaster and fibres come out the
#: same at 1.5.  At 1 the held-out procedural exemplar's straight seams pass 2 % of its seams (1.43 over seeds 0-3).
BUDGET = 1.5
#: Passes of the refinement's re-cut of straight seams, as k-coherence and the jump map: the third pass finds the
#: runs the first two have shortened or joined (over seeds 0-3 on the held-out procedural exemplar it takes the
#: straight share of the seam edges from 2.2 % to 1.7 %; on the other exemplars of the quality table and the tablet,
#: seams and evenness move by 0.04 at most, straight seams by -0.16 to +0.07, SWD by -0.20 to +0.02).
RECUT_PASSES = 3
#: The refinement's contrast weight where the automatic ``contrast`` is on (an exemplar about as large as the
#: output): 8, half the others'.  At 16 quilting's straight seams on the procedural exemplar rose over their target
#: (1.32 at 2.3 % of the seam edges at 256 from 256, 1.41 at 2.2 % at 256 from 224); at 8 they pass (1.17 at 2.2 %;
#: 1.45 at 1.8 %, under the 2 % share the target counts from) with SWD over the shuffled blocks 1.42 and 0.66 (from
#: 1.84 and 0.91 without the term).
AUTO_CONTRAST = 8.0
#: Weight of the seam cost in the refinement's vote, twice the shared default: its cuts run where the two sides continue
#: each other more closely.  On the 21 main crops of the synthesis bench (seeds 0-1) seams fall on 20 and the bumps' pass
#: (1.305 -> 1.26); SWD over the shuffled blocks rises by 0.03 at the median.  At 4 seams fall further but SWD rises on
#: 16 of the 21 (the fibres 1.26 -> 1.43, Benchmarks).
SEAM_WEIGHT = 2.0
#: Quilting feathers the seams whose step is over 2 x the exemplar's steps around their sources (the shared
#: default: 1.5).  At 1.5 its cuts across the fibres blended a ninth of their texels and the fibres' SWD over the
#: shuffled blocks rose from 1.42 to 1.58 over four seeds (a miss); at 2 it is 1.48, and the bumps' seams still pass
#: (1.13 against 1.09, Benchmarks).
FEATHER_STEP = 2.0
#: A coarser scale of the refinement runs only where its 2 x 2 averaged exemplar keeps at least this share of the
#: exemplar's appearance variance (:func:`.refine.keeps_structure`).  Quilting's blocks keep an exemplar's structures
#: whole; where grain or a network of thin lines carries most of the variance, the coarse windows all look alike,
#: and the re-arrangement chosen there cut the demo's cracks into ends in mid-cell and left crack-free areas (192 x
#: 192, seeds 0-3: SWD over the shuffled blocks 2.41, 0.88, 2.35, 1.33 with its quarter scale, which keeps 0.50).
#: At 0.6 the quarter scale is skipped on the cracks, the stucco (0.56), stones, gravel, fibres and strands (0.25-0.44)
#: and the half scale too on the plaster (0.59 there); both stay on everything smoother (the bumps keep 0.95 at the
#: quarter scale and need it: their straight seams 1.17 -> 1.44 without it).  On grain the coarse scales traded patch
#: statistics for seams: the fibres' SWD 1.45 -> 0.97, seams 0.80 -> 0.85 (Benchmarks).
COARSE_KEEP = 0.6


#: The automatic overlap (``overlap: 0``), as a share of the block side: a quarter on a smooth exemplar, a sixth (Efros
#: & Freeman's) on a grainy one, by the exemplar's grain (:func:`.feather.by_grain`).  Where the exemplar is smooth
#: every cut shows, and a wider overlap gives the boundary cut room to go round a bump or a colour area instead of
#: through it along the block's side; on the bumps (192 x 192, seeds 0-1) straight seams 1.42 -> 1.17 at 4.7 % of the
#: seam edges, the last target quilting missed on the main crops.  On a grainy exemplar the cut hides in the grain
#: anyway, and the wider overlap makes the block choice favour blocks that are easy to match: the fibres' SWD over the
#: shuffled blocks 1.45 -> 1.52, a miss (Benchmarks).
SMOOTH_OVERLAP, GRAINY_OVERLAP = 1 / 4, 1 / 6


# ----------------------------------------------------------------------------------------------- layout


@dataclasses.dataclass(frozen=True)
class AxisLayout:
    """Where blocks start along one axis and how much each overlaps its neighbours.

    ``before[i]`` is block i's overlap with block i - 1 (0 for the first block); ``after[i]`` its overlap with
    block 0 across the periodic boundary (non-zero only for the last block of a wrapped layout).  ``canvas`` is the
    length synthesized: the output size when wrapping (indices wrap modulo it), else enough whole blocks to cover
    the output, which is then cropped.
    """

    starts: tuple[int, ...]
    before: tuple[int, ...]
    after: tuple[int, ...]
    canvas: int


def axis_layout(size: int, block: int, overlap: int, wrap: bool) -> AxisLayout:
    """Block placement along one axis (see :class:`AxisLayout`).

    Without wrap, blocks step by ``block - overlap`` and the last one may run past ``size``.  With wrap, the
    ``n = ceil(size / step)`` blocks must tile a period of exactly ``size``, so steps are spread evenly
    (``floor(size / n)`` or one more): overlaps are ``overlap`` or a little wider, never narrower.
    """
    step = block - overlap
    if not wrap:
        n = max(1, -(-(size - overlap) // step))
        starts = tuple(i * step for i in range(n))
        return AxisLayout(starts, (0,) + (overlap,) * (n - 1), (0,) * n, (n - 1) * step + block)
    n = -(-size // step)
    starts = tuple(i * size // n for i in range(n))
    ends = starts[1:] + (size,)
    seams = tuple(block - (e - s) for s, e in zip(starts, ends))  # seam i joins block i and block i + 1 (mod n)
    return AxisLayout(starts, (0,) + seams[:-1], (0,) * (n - 1) + (seams[-1],), size)


def validate(exemplar_size: tuple[int, int], size, block: int, overlap: int, wrap: bool, tolerance: float = 0.0):
    """Raise :class:`BtforgeInputError` naming the parameter when the quilting parameters cannot work."""
    ex_h, ex_w = exemplar_size
    if block < 3:
        raise BtforgeInputError("quilt 'block'", f"expected at least 3 texels, found {block}",
                                "use a block of about the size of the exemplar's features, e.g. 32")
    if block > min(ex_h, ex_w):
        raise BtforgeInputError("quilt 'block'",
                                f"expected a block that fits in the {ex_h} x {ex_w} exemplar, found {block}",
                                f"use block <= {min(ex_h, ex_w)}")
    if overlap < 1 or 2 * overlap >= block:
        raise BtforgeInputError("quilt 'overlap'",
                                f"expected 1 <= overlap < block / 2 = {block / 2:g}, found {overlap}",
                                f"use e.g. overlap {max(1, block // 6)} (block // 6)")
    if len(size) != 2 or min(size) < block:
        raise BtforgeInputError("quilt 'size'",
                                f"expected an [H, W] of at least the block ({block}) each, found {list(size)}",
                                f"use a size of at least [{block}, {block}] or a smaller block")
    if tolerance < 0 or not math.isfinite(tolerance):
        raise BtforgeInputError("quilt 'tolerance'", f"expected a finite value >= 0, found {tolerance}",
                                "use e.g. 0.1: blocks within 10% of the best overlap error are eligible")
    if wrap:
        step = block - overlap
        for axis, n in zip(("height", "width"), size):
            layout = axis_layout(n, block, overlap, True)
            widest = max(layout.before + layout.after)
            if 2 * widest >= block:
                raise BtforgeInputError(
                    "quilt 'size'", f"a periodic {axis} of {n} needs block overlaps of {widest} texels, expected "
                    f"< block / 2 = {block / 2:g}",
                    f"use a multiple of block - overlap = {step}, e.g. {-(-n // step) * step}")



# ----------------------------------------------------------------------------------------------- synthesis


@dataclasses.dataclass
class QuiltResult:
    coords: CoordMap
    stats: dict


def quilt_features(feats: np.ndarray, size, block: int = 32, overlap: int = 6, *, search: str = "rejection",
                   seam: str = "cut", tolerance: float = 0.1, wrap: bool = False, seed: int = 0,
                   engine: str = "opencl", spread: bool = False, budget: float = 0.0) -> QuiltResult:
    """Quilt appearance vectors ``feats [H, W, D]`` into a coordinate map of ``size = (H, W)``.

    ``engine='numpy'`` runs the searches on the NumPy references instead of OpenCL.  ``spread``: among the
    eligible blocks, the one whose exemplar area the output copies least so far.  ``budget`` > 0: only blocks
    whose exemplar area is copied at most ``budget`` x its fair share (plus one copy) are eligible (see
    :meth:`_Canvas.within_budget`).  Returns the map and
    statistics (blocks, candidates, per-projection rejected fractions, timings).
    """
    start_time = time.perf_counter()
    feats = _checked_features(feats, search, seam)
    height, width = (int(v) for v in size)
    validate(feats.shape[:2], (height, width), block, overlap, wrap, tolerance)
    lay_y = axis_layout(height, block, overlap, wrap)
    lay_x = axis_layout(width, block, overlap, wrap)
    uses = collections.Counter((ty, by, lx, rx) for ty, by in zip(lay_y.before, lay_y.after)
                               for lx, rx in zip(lay_x.before, lay_x.after))
    uses.pop((0, 0, 0, 0), None)  # the first block is not searched
    searcher = QuiltSearch(feats, block, method=search, tolerance=tolerance, engine=engine)
    projections = searcher.budget(uses)
    quilt = _Canvas(feats, block, (lay_y.canvas, lay_x.canvas), blend=seam == "blend")
    rng = np.random.default_rng(seed)
    placed: dict[tuple[int, int], tuple[int, int]] = {}
    for i, y in enumerate(lay_y.starts):
        rows = _span(y, block, lay_y.canvas)
        for j, x in enumerate(lay_x.starts):
            region = _region(rows, _span(x, block, lay_x.canvas))
            key = (lay_y.before[i], lay_y.after[i], lay_x.before[j], lay_x.after[j])
            if key == (0, 0, 0, 0):
                pick = int(rng.integers(searcher.n_cand))
            else:
                # Blocks continuing the neighbours' exemplar positions often match well: they seed the threshold.
                hints = tuple(searcher.candidate(placed[(a, b)][0] + y - lay_y.starts[a],
                                                 placed[(a, b)][1] + x - lay_x.starts[b])
                              for a, b in ((i, j - 1), (i - 1, j), (i - 1, j - 1)) if (a, b) in placed)
                usage = quilt.block_usage() if spread or budget > 0 else None
                pick = searcher.pick(searcher.shape(key, projections[key]), quilt.canvas[region], rng, hints,
                                     usage if spread else None, quilt.within_budget(usage, budget))
            placed[(i, j)] = divmod(pick, searcher.cols)
            quilt.place(region, placed[(i, j)], key)
    stats = _quilt_stats(searcher, search, len(lay_y.starts) * len(lay_x.starts), feats.shape[2], start_time)
    return QuiltResult(quilt.coord_map((height, width), wrap), stats)


def _checked_features(feats: np.ndarray, search: str, seam: str) -> np.ndarray:
    feats = np.ascontiguousarray(feats, np.float32)
    if feats.ndim != 3:
        raise BtforgeInputError("quilt 'exemplar'", f"expected [H, W, D] appearance vectors, found shape {feats.shape}",
                                "pass texel_features(buffer), which gives every per-texel buffer that shape")
    if not np.isfinite(feats).all():
        raise BtforgeInputError("quilt 'exemplar'", f"expected finite texel values, found "
                                f"{int((~np.isfinite(feats)).sum())} NaN/Inf", "repair the exemplar before synthesis")
    if search not in SEARCHES:
        raise BtforgeInputError("quilt 'search'", f"expected one of {SEARCHES}, found {search!r}",
                                "use 'rejection' (fast, exact) or 'brute' (the reference)")
    if seam not in SEAMS:
        raise BtforgeInputError("quilt 'seam'", f"expected one of {SEAMS}, found {seam!r}",
                                "use 'cut' (minimum-error boundary) or 'blend' (linear blending)")
    return feats


class _Canvas:
    """The quilt being laid: per canvas texel its exemplar source (and blend partner and weight), its
    appearance vector, and how often each exemplar texel has been copied."""

    def __init__(self, feats: np.ndarray, block: int, shape: tuple[int, int], blend: bool):
        self.feats, self.block, self.blend = feats, block, blend
        self.primary = np.zeros(shape + (2,), np.int32)
        self.second = np.zeros(shape + (2,), np.int32)
        self.weight = np.zeros(shape, np.float32)
        self.canvas = np.zeros(shape + (feats.shape[2],), np.float32)   # what the output's vectors will be
        self.grid = np.indices((block, block), dtype=np.int32).transpose(1, 2, 0)
        self.copied = np.zeros(feats.shape[:2], np.int64)

    def block_usage(self) -> np.ndarray:
        """Per candidate block (flat, row-major over origins): texels of its exemplar area copied so far."""
        return window_sums(self.copied, (self.block, self.block)).ravel()

    def within_budget(self, usage: np.ndarray, budget: float) -> np.ndarray | None:
        """Per candidate block, whether its exemplar area is within the copy budget
        (:func:`~.synthesizer.within_copy_budget`; Efros & Freeman's tolerance is relative to the best overlap
        error, so on a plain ground whose blocks match each other almost exactly only ground blocks would be
        eligible)."""
        return within_copy_budget(usage, self.copied.sum(), self.copied.size, self.block * self.block, budget)

    def place(self, region, origin: tuple[int, int], key: tuple[int, int, int, int]) -> None:
        r0, c0 = origin
        b = self.block
        self.copied[r0:r0 + b, c0:c0 + b] += 1
        new_feats = self.feats[r0:r0 + b, c0:c0 + b]
        new_coords = self.grid + np.array([r0, c0], np.int32)
        if key == (0, 0, 0, 0):
            self.primary[region] = new_coords
            self.second[region] = new_coords
            self.weight[region] = 0
            self.canvas[region] = new_feats
        elif not self.blend:
            old = self.canvas[region]
            err = np.einsum("ijk,ijk->ij", old - new_feats, old - new_feats)
            show = cut_mask(err, key)
            self.primary[region] = np.where(show[..., None], new_coords, self.primary[region])
            self.canvas[region] = np.where(show[..., None], new_feats, old)
        else:
            alpha = blend_alpha(b, key)
            dominant = np.where((self.weight[region] > 0.5)[..., None], self.second[region], self.primary[region])
            whole = alpha >= 1
            first_texel = np.where(whole[..., None], new_coords, dominant)
            w = np.where(whole, np.float32(0), alpha)
            self.primary[region] = first_texel
            self.second[region] = new_coords
            self.weight[region] = w
            self.canvas[region] = ((1 - w)[..., None] * self.feats[first_texel[..., 0], first_texel[..., 1]]
                                   + w[..., None] * new_feats)

    def coord_map(self, size: tuple[int, int], wrap: bool) -> CoordMap:
        height, width = size
        source = (self.feats.shape[0], self.feats.shape[1])
        coords = np.ascontiguousarray(self.primary[:height, :width])
        if not self.blend:
            return CoordMap(coords, source, wrap=wrap)
        w = self.weight[:height, :width]
        other = np.where((w > 0)[..., None], self.second[:height, :width], coords)
        return CoordMap(coords, source, np.ascontiguousarray(other), np.ascontiguousarray(w), wrap=wrap)


def _quilt_stats(searcher: QuiltSearch, search: str, blocks: int, dims: int, start_time: float) -> dict:
    return {
        "search": search,
        "blocks": blocks,
        "candidates": searcher.n_cand,
        "features": dims,
        "overlap_shapes": len(searcher.shapes),
        "queries": searcher.queries,
        "full_distances": searcher.full_distances,
        "full_distance_fraction": round(searcher.full_distances / max(1, searcher.queries * searcher.n_cand), 5),
        "projections": {"/".join(map(str, k)): len(s.funcs) for k, s in searcher.shapes.items() if s.funcs is not None},
        "rejected_after_projection": searcher.rejected_fractions(),
        "host_distances": searcher.host_distances,
        "precompute_s": round(searcher.precompute_s, 4),
        "search_s": round(searcher.search_s, 4),
        "total_s": round(time.perf_counter() - start_time, 4),
    }


# ----------------------------------------------------------------------------------------------- stage


@declare_synthesizer(
    "synth.quilt", deprecated_names=("quilt",),
    version="25",  # 25: a coarser scale of the refinement only where it keeps 0.6 of the exemplar's appearance variance (param coarse_keep): the quarter scale skipped on grainy exemplars and thin-line networks; 24: the automatic overlap (overlap 0) is a quarter of the block on smooth exemplars, a sixth on grainy ones, by the exemplar's grain (was a sixth on all); 23: the refinement's balance term on by default where the output has at most 1.5 x the exemplar's texels (param appearance_balance, -1: automatic, 16 there); 22: straight seams whose re-cut bands overlap are re-cut in separate groups, so a sliver's far piece is offered across it; 21: seams cross-faded over 3 texels on either side (feather 3, was 1); 20: copy budget 0.5 where the output has at most 2 x the exemplar's texels (budget -1: automatic; 1.5 beyond); 19: linear exemplars (stacks, linear fits of light only) compared as a screen shows them, at 25 probe lights sRGB-encoded, 16 principal components; 18: sRGB PTM, SH and HSH exemplars feathered too, their records mixed as display values; 17: linear lrgb exemplars feathered too, through the rgb PTM of the same functions, at steps over 2 x the exemplar's around them (was 1.5); 16: seams cross-faded over 1 texel on blendable exemplars (param feather); 15: the refinement's vote weighs seams 2 x (param seam_weight: seams lower, the bumps' pass); 14: one polish round by default (param polish: seams lower, the knit's pass); 13: the re-cut weighs a straight seam edge that stays 1.5 x its appearance difference (about half the straight seams); 12: the refinement's contrast term on by default where the exemplar is about as large as the output (contrast -1: automatic); 11: copy budget 1.5; 10: three re-cut passes; 9: bridging pieces over straight seams; 8: a copy budget (2) on the blocks' exemplar areas; 7: straight seams re-cut by minimum cuts, the refinement's candidate distances summed in a fixed order (OpenCL kernels); 6: coarse scales first (scales 2), windows jittered one by one; 5: occurrence weight 1 by default; 2: the shared refinement; 3: refinement by a coherent vote; 4: approximate window search, whole windows kept
    params=[
        Param("block", "int", 32, "block side in texels", low=3),
        Param("overlap", "int", 0, "overlap between neighbouring blocks in texels (1 <= overlap < block / 2); "
              "0 picks it by the exemplar's grain: a quarter of the block on a smooth exemplar (every cut "
              "shows, and a wider overlap lets the boundary cut go round a bump instead of along the block's side), "
              "a sixth on a grainy one (the cut hides in the grain), linearly between; at least 1", low=0),
        Param("search", "choice", "rejection", "rejection: exact projection-kernel search (fast); brute: every "
              "candidate's full distance (reference)", choices=SEARCHES),
        Param("seam", "choice", "cut", "cut: minimum-error boundary cut; blend: linear blending across overlaps",
              choices=SEAMS),
        Param("tolerance", "float", 0.5, "candidates within (1 + tolerance) x the best overlap error are eligible; "
              "one is picked among them (see 'spread')", low=0.0),
        Param("budget", "float", AUTO, "a block is eligible only while its exemplar area is copied at most "
              "budget x its fair share (the texels copied so far spread evenly over the exemplar) plus one copy, "
              "so a plain ground that matches itself everywhere cannot crowd out the exemplar's other parts; "
              f"negative (the default): {SMALL_OUTPUT_BUDGET:g} where the output has at most {BUDGET_AREA:g} x the "
              f"exemplar's texels (each part used about equally), else {BUDGET:g}; 0: no limit; lower it, e.g. to 1, "
              "for an output many times the exemplar's area where a plain ground matches itself better than the "
              "rest does", low=-1.0),
        Param("spread", "bool", True, "pick, among the eligible blocks, one whose exemplar area the output copies "
              "least so far (ties at random), so every part of the exemplar gets used; false: any eligible block"),
        *refine_params(auto_weight=AUTO_CONTRAST, seam_weight=SEAM_WEIGHT, feather_step=FEATHER_STEP),
        Param("coarse_keep", "float", COARSE_KEEP, "share of the exemplar's appearance variance a coarser scale of "
              "the refinement must keep (its 2 x 2 averaged exemplar against the exemplar) to be refined: where grain "
              "or thin lines carry more, the coarse windows all look alike, and the re-arrangement chosen there cuts "
              "through what the blocks kept whole (0: every scale 'scales' allows)", low=0.0, high=1.0),
    ],
)
def quilt(ctx, exemplar, *, size, wrap, seed, block, overlap, search, seam, tolerance, budget, spread, refine,
          occurrence, contrast, appearance_balance, scales, polish, seam_weight, feather, coarse_keep):
    """Synthesize a larger texture by image quilting of per-texel reflectance functions.

    Exemplar blocks are laid in raster order (Efros & Freeman 2001) on the texels' appearance vectors
    (:func:`.features.texel_features`: for a PTM fitted to display values the orthonormal Legendre coefficients,
    where vector distance equals function distance - Hel-Or, Malzbender & Gelb 2003; for a stack or a linear fit
    its display values at probe lights, reduced to 16 principal components).  Each block is chosen among the exemplar
    blocks (every position lying wholly inside the exemplar) whose overlap with the already synthesized texture has
    a sum of squared differences within ``(1 + tolerance)`` x the best (with ``spread``, one whose exemplar area
    is copied least so far; else any, at random), and joined by a minimum-error boundary cut
    (``seam: cut``) or linear blending (``seam: blend``, recorded as the map's blend weights).  With ``wrap`` the
    last row and column of blocks are also matched against the first, so the result tiles seamlessly; block
    overlaps are then spread evenly and may be a texel wider than ``overlap``.

    **Copy budget** (``budget``): only blocks whose exemplar area has been copied at most ``budget`` x its fair
    share so far (the copied texels spread evenly over the exemplar), plus one copy of a block, are eligible, and
    the tolerance is taken from the best of those.  Efros & Freeman's tolerance is relative to the best match:
    where most of the exemplar is a smooth ground whose blocks continue each other almost exactly (an object on
    a ground, a relief with a few thin lines), only ground blocks are ever within it, and the output is ground.
    Within the budget the ground gets its share and the rest of the exemplar is used too (the occurrence idea of
    Kaspar et al. 2015, as a hard limit).  The one copy it always allows weighs most where the output is only a
    few times the exemplar's area, so the automatic budget is 0.5 where the output has at most twice the
    exemplar's texels (no part copied much more than the others: about two copies at most) and 1.5 where it has
    more (a plain ground may take up to one and a half times its share; 1 keeps it to about its share).

    ``search: rejection`` (Hel-Or & Hel-Or 2002) projects every candidate's overlap, once per overlap shape, onto up
    to 1024 orthonormal Haar functions of the overlap (one feature dimension each, most energetic first); for each
    block, the sum of squared projected differences is a lower bound on the full distance and rules out almost all
    candidates, and only the survivors get full distances.  Safety margins make it exact: it returns the same
    eligible blocks, hence the same picks, as ``search: brute``.  The stored projections take up to 128 MB.

    **Refinement** (``refine`` rounds, ``occurrence`` weight, ``scales``; :mod:`.refine`): the map finally goes through
    the shared texture optimisation with an occurrence term and corrections, at two coarser scales first, so seams
    follow the content, and structures larger than the fine windows (colour areas, cut stones) are matched as a whole (a
    coarser scale only where it keeps ``coarse_keep`` of the exemplar's appearance variance: on a grainy exemplar or a
    network of thin cracks the quarter scale is skipped); ``polish`` final rounds without the occurrence and contrast
    terms then move the cuts left where windows met to where the content agrees.  Where the output has at most 1.5 x the
    exemplar's texels the balance term (``appearance_balance``) charges windows of appearance classes the output holds
    beyond their share of the exemplar (the held-out procedural exemplar at 256: SWD over the shuffled blocks 0.93 ->
    0.83).

    Outputs
    -------
    coords : CoordMap
        ``[H, W, 2]`` exemplar coordinates (replay on any representation with ``synth.materialize``).

    Notes
    -----
    ``rejected_after_projection`` lists the mean fraction of candidates ruled out after each projection;
    ``full_distance_fraction`` the fraction whose full distance was computed.
    """
    exemplar_size = (exemplar.height, exemplar.width)
    validate(exemplar_size, size, block, overlap or max(1, block // 6), wrap, tolerance)  # before any work
    feats = texel_features(exemplar)
    steps = local_steps(feats)
    if not overlap:   # the automatic overlap, whose periodic layout is checked too
        overlap = auto_overlap(block, grain(feats, steps))
        validate(exemplar_size, size, block, overlap, wrap, tolerance)
    ctx.note("overlap", overlap)
    result = quilt_features(feats, size, block, overlap, search=search, seam=seam, tolerance=tolerance, wrap=wrap,
                            seed=seed, spread=spread,
                            budget=auto_budget(budget, size, exemplar_size, BUDGET))
    for key, value in result.stats.items():
        ctx.note(key, value)
    coords = refined(ctx, feats, result.coords, refine=refine, occurrence=occurrence, scales=scales, seed=seed,
                     recut_passes=RECUT_PASSES, contrast=contrast, auto_weight=AUTO_CONTRAST, polish=polish,
                     seam_weight=seam_weight, balance=appearance_balance, coarse_keep=coarse_keep)
    return {"coords": feathered(coords, feather, records_mix(exemplar), feats, FEATHER_STEP, steps)}


def auto_overlap(block: int, grain_ratio: float) -> int:
    """The overlap ``overlap: 0`` picks for blocks of ``block`` texels on an exemplar of ``grain_ratio``
    (:func:`.feather.grain`): :data:`SMOOTH_OVERLAP` of the block on a smooth exemplar, :data:`GRAINY_OVERLAP` on a
    grainy one (as ``block // 6``), rounded down; at least 1 and under half the block."""
    share = by_grain(grain_ratio, SMOOTH_OVERLAP, GRAINY_OVERLAP)
    return max(1, min(int(share * block), (block - 1) // 2))


STAGES = [quilt]
