"""Hierarchical k-coherence synthesis (Tong et al. 2002, as adapted to BTFs by Bosserhoff & Nicoll).

The building blocks here are shared with the jump-map synthesizer (:mod:`.jumpmap`):

Texton analysis
    The exemplar's per-texel appearance vectors (:func:`~btforge.plugins.synth.features.texel_features`,
    scaled into [-1, 1]) are clustered by k-means (k-means++ seeding on a sample, a fixed iteration cap, a fixed
    seed, assignment on OpenCL).  Each texel keeps the id of its cluster (its *texton*), and a table holds the
    squared distance between every two cluster means, so a texel distance is one table lookup.
Neighbourhood search
    For every exemplar texel, the ``m`` texels with the most similar ``n x n`` neighbourhoods (sum of table
    lookups over the window; the exemplar is edge-extended).  This is an exact all-pairs search on OpenCL,
    O((H W)^2 n^2) lookups with early termination: a fraction of a second for 64 x 64, a few seconds for
    128 x 128.  :func:`neighbourhood_search` is the one implementation both synthesizers use.
Synthesis
    See :func:`kcoherence` (the stage) for the order of work and why it is still causal.

Every OpenCL kernel (``kcoherence.cl``) has a NumPy twin here that performs the same float32 arithmetic in the
same order, so ``engine="numpy"`` gives bit-identical results (tests compare them).
"""
from __future__ import annotations

import dataclasses
import statistics
import time
from pathlib import Path

import numpy as np

from btforge import Param, declare_stage
from btforge.backend import get_backend
from btforge.buffers import CoordMap, PerTexel
from btforge.errors import BtforgeInputError

from .features import downsample, texel_features

KERNELS = Path(__file__).with_name("kcoherence.cl")
CAUSAL_ORDER = "single"      # "single": a causal pass is one work-group looping over wavefronts; "launch": one each
CAUSAL_GROUP = 64
LOCAL = 8  # fixed work-group size: PoCL builds a work-group function per local size, so never let it vary

DEFAULT_TEXTONS = 256        #: cluster count of the texton analysis (capped by the texel count of a level)
KMEANS_ITERATIONS = 6        #: Lloyd iterations at most (stops earlier when no label changes)
KMEANS_SEED_SAMPLE = 4096    #: k-means++ seeding runs on a sample of at most this many texels (>= 2 x textons)
ANALYSIS_SEED = 0            #: the analysis does not depend on the synthesis seed (same exemplar, same textons)
KSET_EXCLUDE = 1             #: coherence-set members are more than this many texels (Chebyshev) from the texel
CORRECTIONS = 1              #: correction passes per level after the first
COARSEST_CORRECTIONS = 2     #: at the coarsest level, where they also repair the random border
MAX_K = 16
MAX_NEIGHBORHOOD = 9
ENGINES = ("opencl", "numpy")


# ============================================================================================ texton analysis


@dataclasses.dataclass(frozen=True)
class Textons:
    """The texton map of one exemplar level.

    ``labels`` ``[H, W]`` int32 texton ids; ``centres`` ``[T, D]`` float32 appearance vectors (cluster means);
    ``table`` ``[T, T]`` float32 squared distances between the centres (>= 0, zero diagonal);
    ``iterations`` the Lloyd iterations run; ``error`` the mean squared quantisation error relative to the
    features' total variance (0 = exact).
    """

    labels: np.ndarray
    centres: np.ndarray
    table: np.ndarray
    iterations: int
    error: float

    @property
    def count(self) -> int:
        return int(self.centres.shape[0])


def normalise_features(features: np.ndarray) -> np.ndarray:
    """Features scaled by their largest magnitude into [-1, 1] (float32): huge values cannot overflow a distance."""
    f = np.asarray(features, dtype=np.float64)
    if f.size and not np.isfinite(f).all():
        raise BtforgeInputError("synthesis 'exemplar'", "expected finite appearance values, found NaN/Inf",
                                "repair the exemplar before synthesis")
    scale = float(np.abs(f).max()) if f.size else 0.0
    if scale > 0:
        f = f / scale
    return np.ascontiguousarray(f, dtype=np.float32)


