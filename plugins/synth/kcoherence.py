"""Hierarchical k-coherence synthesis (Tong et al. 2002, as adapted to BTFs by Bosserhoff & Nicoll).

Analysis (per pyramid level, cached per exemplar content and analysis params: another seed or size costs only
the synthesis)
    Textons of the appearance vectors (:mod:`.textons`) give the synthesis its one-lookup texel distance; the
    coherence set of every exemplar texel - its k - 1 texels with the most similar n x n neighbourhoods of the
    real features - comes from the shared neighbourhood search (:func:`.search.similar_texels`, ``search``
    fast or exact).
Synthesis
    See :func:`kcoherence` (the stage) for the order of work and why it is still causal.

Every OpenCL kernel (``kcoherence.cl``) has a NumPy twin here that performs the same float32 arithmetic in the
same order, so ``engine="numpy"`` gives bit-identical results (tests compare them).
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from btforge import Param
from btforge.backend import get_backend
from btforge.buffers import CoordMap
from btforge.errors import BtforgeInputError

from .block_start import CANDIDATES, matched_blocks
from .device import LOCAL, launch, round_up
from .feather import feathered, records_mix
from .features import downsample, texel_features
from .scan_order import coherent_fraction, level_sizes, output_neighbours, pad_textons, search_offsets, wavefronts
from .search import ContentCache, content_key, similar_texels
from .synthesizer import (AUTO, BUDGET_AREA, MAX_K, MAX_NEIGHBORHOOD, SMALL_OUTPUT_BUDGET, auto_budget, check_params,
                          declare_synthesizer, refine_params, refined, search_param)
from .textons import DEFAULT_TEXTONS, Textons, normalise_features, texton_analysis

KERNELS = Path(__file__).with_name("kcoherence.cl")
CAUSAL_ORDER = "single"      # "single": a causal pass is one work-group looping over wavefronts; "launch": one each
CAUSAL_GROUP = 64
KSET_EXCLUDE = 1             #: coherence-set members are more than this many texels (Chebyshev) from the texel
CORRECTIONS = 1              #: default correction passes per level (the coarsest gets one more: the random border)
MAX_CORRECTIONS = 8
COVERAGE = 0.5               #: default coverage tolerance (0: off; measured best of 0.05-1, README)
COVERAGE_CELL = 4            #: exemplar texels per side of a cell whose use the coverage tie-break evens out
ENGINES = ("opencl", "numpy")
BLOCKS = -1                  #: default side of the exemplar pieces the synthesis starts from (-1: auto)
MIN_AUTO_BLOCK = 16          #: auto: a sixth of the exemplar's shorter side, at least this (measured, README)
AUTO_BLOCK_SHARE = 6
MAX_BLOCKS = 1024
MAX_MATCHING = 4096
#: Passes of the refinement's re-cut of straight seams, four more than the shared default of two: the sides of the
#: start's pieces and the correction passes' one-texel slivers leave many straight runs side by side, and each pass
#: finds the runs the previous cuts have shortened or joined (the re-cut stops early once a pass changes nothing).
#: On the bumps (192 x 192, seeds 0-1), where k-coherence missed the straight-seam target, 3, 4, 5 and 6 passes leave
#: straight seams of 1.26, 1.24, 1.21 and 1.14 x the exemplar's neighbour jump, at 5.3, 4.4, 4.1 and 3.5 % of the
#: seam edges (Benchmarks, "Re-cut bands that overlap, taken in turn").
RECUT_PASSES = 6
#: Default refinement rounds at the coarse scale (two at the full resolution): the coarse rounds decide which
#: exemplar areas meet along the start's block edges, so more of them leave fewer straight cuts there (held-out
#: procedural exemplar, seeds 0-7: straight-seam visibility 1.66 -> 1.46, benchmarks).
COARSE_ROUNDS = 4
#: The refinement's contrast weight where the output has more than :data:`.synthesizer.AUTO_AREA` x the exemplar's
#: texels (up to that the shared 16 holds), and its polish rounds.  Without the term there, the rounds that spread the
#: start's blocks over the exemplar favour its flatter windows: SWD over the shuffled blocks reached 1.54 on the fibres
#: at 128 (a miss) and 1.37-1.38 on the fibres and the tablet at 192.  The term alone raised seams on every stationary
#: crop (the held-out procedural exemplar at 128 1.23 -> 1.28); a second polish round takes most of that back.  On 40
#: crops of the synthesis bench (seeds 0-1) both together lower SWD on 38 (the fibres at 128 1.54 -> 1.23, at 192 1.37
#: -> 1.02), raise seams by 0.01-0.03 at the medians (at most 0.09: the fibres at 96, 0.88 -> 0.97), and the targets
#: missed go from 7 to 6.  A weight of 8 missed as often as none (Benchmarks).
LARGE_CONTRAST = 4.0
POLISH_ROUNDS = 2
#: Weight of the seam cost in the refinement's vote, four times the shared default: its cuts run where the two sides
#: continue each other more closely.  On the 21 main crops of the synthesis bench (seeds 0-1) seams fall on all 21 (by
#: 0.01-0.08; the held-out procedural exemplar at 128 1.24 -> 1.17) with SWD lower on 11; at 2 they fall by less
#: (Benchmarks).
SEAM_WEIGHT = 4.0
#: The start's copy budget where the output has more than :data:`.synthesizer.BUDGET_AREA` x the exemplar's texels:
#: none (0), as before the budget; the strata alone spread the pieces where each exemplar texel is copied twice or more.
LARGE_BUDGET = 0.0
KEEP = 0.5                   #: default weight of a pixel's own source's cost in the correction passes
ANALYSES_KEPT = 4            #: exemplar analyses kept in memory (keyed by content and analysis params)


# ============================================================================================ exemplar pyramid


@dataclasses.dataclass(frozen=True)
class ExemplarLevel:
    """One exemplar level prepared for synthesis: textons, padded texton map, coherence sets."""

    height: int
    width: int
    textons: Textons
    tex: np.ndarray        # [H * W] int32
    tex_pad: np.ndarray    # [H + 2 pad, W + 2 pad] int32, edge-extended
    pad: int
    ksets: np.ndarray      # [H * W, k] int32: the texel itself, then its k - 1 most similar (-1: missing)
    kset_cost: np.ndarray  # [H * W, k - 1] float32

    @property
    def table(self) -> np.ndarray:
        return self.textons.table


_analyses = ContentCache(ANALYSES_KEPT)


def analyse_exemplar(features: np.ndarray, *, k: int, neighborhood: int, levels: int,
                     textons: int = DEFAULT_TEXTONS, search: str = "fast",
                     engine: str = "opencl") -> list[ExemplarLevel]:
    """The exemplar pyramid (finest first) with textons and k-coherence sets per level (analysed independently).

    Kept in memory per exemplar content and params (the last :data:`ANALYSES_KEPT`), so synthesizing again with
    another seed or size skips it.
    """
    key = content_key(features, extra=("kcoherence", k, neighborhood, levels, textons, search, engine))
    return _analyses.get_or_make(key, lambda: _analyse(features, k, neighborhood, levels, textons, search, engine))


def _analyse(features, k, neighborhood, levels, textons, search, engine) -> list[ExemplarLevel]:
    from concurrent.futures import ThreadPoolExecutor
    pad = neighborhood // 2
    pyramid = [normalise_features(features)]
    while len(pyramid) < levels:
        pyramid.append(downsample(pyramid[-1]))
    # the textons (k-means, much of it single-threaded NumPy) run beside the coherence sets (kd-tree and
    # OpenCL steps): each is deterministic, so the overlap changes nothing but the time
    with ThreadPoolExecutor(1) as pool:
        clustered = [pool.submit(texton_analysis, f, min(textons, f.shape[0] * f.shape[1]), engine=engine)
                     for f in pyramid]
        sets = [_coherence_sets(f, k, neighborhood, search, engine) for f in pyramid]
        clustered = [c.result() for c in clustered]
    return [ExemplarLevel(f.shape[0], f.shape[1], tx, tx.labels.ravel().astype(np.int32), pad_textons(tx.labels, pad),
                          pad, ksets, cost) for f, tx, (ksets, cost) in zip(pyramid, clustered, sets)]


def _coherence_sets(features, k, neighborhood, search, engine) -> tuple[np.ndarray, np.ndarray]:
    """Every texel itself, then its k - 1 most similar texels ``[H * W, k]``, and their costs ``[H * W, k - 1]``."""
    h, w, _ = features.shape
    ksets = np.empty((h * w, k), np.int32)
    ksets[:, 0] = np.arange(h * w)
    cost = np.zeros((h * w, k - 1), np.float32)
    if k > 1:
        ksets[:, 1:], cost = similar_texels(features, neighborhood, k - 1, exclude=KSET_EXCLUDE, search=search,
                                            device=engine)
    return ksets, cost


# ============================================================================================ synthesis passes


def synthesis_offsets(radius: int) -> np.ndarray:
    """The window without its centre ``[(2r+1)^2 - 1, 2]`` (dy, dx), nearest first: neighbour and cost order.

    Candidates of equal cost are resolved in favour of the nearest neighbours' coherent sources.
    """
    return search_offsets(radius)[1:]



def _neighbours(ys, xs, offs, ho, wo, wrap):
    return output_neighbours(ys[:, None] + offs[None, :, 0], xs[:, None] + offs[None, :, 1], ho, wo, wrap)


def best_candidates_numpy(level: ExemplarLevel, nsrc: np.ndarray, used: np.ndarray, offs: np.ndarray,
                          k: int, coverage: tuple | None = None, own: np.ndarray | None = None,
                          own_scale: float = 1.0) -> np.ndarray:
    """Twin of ``kc_best`` for ``P`` pixels at once: ``nsrc``/``used`` ``[P, O]`` -> best source ``[P]`` or -1.

    ``coverage`` ``(excess, cell, tolerance)``: then the twin of ``kc_fairest`` re-picks among near ties.
    ``own`` ``[P]``: each pixel's current source, tried before every other candidate (kept on ties).
    """
    he, we, pad = level.height, level.width, level.pad
    n_pix, n_off = nsrc.shape
    if n_pix == 0:
        return np.zeros(0, np.int32)
    sy = np.clip(nsrc // we - offs[None, :, 0], 0, he - 1)
    sx = np.clip(nsrc % we - offs[None, :, 1], 0, we - 1)
    cand = level.ksets[sy * we + sx, :k].reshape(n_pix, n_off * k)
    valid = np.repeat(used, k, axis=1) & (cand >= 0)
    if own is not None:
        cand = np.concatenate([own.astype(cand.dtype)[:, None], cand], axis=1)
        valid = np.concatenate([((own >= 0) & used.any(axis=1))[:, None], valid], axis=1)
    safe = np.where(cand >= 0, cand, 0)
    cy, cx = safe // we + pad, safe % we + pad
    ntex = level.tex[nsrc]
    table = level.table
    acc = np.zeros(cand.shape, np.float32)
    zero = np.float32(0)
    with np.errstate(over="ignore", invalid="ignore"):
        for l in range(n_off):
            term = table[level.tex_pad[cy + offs[l, 0], cx + offs[l, 1]], ntex[:, l:l + 1]]
            acc += np.where(used[:, l:l + 1], term, zero)
    if own is not None:
        acc[:, 0] *= np.float32(own_scale)
    key = np.where(valid, acc, np.float32(np.inf))
    rows = np.arange(n_pix)
    pick = np.argmin(key, axis=1)
    no_finite = ~np.isfinite(key[rows, pick])
    pick = np.where(no_finite, np.argmax(valid, axis=1), pick)  # the kernel keeps its first valid candidate
    if coverage is not None:
        pick = _fairest_numpy(level, cand, valid, key, pick, *coverage)
    best = cand[rows, pick].astype(np.int32)
    best[~valid.any(axis=1)] = -1
    return best


def _fairest_numpy(level, cand, valid, key, pick, excess, cell, tol):
    """Twin of ``kc_fairest``: among candidates costing at most best * (1 + tol), the least over-used cell."""
    rows = np.arange(len(pick))
    best_cost = key[rows, pick]
    if not tol > 0:
        return pick
    limit = best_cost * (np.float32(1) + np.float32(tol))
    safe = np.where(cand >= 0, cand, 0)
    cw = -(-level.width // cell)
    used = excess[(safe // level.width) // cell * cw + (safe % level.width) // cell]
    within = valid & (key <= limit[:, None]) & np.isfinite(best_cost)[:, None]
    least = np.where(within, used, np.inf).min(axis=1)
    fair_key = np.where(within & (used == least[:, None]), key, np.inf)
    fair = np.argmin(fair_key, axis=1)
    return np.where(within.any(axis=1), fair, pick)


def cell_excess(sources: np.ndarray, level: ExemplarLevel, cell: int) -> np.ndarray:
    """Use of each ``cell x cell`` exemplar cell by ``sources`` beyond its fair share, over that share: float32.

    The fair share of a cell is the output's texel count times the cell's share of the exemplar's texels.
    """
    he, we = level.height, level.width
    ch, cw = -(-he // cell), -(-we // cell)
    cells = (sources // we) // cell * cw + (sources % we) // cell
    count = np.bincount(cells, minlength=ch * cw).astype(np.float64)
    rows = np.minimum(cell, he - np.arange(ch) * cell)
    cols = np.minimum(cell, we - np.arange(cw) * cell)
    fair = np.outer(rows, cols).ravel() * (len(sources) / (he * we))
    return (np.maximum(count - fair, 0.0) / fair).astype(np.float32)


def block_side(exemplar_size: tuple[int, int], blocks: int) -> int:
    """The block side ``blocks`` asks for: itself, or for -1 a sixth of the exemplar's shorter side (at least
    :data:`MIN_AUTO_BLOCK`), never more than the exemplar."""
    if blocks < 0:
        blocks = max(MIN_AUTO_BLOCK, min(exemplar_size) // AUTO_BLOCK_SHARE)
    return min(blocks, *exemplar_size)


def causal_pass_numpy(level, cur, fixed, ho, wo, wrap, offs, k, use_prev=False):
    """Twin of the wavefront-ordered causal pass (``kc_causal``); updates ``cur`` (flat) in place."""
    step = int(np.abs(offs).max()) + 1
    prev = cur.copy()
    for t, y0, ny in wavefronts(step, ho, wo):
        ys = np.arange(y0, y0 + ny)
        xs = t - step * ys
        keep = ~fixed[ys * wo + xs]
        ys, xs = ys[keep], xs[keep]
        if not len(ys):
            continue
        qy, qx, inside = _neighbours(ys, xs, offs, ho, wo, wrap)
        q = qy * wo + qx
        p = ys * wo + xs
        done = fixed[q] | (qx + step * qy < t)
        used = inside & (done | (use_prev & (q != p[:, None])))
        best = best_candidates_numpy(level, np.where(done, cur[q], prev[q]), used, offs, k)
        cur[p] = np.where(best >= 0, best, cur[p])


def _groups(n: int, step: int, wrap: bool) -> list[tuple[int, int]]:
    """Interleaved groups ``(start, end)`` of one axis for the correction sub-passes (members ``step`` apart).

    With ``wrap`` and ``n`` not a multiple of ``step``, the classes ``i % step`` would put neighbours across the
    seam into one group, so the last ``n % step`` lines form groups of their own.
    """
    main = n - n % step if wrap else n
    groups = [(start, main) for start in range(min(step, main))]
    return groups + [(line, line + 1) for line in range(main, n)]


def correction_pass_numpy(level, cur, ho, wo, wrap, offs, k, coverage=0.0, keep=1.0):
    """Twin of the correction pass (``kc_correct`` over interleaved sub-passes); updates ``cur`` in place."""
    step = int(np.abs(offs).max()) + 1
    for cy, y_end in _groups(ho, step, wrap):
        for cx, x_end in _groups(wo, step, wrap):
            ys, xs = np.meshgrid(np.arange(cy, y_end, step), np.arange(cx, x_end, step), indexing="ij")
            ys, xs = ys.ravel(), xs.ravel()
            if not len(ys):
                continue
            prev = cur.copy()
            qy, qx, inside = _neighbours(ys, xs, offs, ho, wo, wrap)
            q = qy * wo + qx
            p = ys * wo + xs
            used = inside & (q != p[:, None])
            fair = (cell_excess(prev, level, COVERAGE_CELL), COVERAGE_CELL, coverage) if coverage > 0 else None
            best = best_candidates_numpy(level, prev[q], used, offs, k, coverage=fair,
                                         own=prev[p], own_scale=keep)
            cur[p] = np.where(best >= 0, best, prev[p])


class _DeviceLevel:
    """An exemplar level's arrays on the device, and the kernels that synthesize from it."""

    def __init__(self, level: ExemplarLevel, offs: np.ndarray, k: int):
        self.backend = backend = get_backend()
        options = (f"-DNOFF={len(offs)}",)
        self.causal = backend.kernel(KERNELS, "kc_causal", options)
        self.causal_all = backend.kernel(KERNELS, "kc_causal_all", options)
        self.correct = backend.kernel(KERNELS, "kc_correct", options)
        self.level = level
        self.k = k
        self.noff = len(offs)
        self.offs = offs
        # kept on the object: the device buffers must outlive every launch that uses them
        self.args = (backend.to_device(np.ascontiguousarray(offs[:, 0])),
                     backend.to_device(np.ascontiguousarray(offs[:, 1])), np.int32(len(offs)),
                     backend.to_device(level.tex), backend.to_device(level.tex_pad),
                     np.int32(level.height), np.int32(level.width), np.int32(level.tex_pad.shape[1]),
                     np.int32(level.pad), backend.to_device(level.table), np.int32(level.table.shape[0]),
                     backend.to_device(np.ascontiguousarray(level.ksets)), np.int32(level.ksets.shape[1]), np.int32(k))

    def rw_buffer(self, array: np.ndarray):
        cl = self.backend.cl
        return cl.Buffer(self.backend.context, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR,
                         hostbuf=np.ascontiguousarray(array, np.int32))

    def causal_pass(self, cur_dev, fixed: np.ndarray, ho: int, wo: int, wrap: bool, use_prev: bool = False) -> None:
        backend = self.backend
        step = int(np.abs(self.offs).max()) + 1
        fixed_dev = backend.to_device(fixed.astype(np.uint8))
        prev_dev = backend.empty(4 * ho * wo)
        if use_prev:
            backend.cl.enqueue_copy(backend.queue, prev_dev, cur_dev)
        args = (cur_dev, prev_dev, np.int32(use_prev), fixed_dev, np.int32(ho), np.int32(wo), np.int32(wrap),
                np.int32(step), *self.args)
        if CAUSAL_ORDER == "single":
            self.causal_all.set_args(*args)
            backend.cl.enqueue_nd_range_kernel(backend.queue, self.causal_all, (CAUSAL_GROUP,), (CAUSAL_GROUP,))
            backend.queue.finish()
            return
        kernel = self.causal
        kernel.set_args(np.int32(0), np.int32(0), np.int32(0), *args)
        for t, y0, ny in wavefronts(step, ho, wo):
            kernel.set_arg(0, np.int32(t))
            kernel.set_arg(1, np.int32(y0))
            kernel.set_arg(2, np.int32(ny))
            backend.cl.enqueue_nd_range_kernel(backend.queue, kernel, (round_up(ny),), (LOCAL,))
        backend.queue.finish()

    def correction_pass(self, cur_dev, ho: int, wo: int, wrap: bool, coverage: float = 0.0,
                        keep: float = 1.0) -> None:
        backend = self.backend
        step = int(np.abs(self.offs).max()) + 1
        prev_dev = backend.empty(4 * ho * wo)
        cw = -(-self.level.width // COVERAGE_CELL)
        sources = np.empty(ho * wo, np.int32)
        excess_dev = backend.to_device(np.zeros(1, np.float32))  # unread without coverage (kc_fairest is off)
        for cy, y_end in _groups(ho, step, wrap):
            for cx, x_end in _groups(wo, step, wrap):
                ny, nx = len(range(cy, y_end, step)), len(range(cx, x_end, step))
                if not ny or not nx:
                    continue
                backend.cl.enqueue_copy(backend.queue, prev_dev, cur_dev)
                if coverage > 0:  # counting on the host costs ~1 ms a sub-pass; on the device it saved nothing
                    backend.cl.enqueue_copy(backend.queue, sources, cur_dev)
                    excess_dev = backend.to_device(cell_excess(sources, self.level, COVERAGE_CELL))
                launch(backend, self.correct, (ny, nx), prev_dev, cur_dev, np.int32(ho), np.int32(wo),
                        np.int32(wrap), np.int32(cy), np.int32(cx), np.int32(step), np.int32(y_end),
                        np.int32(x_end), *self.args, excess_dev, np.int32(COVERAGE_CELL), np.int32(cw),
                        np.float32(coverage), np.float32(keep))


@dataclasses.dataclass
class SynthesisResult:
    coords: np.ndarray             # [H, W, 2] int32 into the finest exemplar level
    levels: list[ExemplarLevel]
    seconds_analysis: float
    seconds_synthesis: float


def synthesize(features: np.ndarray, size: tuple[int, int], *, k: int = 6, neighborhood: int = 5, levels: int = 3,
               wrap: bool = False, seed: int = 0, textons: int = DEFAULT_TEXTONS, search: str = "fast",
               corrections: int = CORRECTIONS, coverage: float = COVERAGE, blocks: int = BLOCKS, keep: float = KEEP,
               matching: int = CANDIDATES, budget: float = 0.0, engine: str = "opencl",
               analysis: list[ExemplarLevel] | None = None) -> SynthesisResult:
    """Hierarchical k-coherence synthesis on ``[H, W, D]`` features; see :func:`kcoherence` for the method."""
    if engine not in ENGINES:
        raise BtforgeInputError("kcoherence 'engine'", f"expected one of {ENGINES}, found {engine!r}",
                                "use 'opencl', or 'numpy' for the reference twins")
    # The stage checked its params before any work; direct callers reach the bounds its Params enforce only here.
    check_params("synth.kcoherence", features.shape[:2], size=size, neighborhood=neighborhood, k=k, levels=levels)
    if not 0 <= corrections <= MAX_CORRECTIONS:
        raise BtforgeInputError("kcoherence param 'corrections'",
                                f"expected an int in [0, {MAX_CORRECTIONS}], found {corrections}",
                                f"use e.g. {CORRECTIONS} correction pass per level")
    if not -1 <= blocks <= MAX_BLOCKS:
        raise BtforgeInputError("kcoherence param 'blocks'", f"expected an int in [-1, {MAX_BLOCKS}], found {blocks}",
                                "use -1 (a sixth of the exemplar), e.g. 16, or 0 for the hierarchical synthesis "
                                "from a random border")
    blocks = block_side(features.shape[:2], blocks)
    if not 0.0 <= keep <= 1.0:
        raise BtforgeInputError("kcoherence param 'keep'", f"expected a value in [0, 1], found {keep}",
                                f"use e.g. {KEEP}; 1 keeps a pixel's source only where nothing is cheaper")
    start = time.perf_counter()
    # with blocks only the finest level is synthesized, so only it is analysed
    pyramid = analysis if analysis is not None else analyse_exemplar(
        features, k=k, neighborhood=neighborhood, levels=1 if blocks else levels, textons=textons, search=search,
        engine=engine)
    analysed = time.perf_counter()
    offs = synthesis_offsets(neighborhood // 2)
    synthesized = 1 if blocks else levels
    out_sizes = level_sizes(int(size[0]), int(size[1]), synthesized)
    rng = np.random.default_rng(seed)
    cur = None
    for l in reversed(range(synthesized)):
        level = pyramid[l]
        ho, wo = out_sizes[l]
        if cur is None and blocks:
            # matched exemplar pieces: the correction passes repair their seams
            cur, passes_causal = matched_blocks(rng, features, out_sizes[l], blocks, matching, wrap, budget), []
        else:
            cur, passes_causal = _level_start(cur, pyramid, l, out_sizes, rng, wrap, neighborhood // 2)
        passes = corrections + 1 if l == synthesized - 1 else corrections
        if engine == "numpy":
            for fixed, use_prev in passes_causal:
                causal_pass_numpy(level, cur, fixed, ho, wo, wrap, offs, k, use_prev=use_prev)
            for _ in range(passes):
                correction_pass_numpy(level, cur, ho, wo, wrap, offs, k, coverage, keep)
        else:
            dev = _DeviceLevel(level, offs, k)
            cur_dev = dev.rw_buffer(cur)
            for fixed, use_prev in passes_causal:
                dev.causal_pass(cur_dev, fixed, ho, wo, wrap, use_prev=use_prev)
            for _ in range(passes):
                dev.correction_pass(cur_dev, ho, wo, wrap, coverage, keep)
            dev.backend.cl.enqueue_copy(dev.backend.queue, cur, cur_dev)
            dev.backend.queue.finish()
    finest = pyramid[0]
    coords = np.stack(np.divmod(cur.reshape(out_sizes[0]), finest.width), axis=-1).astype(np.int32)
    return SynthesisResult(coords, pyramid, analysed - start, time.perf_counter() - analysed)


def _level_start(cur, pyramid, l, out_sizes, rng, wrap, radius):
    """A level's starting sources (flat int32) and its causal passes as (fixed mask, read later neighbours from
    the previous state), in the hierarchical synthesis."""
    level = pyramid[l]
    ho, wo = out_sizes[l]
    ys, xs = np.divmod(np.arange(ho * wo), wo)
    if cur is None:
        # coarsest level: the border (first `radius` rows and columns) seeded with random exemplar texels
        cur = rng.integers(0, level.height * level.width, ho * wo).astype(np.int32)
        passes = [((ys < radius) | (xs < radius), False)]
        if wrap:
            # periodic output: a second, toroidal pass re-synthesizes everything, the border included, with
            # the neighbours not yet redone (across the seams) read from the first pass's result
            passes.append((np.zeros(ho * wo, bool), True))
        return cur, passes
    # finer level: coarse coordinates x 2 plus the pixel's offset in its 2 x 2 block; even pixels fixed
    coarse_level, wc = pyramid[l + 1], out_sizes[l + 1][1]
    parent = cur[(ys // 2) * wc + xs // 2]
    sy = np.minimum(2 * (parent // coarse_level.width) + ys % 2, level.height - 1)
    sx = np.minimum(2 * (parent % coarse_level.width) + xs % 2, level.width - 1)
    return (sy * level.width + sx).astype(np.int32), [((ys % 2 == 0) & (xs % 2 == 0), False)]


# ============================================================================================ the stage


@declare_synthesizer(
    "synth.kcoherence", deprecated_names=("kcoherence",),
    version="28",  # 28: the refinement's balance term on by default where the output has at most 1.5 x the exemplar's texels (param appearance_balance, -1: automatic, 16 there); 27: straight seams whose re-cut bands overlap are re-cut in separate groups, so a sliver's far piece is offered across it, in six re-cut passes (was 3); 26: seams cross-faded over 3 texels on either side (feather 3, was 1); 25: the start's pieces within a copy budget (param budget, automatic: 0.5 up to twice the exemplar's texels, else none); 24: linear exemplars (stacks, linear fits of light only) compared as a screen shows them, at 25 probe lights sRGB-encoded, 16 principal components; 23: sRGB PTM, SH and HSH exemplars feathered too, their records mixed as display values; 22: linear lrgb exemplars feathered too, through the rgb PTM of the same functions; 21: seams cross-faded over 1 texel on blendable exemplars (param feather); 20: the refinement's vote weighs seams 4 x (param seam_weight: seams lower on every crop measured); 19: the refinement's contrast term at 4 by default where the output has more than 1.5 x the exemplar's texels (contrast -1), and two polish rounds (polish 2); 18: one polish round by default (param polish: seams lower, the procedural exemplar's at 128 pass); 17: the re-cut weighs a straight seam edge that stays 1.5 x its appearance difference (about half the straight seams); 16: the refinement's contrast term on by default where the exemplar is about as large as the output (contrast -1: automatic); 15: four refinement rounds at the coarse scale (coarse_refine 4); 14: bridging pieces over straight seams, three re-cut passes; 13: the start's pieces matched at their edges (matching 64); 12: straight seams re-cut by minimum cuts, the refinement's candidate distances summed in a fixed order (OpenCL kernels); 11: a coarse scale first (scales 1), windows jittered one by one; 10: occurrence weight 1 by default; 9: refinement with an approximate window search; 3: fast self-join by graph nominees + coherence propagation; 4: coverage tie-break in the correction passes (default 0.5); 5: stratified blocks (16) and keep (0.5); 6: the self-join seeded by a kd-tree, steps read window distances from the image; 7: the shared refinement; 8: refinement by a coherent vote
    seed_doc="random seed of the border; the same seed gives the same result",
    params=[
        Param("k", "int", 6, "candidates per neighbour: the coherent source and its k - 1 most similar texels",
              low=1, high=MAX_K),
        Param("neighborhood", "int", 5, "odd window size n of the n x n neighbourhoods compared",
              low=3, high=MAX_NEIGHBORHOOD),
        Param("levels", "int", 3, "pyramid levels (each half the previous resolution) of the hierarchical start "
              "(blocks: 0); with blocks the finest level alone is analysed and synthesized", low=1, high=12),
        Param("textons", "int", DEFAULT_TEXTONS, "texton (k-means cluster) count per level, at most the texels "
              "of the level", low=1, high=2048),
        search_param(),
        Param("corrections", "int", CORRECTIONS, "correction passes per level after its causal pass (the "
              "coarsest level gets one more)", low=0, high=MAX_CORRECTIONS),
        Param("coverage", "float", COVERAGE, "coverage tolerance of the correction passes: among candidates "
              "within this relative cost of the best, the least over-used exemplar cell wins (0: off)",
              low=0.0, high=1.0),
        Param("blocks", "int", BLOCKS, "side in texels of the exemplar pieces the synthesis starts from, laid side "
              "by side with origins spread evenly over the exemplar; only the finest level is then synthesized "
              "(its correction passes repair the seams).  -1: a sixth of the exemplar's shorter side, at least 16; "
              "0: the hierarchical synthesis from a random border over 'levels' levels", low=-1, high=MAX_BLOCKS),
        Param("matching", "int", CANDIDATES, "exemplar origins compared for each piece of the start (drawn from the "
              "strata not yet used): the one whose edges continue the pieces already beside it best is laid, so "
              "colour areas continue across the pieces' edges (1: a random one)", low=1, high=MAX_MATCHING),
        Param("budget", "float", AUTO, "copy budget of the start's pieces: a piece is taken only while its exemplar "
              "area is copied at most budget x its fair share (the texels laid so far spread evenly over the "
              f"exemplar) plus one copy, or where none is.  Negative (the default): {SMALL_OUTPUT_BUDGET:g} where the "
              f"output has at most {BUDGET_AREA:g} x the exemplar's texels (the pieces' seam cost favours an "
              "exemplar's plain parts), else 0: no limit", low=-1.0, high=100.0),
        Param("keep", "float", KEEP, "weight of a pixel's own source's cost in the correction passes: a source "
              "changes only to a candidate cheaper than this times its own cost (1: to any cheaper one)",
              low=0.0, high=1.0),
        *refine_params(scales=1, coarse_refine=COARSE_ROUNDS, polish=POLISH_ROUNDS, large_weight=LARGE_CONTRAST,
                       seam_weight=SEAM_WEIGHT),
    ],
)
def kcoherence(ctx, exemplar, *, size, wrap, seed, k, neighborhood, levels, textons, search, corrections,
               coverage, blocks, matching, budget, keep, refine, occurrence, contrast, appearance_balance, scales,
               coarse_refine, polish, seam_weight, feather):
    """Synthesize a larger texture by hierarchical k-coherence search; outputs a coordinate map.

    Method (Tong et al. 2002 as used for BTFs by Bosserhoff & Nicoll):

    1. **Analysis**, per pyramid level (the exemplar's appearance vectors, Gaussian-blurred and halved per
       level, analysed independently): k-means textons with a table of texton distances, and for every
       exemplar texel its coherence set - itself and the k - 1 texels with the most similar n x n
       neighbourhoods of the appearance vectors (the shared search, ``search`` fast or exact; texels within one
       texel of it are left out).  The analysis is kept per exemplar: another seed or size skips it.
    2. **Start from matched blocks** (the default, ``blocks`` != 0): the output is tiled, in scanline order,
       with ``blocks x blocks`` pieces of the exemplar (-1: a sixth of its shorter side, at least 16 texels)
       whose origins are spread evenly: the exemplar's origins are cut into strata about a block apart, and
       every stratum gives one piece before any gives a second.  Among ``matching`` origins drawn from the
       strata still open, the piece whose edges continue the pieces already laid beside it best (least seam
       cost, as Graphcut Textures places a patch) is laid (:mod:`.block_start`); random pieces meet as
       unrelated colour areas along straight edges.  Only the finest level is synthesized: its correction
       passes (4. below, ``corrections`` + 1 of them) repair the seams between the pieces.  The output thus
       copies large coherent pieces and uses the whole exemplar about evenly, which the hierarchical start
       below does not (its passes drift to a few easily continued regions; README, Benchmarks).
       **Copy budget** (``budget``): the strata even out the pieces' origins, but within a stratum the seam cost
       picks the smoothest piece, so an exemplar's plain parts are over-used (RealRTI item4 at 192 x 192: the
       face, little of its ornate border; SWD over the shuffled blocks 2.08).  Where the output has at most twice
       the exemplar's texels a piece is taken only while its exemplar area is copied at most 0.5 x its fair share
       plus one copy, or where none is (quilting's rule, :func:`.synthesizer.within_copy_budget`): item4 1.40.
    2'. **Hierarchical start** (``blocks: 0``), coarsest level: the first n // 2 rows and columns are seeded
       with random exemplar texels; every other pixel takes, among the coherence sets of the coherent sources
       suggested by its causal (L-shaped) neighbours, the candidate whose neighbourhood differs least (sums of
       texton-table lookups).
    3. **Finer levels** (``blocks: 0``): every pixel starts from its parent's source x 2 plus its offset in
       the 2 x 2 block; the even-even pixels are kept (and used as known neighbours, also below and to the
       right), the others are synthesized as in 2'.
    4. **Correction** (Tong et al. 2002; Lefebvre & Hoppe 2005): after each level's causal pass, ``corrections``
       passes choose every pixel again from its k-coherence candidates with its now complete, non-causal
       neighbourhood (one pass more at the coarsest level, where they also repair the random border or the
       seams).  **Keep**: the pixel's own source is a candidate too, at ``keep`` x its cost, so a source
       changes only for a clearly better match (seams change, the pieces' insides stay).
       **Coverage**: in these passes, among the candidates whose cost is within ``coverage`` (relative) of the
       best, the one whose 4 x 4 exemplar cell is used least beyond its fair share (the output's texels spread
       evenly over the exemplar; counted before each sub-pass) wins, then the cheapest.  Only near ties are
       re-ordered, so a clearly better match always wins (a fixed usage penalty on every candidate collapsed
       outputs).  The defaults (blocks -1, keep 0.5, 1 correction, coverage 0.5) are the best measured
       (README, Benchmarks).

    Order of work: scanline dependencies are resolved by wavefronts ``x + (r + 1) * y = t`` (r = n // 2).  A
    pixel uses a neighbour only once that neighbour is fixed or lies on an earlier wavefront, and pixels of one
    wavefront never see each other, so each wavefront is synthesized in parallel; for an output that does not
    wrap this is exactly the L-shaped causal neighbourhood of scanline order, so the result is the scanline
    result.  On the device a whole pass is one work-group that steps through the wavefronts with barriers.
    The correction visits pixels in (r + 1) x (r + 1) interleaved sub-passes whose pixels do not see each other
    (also across a wrapping seam).

    ``wrap``: neighbourhoods continue across the output's edges (the correction passes repair the wrap-around
    seams of the blocks too); with ``blocks: 0`` the coarsest level gets a second, toroidal causal pass in which
    pixels not yet redone (across the seams) are read from the first pass; the result tiles seamlessly.

    **Refinement** (``refine`` and ``coarse_refine`` rounds, ``occurrence`` weight, ``scales``; :mod:`.refine`):
    the map finally goes through the shared texture optimisation with an occurrence term and corrections, at half
    resolution first (``scales: 1``, ``coarse_refine`` rounds there, ``refine`` at the full resolution), so seams
    follow the content instead of the block grid, and colour areas larger than a block are no longer cut into
    squares; ``polish`` rounds without the occurrence and contrast terms end it (two by default), and the contrast
    term weighs 4 by default where the output has more than 1.5 x the exemplar's texels; up to that the balance term
    (``appearance_balance``) charges windows of appearance classes the output holds beyond their share of the
    exemplar (the tablet at 256: SWD over the shuffled blocks 1.55 -> 1.35).  ``scales: 2`` lowers seams
    further (1.23 instead of 1.32 on the held-out procedural exemplar) but moves the patch statistics of fine
    textures away from the exemplar's (sliced Wasserstein distance 1.60 x the shuffled-block baseline's on
    fibres, against 1.21).

    Outputs
    -------
    coords : CoordMap
        ``[H, W, 2]`` (row, column) into the exemplar; replay it on any per-texel buffer with ``synth.materialize``.

    Notes
    -----
    textons (per level, finest first), texton_error (quantisation error / variance per level), kset_distance
    (median neighbourhood distance of a texel's most similar other texel, finest level),
    candidates_per_pixel_max (before duplicates are skipped), coherent_fraction (adjacent pixel pairs that are
    coherent copies), seconds_analysis, seconds_synthesis.
    """
    size = tuple(int(v) for v in size)
    check_params("synth.kcoherence", (exemplar.height, exemplar.width), size=size, neighborhood=neighborhood, k=k,
                 levels=levels)
    features = texel_features(exemplar)
    result = synthesize(features, size, k=k, neighborhood=neighborhood, levels=levels, wrap=wrap, seed=seed,
                        textons=textons, search=search, corrections=corrections,
                        coverage=coverage, blocks=blocks, keep=keep, matching=matching,
                        budget=auto_budget(budget, size, (exemplar.height, exemplar.width), LARGE_BUDGET))
    ctx.note("textons", [lv.textons.count for lv in result.levels])
    ctx.note("texton_error", [round(lv.textons.error, 4) for lv in result.levels])
    if k > 1:
        finite = result.levels[0].kset_cost[:, 0][np.isfinite(result.levels[0].kset_cost[:, 0])]
        ctx.note("kset_distance", round(float(np.median(finite)), 4) if finite.size else None)
    n_window = neighborhood * neighborhood - 1
    ctx.note("candidates_per_pixel_max", {"causal": (n_window // 2) * k, "correction": n_window * k})
    ctx.note("coherent_fraction", round(coherent_fraction(result.coords, wrap), 4))
    ctx.note("seconds_analysis", round(result.seconds_analysis, 3))
    ctx.note("seconds_synthesis", round(result.seconds_synthesis, 3))
    coords = CoordMap(result.coords, (exemplar.height, exemplar.width), wrap=wrap)
    coords = refined(ctx, features, coords, refine=refine, occurrence=occurrence, scales=scales, seed=seed,
                     recut_passes=RECUT_PASSES, coarse_refine=coarse_refine, contrast=contrast,
                     large_weight=LARGE_CONTRAST, polish=polish, seam_weight=seam_weight,
                     balance=appearance_balance)
    return {"coords": feathered(coords, feather, records_mix(exemplar), features)}


STAGES = [kcoherence]
