"""The self-join of an image's neighbourhoods: for every texel, the texels whose windows are most similar.

:func:`.search.similar_texels` asks this of one image (the k-coherence sets, the jump map's targets): queries
and exemplar are the same windows, laid out on a grid, and neighbouring texels have shifted matches, which a
general index (:func:`.search.knn`) does not know.  :func:`self_join` uses it (PatchMatch with NN-descent,
``selfjoin.cl``, one work-item per texel and one launch per step; :func:`improve_numpy` is its twin):

- the lists start from seeds: with ``init="tree"`` the :data:`TREE_SEEDS` nearest texels in an approximate
  kd-tree over the windows' :data:`TREE_DIMS` leading principal components (scipy's cKDTree on every core; few
  dimensions keep the tree fast, the steps repair what it misses), with ``init="random"`` random texels;
- every step, a texel tries the first b entries of its four neighbours' lists shifted back, the first b entries
  of its first b matches' lists and, in the first :data:`RANDOM_STEPS` steps, a few random texels; later steps
  skip texels whose candidates are those of the step before, and the steps stop once fewer than
  :data:`SETTLED` of the lists change.  The breadth b (:func:`breadth`) grows with the image;
- a last step draws the neighbours' whole lists and :data:`LAST_EXTRA` more matches' lists, once.

Distances are always the full window distances, read from the edge-padded feature image (no ``[N, D x window]``
vectors: 9 x 25 floats a texel would be 236 MB at 512 x 512), so what is found is exact; what can be missed is
a true neighbour no step nominated.  Recall against the exact engine is tested against
:data:`.search.SELF_RECALL_FLOOR` and reported by ``btforge bench kcoherence --recall N``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from btforge.backend import get_backend, single_threaded_blas

from .search_base import NONE_KEY, cores, empty_lists, packed, principal_projection, smallest, square_window

KERNELS = Path(__file__).with_name("selfjoin.cl")
TREE_DIMS = 8            #: principal components of the windows the kd-tree compares
TREE_SEEDS = 4           #: kd-tree nominees per texel, beyond the excluded texels around it
TREE_EPS = 3.0           #: the kd-tree's approximation: nominees within (1 + eps) x the true distances
TREE_LEAF = 32           #: points per kd-tree leaf
RANDOM_SEEDS = 24        #: random seeds per texel of init="random"
STEP_RANDOM = 2          #: random candidates per texel in each of the first RANDOM_STEPS steps
RANDOM_STEPS = {"tree": 2, "random": 6}
STEPS = {"tree": 8, "random": 14}   #: steps after the seeding one, at most (before the last, wider one)
SETTLED = 0.01           #: share of changed lists below which the steps stop
LIST = 8                 #: list length kept during the steps (at least the length asked for)
BREADTH = 4              #: entries propagated from each neighbour's list, and matches whose matches are tried, at first
BREADTH_TEXELS = 1 << 15  #: images of up to about this many texels start at BREADTH; each doubling beyond, one more
LAST_EXTRA = 2           #: once the lists settle, a last step draws the neighbours' whole lists and this many
                         #: more matches' lists
PCA_SAMPLE = 4096        #: windows the principal components are fitted on
SEED = 0x5eed

_U32 = np.uint32


def self_join(features: np.ndarray, radius: int, m: int, *, exclude: int = 0, allowed: np.ndarray | None = None,
              init: str = "tree", device: str = "opencl") -> tuple[np.ndarray, np.ndarray]:
    """For every texel of ``[H, W, D]`` features, the ``m`` allowed texels more than ``exclude`` (Chebyshev) away
    whose ``(2 radius + 1)^2`` windows (the image edge-extended) are nearest, as far as the steps find them.

    Returns ``[H * W, m]`` int32 texels sorted by (squared window distance, index), -1 where none was found, and
    their ``[H * W, m]`` float32 squared distances (inf where missing).  ``device`` ``numpy`` runs the twin.
    """
    f = np.ascontiguousarray(features, np.float32)
    h, w, _ = f.shape
    allowed = np.ones(h * w, bool) if allowed is None else np.asarray(allowed, bool).ravel()
    image = padded_image(f, radius)
    top = max(LIST, m)
    if init == "tree":
        seeds, n_random = tree_seeds(image, h, w, radius, allowed, TREE_SEEDS + (2 * exclude + 1) ** 2), 0
    else:
        seeds, n_random = np.zeros((h * w, 0), np.int32), RANDOM_SEEDS
    steps = (_Steps if device == "opencl" else _NumpySteps)(image, h, w, radius, exclude, allowed, top)
    wide = min(breadth(h * w), top)
    steps.step(seeds, 0, n_random, False, (wide, wide))
    count = _settle(steps, init, 1, (wide, wide), h * w)
    if wide < top:
        # a last, wider step: every texel tries, once, its neighbours' whole lists and more of its matches' lists
        steps.step(None, count + 1, 0, False, (top, min(top, wide + LAST_EXTRA)))
    idx, dist = steps.lists()
    return idx[:, :m], dist[:, :m]


def _settle(steps, init, first: int, wide: tuple[int, int], n: int) -> int:
    """Steps from ``first`` on until fewer than :data:`SETTLED` of the lists change (random candidates in the
    first :data:`RANDOM_STEPS` of them); the last step's number."""
    last = first + STEPS[init] - 1
    for s in range(first, last + 1):
        settle = s > RANDOM_STEPS[init]
        if steps.step(None, s, 0 if settle else STEP_RANDOM, settle, wide) < SETTLED * n and settle:
            return s
    return last