def kmeans_pp_seeds(x: np.ndarray, n: int, rng: np.random.Generator, sample: int = KMEANS_SEED_SAMPLE) -> np.ndarray:
    """k-means++ seeding on a sample of the rows of ``x``: ``min(sample, 8 n)`` rows, at least ``2 n``.

    Stops early when every sampled point is already a centre (fewer distinct points than ``n``).
    """
    size = min(len(x), max(min(sample, 8 * n), 2 * n))
    pool = x if len(x) <= size else x[np.sort(rng.choice(len(x), size, replace=False))]
    pool = np.ascontiguousarray(pool, dtype=np.float32)
    chosen = [int(rng.integers(len(pool)))]
    d2 = ((pool - pool[chosen[0]]) ** 2).sum(axis=1, dtype=np.float64)
    while len(chosen) < n:
        cumulative = np.cumsum(d2)
        total = cumulative[-1]
        if not total > 0:
            break  # fewer distinct points than centres asked for
        pick = min(int(np.searchsorted(cumulative, rng.random() * total, side="right")), len(pool) - 1)
        if d2[pick] <= 0:  # rounding at the end of the cumulative sum; take the farthest point instead
            pick = int(np.argmax(d2))
        chosen.append(pick)
        np.minimum(d2, ((pool - pool[pick]) ** 2).sum(axis=1, dtype=np.float64), out=d2)
    return pool[chosen]