def breadth(texels: int) -> int:
    """Entries a step draws from each source list: :data:`BREADTH`, one more per doubling of the texels beyond
    :data:`BREADTH_TEXELS`: a larger image holds more near matches that coherence alone does not reach."""
    return BREADTH + max(0, int(round(np.log2(max(texels, 1) / BREADTH_TEXELS))))


def padded_image(features: np.ndarray, radius: int) -> np.ndarray:
    """``[H, W, D]`` features edge-extended by ``radius`` on every side, C-contiguous float32."""
    return np.ascontiguousarray(np.pad(features, ((radius, radius), (radius, radius), (0, 0)), mode="edge"),
                                np.float32)


def tree_seeds(image: np.ndarray, h: int, w: int, radius: int, allowed: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` allowed texels ``[h * w, count]`` int32 (-1: fewer allowed) whose windows' leading principal
    components are nearest each texel's, in the :func:`padded_image` of an ``h x w`` image (scipy's cKDTree,
    queried on every core; deterministic)."""
    from scipy.spatial import cKDTree
    listed = np.flatnonzero(allowed).astype(np.int32)
    if not len(listed):
        return np.full((h * w, 0), -1, np.int32)
    reduced = window_components(image, h, w, radius, TREE_DIMS)
    tree = cKDTree(reduced[listed], leafsize=TREE_LEAF, balanced_tree=False, compact_nodes=False)
    count = min(count, len(listed))
    _, rows = tree.query(reduced, k=count, eps=TREE_EPS, workers=cores())
    rows = rows.reshape(len(reduced), count)
    return np.where(rows < len(listed), listed[np.minimum(rows, len(listed) - 1)], -1).astype(np.int32)


def window_components(image: np.ndarray, h: int, w: int, radius: int, dims: int) -> np.ndarray:
    """Every texel's window in the :func:`padded_image` of an ``h x w`` image, projected on the windows' ``dims``
    leading principal axes ``[h * w, dims]`` float32 (fitted on :data:`PCA_SAMPLE` windows; the mean is not
    subtracted: a kd-tree does not need it), summed one window offset at a time so the ``[h * w, D x window]``
    vectors never exist."""
    d = image.shape[2]
    offsets = square_window(2 * radius + 1) + radius
    rng = np.random.default_rng(0)
    pick = np.sort(rng.choice(h * w, min(PCA_SAMPLE, h * w), replace=False))
    py, px = np.divmod(pick, w)
    sample = image[py[:, None] + offsets[None, :, 0], px[:, None] + offsets[None, :, 1]].reshape(len(pick), -1)
    axes = principal_projection(sample, max_dims=dims, min_dims=dims).axes.reshape(len(offsets), d, -1)
    out = np.zeros((h, w, axes.shape[2]), np.float32)
    with single_threaded_blas():  # thin products: threads cost more than they save
        for (oy, ox), a in zip(offsets, axes):
            out += image[oy:oy + h, ox:ox + w] @ a
    return out.reshape(h * w, -1)


# ============================================================================================ the steps


class _Steps:
    """``selfjoin_step`` over one image, the lists and their changed flags kept on the device between launches."""

    def __init__(self, image, h, w, radius, exclude, allowed, top):
        self.backend = get_backend()
        cl = self.backend.cl
        self.n, self.h, self.w, self.exclude, self.top = h * w, h, w, exclude, top
        self.options = (f"-DFEATURES={image.shape[2]}", f"-DRADIUS={radius}", f"-DTOPK={top}")
        self.image = self.backend.host_input(image)
        self.allowed = self.backend.host_input(np.ascontiguousarray(allowed, np.uint8))
        mf = cl.mem_flags
        ctx = self.backend.context
        self.buffers = [(cl.Buffer(ctx, mf.READ_WRITE, size=4 * self.n * top), cl.Buffer(ctx, mf.READ_WRITE, size=4 * self.n * top),
                         cl.Buffer(ctx, mf.READ_WRITE, size=self.n)) for _ in range(2)]
        idx, dist = empty_lists(self.n, top)
        cl.enqueue_copy(self.backend.queue, self.buffers[0][0], idx)
        cl.enqueue_copy(self.backend.queue, self.buffers[0][1], dist)
        cl.enqueue_copy(self.backend.queue, self.buffers[0][2], np.ones(self.n, np.uint8))
        self.no_seeds = self.backend.to_device(np.full(1, -1, np.int32))

    def step(self, seeds, step: int, n_random: int, skip_settled: bool, wide) -> int:
        """One launch drawing ``wide`` = (entries of each neighbour's list, matches whose first as many entries
        are tried); returns how many lists changed."""
        nprop, nn = wide
        (idx_in, d_in, ch_in), (idx_out, d_out, ch_out) = self.buffers
        seeds_dev = self.no_seeds if seeds is None or not seeds.shape[1] else \
            self.backend.to_device(np.ascontiguousarray(seeds, np.int32))
        n_seed = 0 if seeds is None else seeds.shape[1]
        kernel = self.backend.kernel(KERNELS, "selfjoin_step", (*self.options, f"-DNPROP={nprop}", f"-DNN={nn}"))
        kernel.set_args(self.image, np.int32(self.h), np.int32(self.w), np.int32(self.exclude), self.allowed,
                             idx_in, d_in, ch_in, idx_out, d_out, ch_out, seeds_dev, np.int32(n_seed), np.uint32(SEED),
                             np.uint32(step), np.int32(n_random), np.int32(skip_settled))
        self.backend.cl.enqueue_nd_range_kernel(self.backend.queue, kernel, (-(-self.n // 64) * 64,), (64,))
        self.buffers.reverse()
        return int(np.count_nonzero(self.backend.from_device(self.buffers[0][2], (self.n,), np.uint8)))

    def lists(self) -> tuple[np.ndarray, np.ndarray]:
        idx_dev, d_dev, _ = self.buffers[0]
        return (self.backend.from_device(idx_dev, (self.n, self.top), np.int32),
                self.backend.from_device(d_dev, (self.n, self.top), np.float32))


class _NumpySteps:
    """The twin of :class:`_Steps`: :func:`improve_numpy` on host lists."""

    def __init__(self, image, h, w, radius, exclude, allowed, top):
        self.args = (image, h, w, radius, exclude, allowed)
        self.idx, self.dist = empty_lists(h * w, top)
        self.changed = np.ones(h * w, bool)

    def step(self, seeds, step: int, n_random: int, skip_settled: bool, wide) -> int:
        nprop, nn = wide
        seeds = np.zeros((len(self.idx), 0), np.int32) if seeds is None else seeds
        self.idx, self.dist, self.changed = improve_numpy(*self.args, self.idx, self.dist, self.changed, seeds, SEED,
                                                          step, n_random, skip_settled, nprop, nn)
        return int(np.count_nonzero(self.changed))

    def lists(self) -> tuple[np.ndarray, np.ndarray]:
        return self.idx, self.dist


def improve_opencl(image, h, w, radius, exclude, allowed, idx, dist, changed, seeds, seed, step, n_random,
                   skip_settled, nprop, nn):
    """One ``selfjoin_step`` launch (the twin's signature): the improved lists and their changed flags."""
    backend = get_backend()
    cl = backend.cl
    n, top = idx.shape
    kernel = backend.kernel(KERNELS, "selfjoin_step", (f"-DFEATURES={image.shape[2]}", f"-DRADIUS={radius}",
                                                       f"-DTOPK={top}", f"-DNPROP={nprop}", f"-DNN={nn}"))
    mf = cl.mem_flags
    inputs = [backend.to_device(np.ascontiguousarray(a)) for a in
              (image, allowed.astype(np.uint8), idx.astype(np.int32), dist.astype(np.float32), changed.astype(np.uint8),
               seeds.astype(np.int32) if seeds.size else np.full(1, -1, np.int32))]
    outs = [cl.Buffer(backend.context, mf.READ_WRITE, size=s) for s in (4 * n * top, 4 * n * top, n)]
    kernel.set_args(inputs[0], np.int32(h), np.int32(w), np.int32(exclude), inputs[1], inputs[2], inputs[3], inputs[4],
                    *outs, inputs[5], np.int32(seeds.shape[1]), np.uint32(seed), np.uint32(step), np.int32(n_random),
                    np.int32(skip_settled))
    cl.enqueue_nd_range_kernel(backend.queue, kernel, (-(-n // 64) * 64,), (64,))
    return (backend.from_device(outs[0], (n, top), np.int32), backend.from_device(outs[1], (n, top), np.float32),
            backend.from_device(outs[2], (n,), np.uint8).astype(bool))


# ============================================================================================ the twin


def mix_hash(h: np.ndarray) -> np.ndarray:
    """Twin of ``mix_hash`` (uint32 arithmetic, wrapping)."""
    h = np.asarray(h, _U32)
    h = h ^ (h >> _U32(16))
    h = h * _U32(0x7feb352d)
    h = h ^ (h >> _U32(15))
    h = h * _U32(0x846ca68b)
    return h ^ (h >> _U32(16))


def candidates_numpy(idx: np.ndarray, h: int, w: int, seeds: np.ndarray, seed: int, step: int, n_random: int,
                     nprop: int, nn: int) -> np.ndarray:
    """Every texel's candidates ``[N, C]`` int64 (-1: none) in the kernel's order: seeds, propagation from the 4
    neighbours, neighbours of neighbours, random texels."""
    n = len(idx)
    ys, xs = np.divmod(np.arange(n), w)
    parts = [seeds.astype(np.int64)]
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        qy, qx = ys + dy, xs + dx
        inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
        j = np.where(inside[:, None], idx[np.where(inside, qy * w + qx, 0), :nprop], -1).astype(np.int64)
        jy, jx = np.divmod(np.maximum(j, 0), w)
        cy, cx = jy - dy, jx - dx
        parts.append(np.where((j >= 0) & (cy >= 0) & (cy < h) & (cx >= 0) & (cx < w), cy * w + cx, -1))
    own = idx[:, :nn].astype(np.int64)
    matched = idx[np.maximum(own, 0)][:, :, :nn]                        # [N, nn, nn]
    parts.append(np.where((own >= 0)[:, :, None], matched, -1).reshape(n, nn * nn).astype(np.int64))
    if n_random:
        r = np.arange(n_random, dtype=_U32)[None, :]
        p = np.arange(n, dtype=_U32)[:, None]
        inner = mix_hash(_U32(step) * _U32(0x10001) + r)
        parts.append((mix_hash(_U32(seed) ^ mix_hash(p * _U32(0x9e3779b1) ^ inner)) % _U32(n)).astype(np.int64))
    return np.concatenate(parts, axis=1)


def sources_changed_numpy(changed: np.ndarray, idx: np.ndarray, h: int, w: int, nn: int) -> np.ndarray:
    """Twin of ``sources_changed``: texels whose own, 4 neighbours' or first ``nn`` matches' lists changed."""
    grid = changed.reshape(h, w)
    out = grid.copy()
    out[1:] |= grid[:-1]
    out[:-1] |= grid[1:]
    out[:, 1:] |= grid[:, :-1]
    out[:, :-1] |= grid[:, 1:]
    own = idx[:, :nn]
    return out.ravel() | ((own >= 0) & changed[np.maximum(own, 0)]).any(axis=1)


def window_distances_numpy(image: np.ndarray, w: int, radius: int, rows: np.ndarray, cand: np.ndarray) -> np.ndarray:
    """Twin of ``window_distance`` (without abandoning: a sum abandoned above the last entry is rejected either
    way): squared distances ``[len(rows), C]`` float32 of texels ``rows`` to their candidates ``cand`` (-1: inf)."""
    side, d = 2 * radius + 1, image.shape[2]
    flat, stride = image.reshape(-1), w + 2 * radius
    segment = np.arange(side * d)
    ry, rx = np.divmod(rows, w)
    cy, cx = np.divmod(np.maximum(cand, 0), w)
    acc = np.zeros(cand.shape, np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        for row in range(side):
            u = flat[((ry + row) * stride + rx)[:, None] * d + segment][:, None, :]
            v = flat[((cy + row) * stride + cx)[:, :, None] * d + segment]
            acc += _row_sum(np.square(u - v))
    return np.where(cand >= 0, acc, np.float32(np.inf))


def _row_sum(squares: np.ndarray) -> np.ndarray:
    """The kernel's sum of one window row's squares ``[..., L]``: 8 lanes over the whole chunks of 8, summed
    pairwise, then the last ``L % 8`` one by one."""
    chunks = squares.shape[-1] // 8
    total = np.zeros(squares.shape[:-1], np.float32)
    if chunks:
        lanes = squares[..., :8 * chunks].reshape(*squares.shape[:-1], chunks, 8)
        lane = lanes[..., 0, :].copy()
        for c in range(1, chunks):
            lane += lanes[..., c, :]
        total = ((lane[..., 0] + lane[..., 1]) + (lane[..., 2] + lane[..., 3])) + \
                ((lane[..., 4] + lane[..., 5]) + (lane[..., 6] + lane[..., 7]))
    for j in range(8 * chunks, squares.shape[-1]):
        total = total + squares[..., j]
    return total


def improve_numpy(image, h, w, radius, exclude, allowed, idx, dist, changed, seeds, seed, step, n_random,
                  skip_settled, nprop, nn, chunk=2048):
    """Twin of ``selfjoin_step``: the ``TOPK`` smallest (distance, index) of the old list and the admissible
    candidates, and which lists changed."""
    n, top = idx.shape
    active = sources_changed_numpy(changed, idx, h, w, min(nn, top)) if skip_settled else np.ones(n, bool)
    cand = candidates_numpy(idx, h, w, seeds, seed, step, n_random, min(nprop, top), min(nn, top))
    ys, xs = np.divmod(np.arange(n), w)
    cy, cx = np.divmod(np.maximum(cand, 0), w)
    near = np.maximum(np.abs(cy - ys[:, None]), np.abs(cx - xs[:, None])) <= exclude
    cand = np.where((cand >= 0) & allowed[np.maximum(cand, 0)] & ~near, cand, -1)
    new_idx, new_dist = idx.copy(), dist.copy()
    for start in np.arange(0, n, chunk):
        rows = np.flatnonzero(active[start:start + chunk]) + start
        if not len(rows):
            continue
        c = cand[rows]
        keys = np.concatenate([packed(dist[rows], idx[rows]), packed(window_distances_numpy(image, w, radius, rows, c), c)],
                              axis=1)
        keys.sort(axis=1)
        repeat = np.zeros(keys.shape, bool)
        repeat[:, 1:] = (keys[:, 1:] == keys[:, :-1]) & (keys[:, 1:] != NONE_KEY)
        keys[repeat] = NONE_KEY
        new_idx[rows], new_dist[rows] = smallest(keys, top)
    return new_idx.astype(np.int32), new_dist, (new_idx != idx).any(axis=1)