def _round_up(n: int, to: int = LOCAL) -> int:
    return max(to, -(-int(n) // to) * to)


def _launch(backend, kernel, size: tuple[int, ...], *args) -> None:
    """Enqueue over ``size`` rounded up to whole work-groups of a fixed shape (the kernels check their bounds)."""
    kernel.set_args(*args)
    local = (1,) * (len(size) - 1) + (LOCAL,)
    glob = tuple(max(1, s) for s in size[:-1]) + (_round_up(size[-1]),)
    backend.cl.enqueue_nd_range_kernel(backend.queue, kernel, glob, local)


def assign_numpy(x: np.ndarray, centres: np.ndarray, chunk: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``kmeans_assign``: nearest centre (first on ties) and its squared distance, in float32."""
    n, d = x.shape
    labels = np.empty(n, np.int32)
    dist = np.empty(n, np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        for start in range(0, n, chunk):
            xs = x[start:start + chunk]
            acc = np.zeros((len(xs), len(centres)), np.float32)
            for j in range(d):
                t = xs[:, j, None] - centres[None, :, j]
                acc += t * t
            labels[start:start + chunk] = np.argmin(acc, axis=1)
            dist[start:start + chunk] = acc[np.arange(len(xs)), labels[start:start + chunk]]
    return labels, dist


def assign_opencl(x: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest centre of every row of ``x`` on OpenCL (``kmeans_assign``)."""
    backend = get_backend()
    n, d = x.shape
    kernel = backend.kernel(KERNELS, "kmeans_assign", (f"-DDIM={d}",))
    labels_dev = backend.empty(4 * n)
    dist_dev = backend.empty(4 * n)
    _launch(backend, kernel, (n,), backend.to_device(np.ascontiguousarray(x, np.float32)),
                backend.to_device(np.ascontiguousarray(centres, np.float32)), np.int32(n),
                np.int32(len(centres)), labels_dev, dist_dev)
    return backend.from_device(labels_dev, (n,), np.int32), backend.from_device(dist_dev, (n,), np.float32)


def kmeans(x: np.ndarray, n: int, seed: int = ANALYSIS_SEED, iterations: int = KMEANS_ITERATIONS,
           engine: str = "opencl") -> tuple[np.ndarray, np.ndarray, int]:
    """Lloyd's k-means on the rows of ``x`` ``[N, D]`` float32: ``(labels [N], centres [T, D], iterations)``.

    k-means++ seeding (fewer than ``n`` centres when there are fewer distinct points), at most ``iterations``
    rounds, an emptied cluster keeps its centre.  Deterministic for a given ``seed``.
    """
    assign = assign_opencl if engine == "opencl" else assign_numpy
    rng = np.random.default_rng(seed)
    centres = kmeans_pp_seeds(x, max(1, min(n, len(x))), rng)
    labels, _ = assign(x, centres)
    done = 0
    for done in range(1, iterations + 1):
        counts = np.bincount(labels, minlength=len(centres))
        sums = np.stack([np.bincount(labels, weights=x[:, j].astype(np.float64), minlength=len(centres))
                         for j in range(x.shape[1])], axis=1)
        filled = counts > 0
        centres = centres.copy()
        centres[filled] = (sums[filled] / counts[filled, None]).astype(np.float32)
        new_labels, _ = assign(x, centres)
        changed = bool((new_labels != labels).any())
        labels = new_labels
        if not changed:
            break
    return labels, centres, done


def texton_table(centres: np.ndarray, chunk: int = 64) -> np.ndarray:
    """Squared distances between every two centres ``[T, T]`` float32 (zero diagonal, symmetric, >= 0).

    Summed directly from the differences (no BLAS), so the table does not depend on threading or blocking.
    """
    c = centres.astype(np.float64)
    table = np.empty((len(c), len(c)), np.float32)
    for start in range(0, len(c), chunk):
        table[start:start + chunk] = ((c[start:start + chunk, None, :] - c[None, :, :]) ** 2).sum(axis=2)
    table = np.minimum(table, table.T)  # exactly symmetric
    np.fill_diagonal(table, 0.0)
    return table


def texton_analysis(features: np.ndarray, n_textons: int = DEFAULT_TEXTONS, *, seed: int = ANALYSIS_SEED,
                    engine: str = "opencl") -> Textons:
    """Cluster ``[H, W, D]`` float32 features into at most ``n_textons`` textons (see the module docstring)."""
    h, w, d = features.shape
    x = np.ascontiguousarray(features.reshape(-1, d), dtype=np.float32)
    distinct, inverse = np.unique(x, axis=0, return_inverse=True)
    if len(distinct) <= n_textons:
        # no more distinct vectors than textons (small or flat levels): every vector is its own texton, exactly
        labels, centres, iterations = inverse.reshape(-1).astype(np.int32), np.ascontiguousarray(distinct), 0
    else:
        labels, centres, iterations = kmeans(x, n_textons, seed, engine=engine)
    residual = x.astype(np.float64) - centres[labels].astype(np.float64)
    variance = float(((x - x.mean(axis=0)) ** 2).sum())
    error = float((residual ** 2).sum() / variance) if variance > 0 else 0.0
    return Textons(labels.reshape(h, w).astype(np.int32), centres, texton_table(centres), iterations, error)


# ============================================================================================ neighbourhood search


def search_offsets(radius: int) -> np.ndarray:
    """Window offsets ``[(2r+1)^2, 2]`` (dy, dx), centre first, then by growing distance (early termination)."""
    dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    offs = np.column_stack([dy.ravel(), dx.ravel()])
    order = np.lexsort((offs[:, 1], offs[:, 0], np.abs(offs).max(axis=1), (offs ** 2).sum(axis=1)))
    return offs[order].astype(np.int32)


def pad_textons(labels: np.ndarray, pad: int) -> np.ndarray:
    """The texton map edge-extended by ``pad`` texels on every side (int32, C-contiguous)."""
    return np.ascontiguousarray(np.pad(labels, pad, mode="edge"), dtype=np.int32)


def neighbourhood_search(labels: np.ndarray, table: np.ndarray, neighborhood: int, m: int, *, exclude: int = 0,
                         allowed: np.ndarray | None = None, engine: str = "opencl") -> tuple[np.ndarray, np.ndarray]:
    """The ``m`` most similar neighbourhoods of every texel of a texton map.

    Parameters
    ----------
    labels
        ``[H, W]`` texton ids.
    table
        ``[T, T]`` texton distances, every entry >= 0.
    neighborhood
        Odd window size n; the distance of two texels is the sum of table lookups over their n x n windows
        (the map is edge-extended), added in the order of :func:`search_offsets`.
    m
        List length.
    exclude
        Texels within this Chebyshev distance of a texel are not in its list (0: the texel itself; -1: none).
    allowed
        ``[H, W]`` bool: only these texels may appear in lists (default: all).

    Returns
    -------
    (idx, cost)
        ``[H * W, m]`` int32 row-major texel indices sorted by (distance, index), -1 where fewer than ``m``
        texels qualify; ``[H * W, m]`` float32 distances (inf where missing).
    """
    h, w = labels.shape
    radius = neighborhood // 2
    allowed_u8 = np.ones(h * w, np.uint8) if allowed is None else np.ascontiguousarray(allowed, np.uint8).ravel()
    padded = pad_textons(labels, radius)
    offs = search_offsets(radius)
    if engine == "numpy":
        return _search_numpy(padded, h, w, radius, offs, table, m, exclude, allowed_u8.astype(bool))
    return _search_opencl(padded, h, w, radius, offs, table, m, exclude, allowed_u8)


def _search_numpy(padded, h, w, pad, offs, table, m, exclude, allowed, chunk: int = 256):
    n = h * w
    ys, xs = np.divmod(np.arange(n), w)
    # per offset, the texton of every texel's window entry
    window = np.stack([padded[ys + pad + dy, xs + pad + dx] for dy, dx in offs])          # [O, N]
    idx_out = np.full((n, m), -1, np.int32)
    cost_out = np.full((n, m), np.inf, np.float32)
    q = np.arange(n)
    with np.errstate(over="ignore", invalid="ignore"):
        for start in range(0, n, chunk):
            p = np.arange(start, min(n, start + chunk))
            acc = np.zeros((len(p), n), np.float32)
            for o in range(len(offs)):
                acc += table[window[o, p][:, None], window[o][None, :]]
            masked = ~allowed[None, :] | ((np.abs(ys[p][:, None] - ys[None, :]) <= exclude)
                                         & (np.abs(xs[p][:, None] - xs[None, :]) <= exclude))
            for row in range(len(p)):
                order = np.lexsort((q, acc[row], masked[row]))[:m]
                good = ~masked[row, order]
                idx_out[p[row], :good.sum()] = order[good]
                cost_out[p[row], :good.sum()] = acc[row, order[good]]
    return idx_out, cost_out


def _search_opencl(padded, h, w, pad, offs, table, m, exclude, allowed, chunk: int = 4096):
    backend = get_backend()
    kernel = backend.kernel(KERNELS, "nbhd_search", (f"-DNOFF={len(offs)}", f"-DTOP={m}"))
    wp = w + 2 * pad
    flat_offs = (offs[:, 0] * wp + offs[:, 1]).astype(np.int32)
    n = h * w
    tex_dev = backend.to_device(padded)
    offs_dev = backend.to_device(flat_offs)
    table_dev = backend.to_device(np.ascontiguousarray(table, np.float32))
    allowed_dev = backend.to_device(allowed)
    own = padded[pad:pad + h, pad:pad + w].ravel()
    members = np.argsort(own, kind="stable").astype(np.int32)  # texels grouped by texton, for the first tries
    starts = np.searchsorted(own[members], np.arange(table.shape[0] + 1)).astype(np.int32)
    members_dev, starts_dev = backend.to_device(members), backend.to_device(starts)
    idx = np.empty((n, m), np.int32)
    cost = np.empty((n, m), np.float32)
    for start in range(0, n, chunk):
        count = min(chunk, n - start)
        idx_dev = backend.empty(4 * count * m)
        cost_dev = backend.empty(4 * count * m)
        _launch(backend, kernel, (count,), tex_dev, np.int32(h), np.int32(w), np.int32(wp), np.int32(pad),
                offs_dev, np.int32(len(offs)), table_dev, np.int32(table.shape[0]), members_dev, starts_dev,
                allowed_dev, np.int32(exclude), np.int32(start), np.int32(count), idx_dev, cost_dev)
        idx[start:start + count] = backend.from_device(idx_dev, (count, m), np.int32)
        cost[start:start + count] = backend.from_device(cost_dev, (count, m), np.float32)
    return idx, cost


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


def level_sizes(height: int, width: int, levels: int) -> list[tuple[int, int]]:
    """Sizes of a pyramid, finest first: each level half the previous, rounded up."""
    return [(-(-height // 2 ** l), -(-width // 2 ** l)) for l in range(levels)]


def analyse_exemplar(features: np.ndarray, *, k: int, neighborhood: int, levels: int,
                     textons: int = DEFAULT_TEXTONS, engine: str = "opencl") -> list[ExemplarLevel]:
    """The exemplar pyramid (finest first) with textons and k-coherence sets per level (analysed independently)."""
    pad = neighborhood // 2
    out = []
    level_features = normalise_features(features)
    for l in range(levels):
        if l:
            level_features = downsample(level_features)
        h, w, _ = level_features.shape
        tx = texton_analysis(level_features, min(textons, h * w), engine=engine)
        ksets = np.empty((h * w, k), np.int32)
        ksets[:, 0] = np.arange(h * w)
        cost = np.zeros((h * w, k - 1), np.float32)
        if k > 1:
            ksets[:, 1:], cost = neighbourhood_search(tx.labels, tx.table, neighborhood, k - 1,
                                                      exclude=KSET_EXCLUDE, engine=engine)
        out.append(ExemplarLevel(h, w, tx, tx.labels.ravel().astype(np.int32), pad_textons(tx.labels, pad), pad,
                                 ksets, cost))
    return out


# ============================================================================================ synthesis passes


def synthesis_offsets(radius: int) -> np.ndarray:
    """The window without its centre ``[(2r+1)^2 - 1, 2]`` (dy, dx), nearest first: neighbour and cost order.

    Candidates of equal cost are resolved in favour of the nearest neighbours' coherent sources.
    """
    return search_offsets(radius)[1:]


def wavefront_rows(t: int, step: int, ho: int, wo: int) -> tuple[int, int]:
    """First row and row count of wavefront ``t`` (pixels with ``x + step * y == t``)."""
    y_lo = max(0, -(-(t - (wo - 1)) // step))
    y_hi = min(ho - 1, t // step)
    return y_lo, y_hi - y_lo + 1


def wavefronts(step: int, ho: int, wo: int):
    """``(t, first row, row count)`` of every non-empty wavefront ``x + step * y == t`` of an ``ho x wo`` output,
    in the order they must be synthesized."""
    for t in range((wo - 1) + step * (ho - 1) + 1):
        y0, ny = wavefront_rows(t, step, ho, wo)
        if ny > 0:
            yield t, y0, ny


def output_neighbours(qy: np.ndarray, qx: np.ndarray, ho: int, wo: int, wrap: bool):
    """Output pixels ``(qy, qx)`` moved onto the ``ho x wo`` grid, and whether they exist: wrapped around a tiling
    output, clipped (and marked outside) otherwise.  The twins' one copy of the kernels' neighbour rule."""
    if wrap:
        return qy % ho, qx % wo, np.ones(qy.shape, bool)
    inside = (qy >= 0) & (qy < ho) & (qx >= 0) & (qx < wo)
    return np.clip(qy, 0, ho - 1), np.clip(qx, 0, wo - 1), inside


def _neighbours(ys, xs, offs, ho, wo, wrap):
    return output_neighbours(ys[:, None] + offs[None, :, 0], xs[:, None] + offs[None, :, 1], ho, wo, wrap)


def best_candidates_numpy(level: ExemplarLevel, nsrc: np.ndarray, used: np.ndarray, offs: np.ndarray,
                          k: int) -> np.ndarray:
    """Twin of ``kc_best`` for ``P`` pixels at once: ``nsrc``/``used`` ``[P, O]`` -> best source ``[P]`` or -1."""
    he, we, pad = level.height, level.width, level.pad
    n_pix, n_off = nsrc.shape
    if n_pix == 0:
        return np.zeros(0, np.int32)
    sy = np.clip(nsrc // we - offs[None, :, 0], 0, he - 1)
    sx = np.clip(nsrc % we - offs[None, :, 1], 0, we - 1)
    cand = level.ksets[sy * we + sx, :k].reshape(n_pix, n_off * k)
    valid = np.repeat(used, k, axis=1) & (cand >= 0)
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
    key = np.where(valid, acc, np.float32(np.inf))
    rows = np.arange(n_pix)
    pick = np.argmin(key, axis=1)
    no_finite = ~np.isfinite(key[rows, pick])
    pick = np.where(no_finite, np.argmax(valid, axis=1), pick)  # the kernel keeps its first valid candidate
    best = cand[rows, pick].astype(np.int32)
    best[~valid.any(axis=1)] = -1
    return best


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


def correction_pass_numpy(level, cur, ho, wo, wrap, offs, k):
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
            best = best_candidates_numpy(level, prev[q], used, offs, k)
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
            backend.cl.enqueue_nd_range_kernel(backend.queue, kernel, (_round_up(ny),), (LOCAL,))
        backend.queue.finish()

    def correction_pass(self, cur_dev, ho: int, wo: int, wrap: bool) -> None:
        backend = self.backend
        step = int(np.abs(self.offs).max()) + 1
        prev_dev = backend.empty(4 * ho * wo)
        for cy, y_end in _groups(ho, step, wrap):
            for cx, x_end in _groups(wo, step, wrap):
                ny, nx = len(range(cy, y_end, step)), len(range(cx, x_end, step))
                if not ny or not nx:
                    continue
                backend.cl.enqueue_copy(backend.queue, prev_dev, cur_dev)
                _launch(backend, self.correct, (ny, nx), prev_dev, cur_dev, np.int32(ho), np.int32(wo),
                        np.int32(wrap), np.int32(cy), np.int32(cx), np.int32(step), np.int32(y_end),
                        np.int32(x_end), *self.args)


@dataclasses.dataclass
class SynthesisResult:
    coords: np.ndarray             # [H, W, 2] int32 into the finest exemplar level
    levels: list[ExemplarLevel]
    seconds_analysis: float
    seconds_synthesis: float


def synthesize(features: np.ndarray, size: tuple[int, int], *, k: int = 6, neighborhood: int = 5, levels: int = 3,
               wrap: bool = False, seed: int = 0, textons: int = DEFAULT_TEXTONS, engine: str = "opencl",
               analysis: list[ExemplarLevel] | None = None) -> SynthesisResult:
    """Hierarchical k-coherence synthesis on ``[H, W, D]`` features; see :func:`kcoherence` for the method."""
    if engine not in ENGINES:
        raise BtforgeInputError("kcoherence 'engine'", f"expected one of {ENGINES}, found {engine!r}",
                                "use 'opencl', or 'numpy' for the reference twins")
    # The stage checked its params before any work; direct callers reach the bounds its Params enforce only here.
    check_params("kcoherence", features.shape[:2], size=size, neighborhood=neighborhood, k=k, levels=levels)
    start = time.perf_counter()
    pyramid = analysis if analysis is not None else analyse_exemplar(
        features, k=k, neighborhood=neighborhood, levels=levels, textons=textons, engine=engine)
    analysed = time.perf_counter()
    radius = neighborhood // 2
    offs = synthesis_offsets(radius)
    out_sizes = level_sizes(int(size[0]), int(size[1]), levels)
    rng = np.random.default_rng(seed)
    cur = None
    for l in reversed(range(levels)):
        level = pyramid[l]
        ho, wo = out_sizes[l]
        ys, xs = np.divmod(np.arange(ho * wo), wo)
        # causal passes as (fixed mask, read later neighbours from the previous state)
        if cur is None:
            # coarsest level: the border (first `radius` rows and columns) seeded with random exemplar texels
            cur = rng.integers(0, level.height * level.width, ho * wo).astype(np.int32)
            passes_causal = [((ys < radius) | (xs < radius), False)]
            if wrap:
                # periodic output: a second, toroidal pass re-synthesizes everything, the border included, with
                # the neighbours not yet redone (across the seams) read from the first pass's result
                passes_causal.append((np.zeros(ho * wo, bool), True))
        else:
            # finer level: coarse coordinates x 2 plus the pixel's offset in its 2 x 2 block; even pixels fixed
            coarse_level, wc = pyramid[l + 1], out_sizes[l + 1][1]
            parent = cur[(ys // 2) * wc + xs // 2]
            sy = np.minimum(2 * (parent // coarse_level.width) + ys % 2, level.height - 1)
            sx = np.minimum(2 * (parent % coarse_level.width) + xs % 2, level.width - 1)
            cur = (sy * level.width + sx).astype(np.int32)
            passes_causal = [((ys % 2 == 0) & (xs % 2 == 0), False)]
        passes = COARSEST_CORRECTIONS if l == levels - 1 else CORRECTIONS
        if engine == "numpy":
            for fixed, use_prev in passes_causal:
                causal_pass_numpy(level, cur, fixed, ho, wo, wrap, offs, k, use_prev=use_prev)
            for _ in range(passes):
                correction_pass_numpy(level, cur, ho, wo, wrap, offs, k)
        else:
            dev = _DeviceLevel(level, offs, k)
            cur_dev = dev.rw_buffer(cur)
            for fixed, use_prev in passes_causal:
                dev.causal_pass(cur_dev, fixed, ho, wo, wrap, use_prev=use_prev)
            for _ in range(passes):
                dev.correction_pass(cur_dev, ho, wo, wrap)
            dev.backend.cl.enqueue_copy(dev.backend.queue, cur, cur_dev)
            dev.backend.queue.finish()
    finest = pyramid[0]
    coords = np.stack(np.divmod(cur.reshape(out_sizes[0]), finest.width), axis=-1).astype(np.int32)
    return SynthesisResult(coords, pyramid, analysed - start, time.perf_counter() - analysed)


def coherent_fraction(coords: np.ndarray, wrap: bool = False) -> float:
    """Fraction of horizontally and vertically adjacent pixel pairs that are coherent copies.

    A pair is coherent when the right (lower) pixel's source is the left (upper) pixel's source plus one column
    (row).  With ``wrap`` the pairs across the periodic seams count too.
    """
    c = coords.astype(np.int64)
    if wrap:
        right, down = np.roll(c, -1, axis=1), np.roll(c, -1, axis=0)
        h_ok = (right[..., 0] == c[..., 0]) & (right[..., 1] == c[..., 1] + 1)
        v_ok = (down[..., 0] == c[..., 0] + 1) & (down[..., 1] == c[..., 1])
    else:
        h_ok = (c[:, 1:, 0] == c[:, :-1, 0]) & (c[:, 1:, 1] == c[:, :-1, 1] + 1)
        v_ok = (c[1:, :, 0] == c[:-1, :, 0] + 1) & (c[1:, :, 1] == c[:-1, :, 1])
    total = h_ok.size + v_ok.size
    return float((h_ok.sum() + v_ok.sum()) / total) if total else 1.0


# ============================================================================================ the stage


def check_params(stage: str, exemplar_size: tuple[int, int], *, size, neighborhood: int, k: int | None = None,
                 levels: int | None = None) -> None:
    """Raise :class:`BtforgeInputError` naming the parameter when a synthesis parameter cannot be used."""
    if neighborhood < 3 or neighborhood % 2 == 0 or neighborhood > MAX_NEIGHBORHOOD:
        raise BtforgeInputError(f"{stage} param 'neighborhood'",
                                f"expected an odd window size in [3, {MAX_NEIGHBORHOOD}], found {neighborhood}",
                                "use 3, 5, 7 or 9")
    if k is not None and not 1 <= k <= MAX_K:
        raise BtforgeInputError(f"{stage} param 'k'", f"expected an int in [1, {MAX_K}], found {k}",
                                "use e.g. 6: the coherent source and 5 similar texels")
    if len(size) != 2 or min(size) < 1:
        raise BtforgeInputError(f"{stage} param 'size'", f"expected [H, W] with both at least 1, found {list(size)}",
                                "give the output size as two positive ints, e.g. [256, 256]")
    if levels is None:
        return
    if levels < 1:
        raise BtforgeInputError(f"{stage} param 'levels'", f"expected at least 1, found {levels}",
                                "use 1 for a single-resolution synthesis, 3 for the usual pyramid")
    coarsest = level_sizes(*exemplar_size, levels)[-1]
    if min(coarsest) < neighborhood:
        raise BtforgeInputError(
            f"{stage} param 'levels'",
            f"{levels} levels shrink the {exemplar_size[0]} x {exemplar_size[1]} exemplar to "
            f"{coarsest[0]} x {coarsest[1]}, smaller than the {neighborhood} x {neighborhood} neighbourhood",
            "use fewer levels, a smaller neighbourhood or a larger exemplar")


@declare_stage(
    "kcoherence",
    inputs={"exemplar": "PerTexel"},
    outputs={"coords": "CoordMap"},
    params=[
        Param("size", "ints", (256, 256), "output size [H, W] in texels", low=1, length=2),
        Param("k", "int", 6, "candidates per neighbour: the coherent source and its k - 1 most similar texels",
              low=1, high=MAX_K),
        Param("neighborhood", "int", 5, "odd window size n of the n x n neighbourhoods compared",
              low=3, high=MAX_NEIGHBORHOOD),
        Param("levels", "int", 3, "pyramid levels (each half the previous resolution)", low=1, high=12),
        Param("wrap", "bool", False, "make the result tile seamlessly (periodic output boundary)"),
        Param("seed", "int", 0, "random seed of the border; the same seed gives the same result"),
        Param("textons", "int", DEFAULT_TEXTONS, "texton (k-means cluster) count per level, at most the texels "
              "of the level", low=1, high=2048),
    ],
)
def kcoherence(ctx, exemplar, *, size, k, neighborhood, levels, wrap, seed, textons):
    """Synthesize a larger texture by hierarchical k-coherence search; outputs a coordinate map.

    Method (Tong et al. 2002 as used for BTFs by Bosserhoff & Nicoll):

    1. **Analysis**, per pyramid level (the exemplar's appearance vectors, Gaussian-blurred and halved per
       level, analysed independently): k-means textons with a table of texton distances, and for every
       exemplar texel its coherence set - itself and the k - 1 texels with the most similar n x n
       neighbourhoods (exact all-pairs search on OpenCL; texels within one texel of it are left out).
    2. **Coarsest level**: the first n // 2 rows and columns are seeded with random exemplar texels; every other
       pixel takes, among the coherence sets of the coherent sources suggested by its causal (L-shaped)
       neighbours, the candidate whose neighbourhood differs least (sums of texton-table lookups).
    3. **Finer levels**: every pixel starts from its parent's source x 2 plus its offset in the 2 x 2 block; the
       even-even pixels are kept (and used as known neighbours, also below and to the right), the others are
       synthesized as in 2.
    4. **Correction**: after each level every pixel is chosen again with its full, non-causal neighbourhood
       (twice at the coarsest level, where it also repairs the random border).

    Order of work: scanline dependencies are resolved by wavefronts ``x + (r + 1) * y = t`` (r = n // 2).  A
    pixel uses a neighbour only once that neighbour is fixed or lies on an earlier wavefront, and pixels of one
    wavefront never see each other, so each wavefront is synthesized in parallel; for an output that does not
    wrap this is exactly the L-shaped causal neighbourhood of scanline order, so the result is the scanline
    result.  On the device a whole pass is one work-group that steps through the wavefronts with barriers.
    The correction visits pixels in (r + 1) x (r + 1) interleaved sub-passes whose pixels do not see each other
    (also across a wrapping seam).

    ``wrap``: neighbourhoods continue across the output's edges, and the coarsest level gets a second, toroidal
    causal pass in which pixels not yet redone (across the seams) are read from the first pass; the result
    tiles seamlessly.

    Outputs
    -------
    coords : CoordMap
        ``[H, W, 2]`` (row, column) into the exemplar; replay it on any per-texel buffer with ``materialize``.

    Notes
    -----
    textons (per level, finest first), texton_error (quantisation error / variance per level), kset_distance
    (median neighbourhood distance of a texel's most similar other texel, finest level),
    candidates_per_pixel_max (before duplicates are skipped), coherent_fraction (adjacent pixel pairs that are
    coherent copies), seconds_analysis, seconds_synthesis.
    """
    size = tuple(int(v) for v in size)
    check_params("kcoherence", (exemplar.height, exemplar.width), size=size, neighborhood=neighborhood, k=k,
                 levels=levels)
    features = texel_features(exemplar)
    result = synthesize(features, size, k=k, neighborhood=neighborhood, levels=levels, wrap=wrap, seed=seed,
                        textons=textons)
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
    return {"coords": CoordMap(result.coords, (exemplar.height, exemplar.width), wrap=wrap)}


STAGES = [kcoherence]


# ============================================================================================ benchmark


def benchmark_exemplar(size: int = 64, lights: int = 16, seed: int = 1) -> PerTexel:
    """A ``size x size`` single-view stack of the procedural demo material under ``lights`` lights."""
    from btforge.buffers import SampleStack
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights

    material = make_material(size, size, bumps=max(8, size * size // 200), seed=seed)
    dirs = hemisphere_lights(lights, min_elevation_deg=20.0)
    images = render_lights(material, dirs)                      # [L, H, W, 3]
    return SampleStack(np.ascontiguousarray(images[None], np.float32), dirs, [[0.0, 0.0, 1.0]])


def benchmark_kcoherence(exemplar_size: int = 64, size: int = 256, *, k: int = 6, neighborhood: int = 5,
                         levels: int = 3, wrap: bool = False, repeat: int = 3, seed: int = 0) -> dict:
    """Median wall time of the ``kcoherence`` stage on the demo material (kernels compiled beforehand).

    Returns the figures as a dict: ``median_s`` (the whole stage call), ``analysis_median_s`` (textons and
    coherence sets of every level), ``synthesis_median_s`` (all passes), ``other_median_s`` (appearance vectors,
    building the CoordMap), ``cpu_median_s`` (process CPU time, all threads), the configuration and the device.
    """
    from btforge.context import StageContext

    exemplar = benchmark_exemplar(exemplar_size)
    params = dict(size=[size, size], k=k, neighborhood=neighborhood, levels=levels, wrap=wrap, seed=seed)
    kcoherence(exemplar=exemplar, **{**params, "size": [16, 16]})  # warm-up: kernel builds
    totals, analysis, synthesis, cpu = [], [], [], []
    for _ in range(repeat):
        ctx = StageContext(node="bench", quiet=True)
        start, start_cpu = time.perf_counter(), time.process_time()
        kcoherence(ctx=ctx, exemplar=exemplar, **params)
        totals.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        analysis.append(ctx.notes["seconds_analysis"])
        synthesis.append(ctx.notes["seconds_synthesis"])
    total = statistics.median(totals)
    return {
        "exemplar": [exemplar_size, exemplar_size], "size": [size, size], "k": k, "neighborhood": neighborhood,
        "levels": levels, "wrap": wrap, "repeat": repeat, "device": get_backend().description,
        "median_s": total, "analysis_median_s": statistics.median(analysis),
        "synthesis_median_s": statistics.median(synthesis),
        "other_median_s": total - statistics.median(analysis) - statistics.median(synthesis),
        "cpu_median_s": statistics.median(cpu), "coherent_fraction": ctx.notes["coherent_fraction"],
        "causal_order": CAUSAL_ORDER,
    }
