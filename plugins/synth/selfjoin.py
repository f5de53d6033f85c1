"""The self-join of an exemplar's neighbourhoods by coherence propagation (PatchMatch with NN-descent).

:func:`.search.similar_texels` asks, for every texel of one image, for the texels with the nearest
neighbourhoods: queries and exemplar are the same vectors, laid out on a grid.  Neighbouring texels then have
shifted matches, which a general index (:func:`.search.knn`) does not know.  :func:`self_join` uses it: lists
start from random texels and improve, every step, from the neighbours' matches shifted back, from the
matches' own matches and from a few random texels (``selfjoin.cl``, one work-item per texel, one launch per
step; ``improve_numpy`` is its twin).  The steps run on the vectors' leading principal axes with lists of
:data:`LIST_FACTOR` x the length asked for, re-ranked at full dimension at the end, as the fast engine does.
What can be missed is a true neighbour no step nominated; the recall against the exact engine is tested
against :data:`.search.FAST_RECALL_FLOOR` on a 48 x 48 exemplar and reported by the bench; it falls on
larger, smoother exemplars (0.44 on the 512 x 512 ``tablet1.ptm``, where HNSW finds 0.74), which is why this
is the opt-in ``search: coherent`` and not the default.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from btforge.backend import get_backend

from .search import candidate_distances_opencl, principal_projection

KERNELS = Path(__file__).with_name("selfjoin.cl")
STEPS = 8                #: improvement steps after the first
FIRST_RANDOM = 24        #: random candidates per texel in the first step (the lists start empty)
STEP_RANDOM = 4          #: random candidates per texel in every later step
LIST_FACTOR = 2          #: lists kept during the steps, per entry asked for (re-ranked at full dimension)
MIN_LIST = 8
NN = 4                   #: nearest entries of a texel's list whose own nearest NN entries are tried
REDUCED_DIMS = 16        #: principal axes the steps compare (at most; fewer if they keep the variance)
SAMPLE = 2048            #: vectors the principal axes are fitted on
SEED = 0x5eed

_U32 = np.uint32


def mix_hash(h: np.ndarray) -> np.ndarray:
    """Twin of ``mix_hash`` (uint32 arithmetic, wrapping)."""
    h = np.asarray(h, _U32)
    h = h ^ (h >> _U32(16))
    h = h * _U32(0x7feb352d)
    h = h ^ (h >> _U32(15))
    h = h * _U32(0x846ca68b)
    return h ^ (h >> _U32(16))


def candidates_numpy(idx: np.ndarray, h: int, w: int, seed: int, step: int, n_random: int,
                     nn: int = NN, spread: int = 1) -> np.ndarray:
    """Every texel's candidates ``[N, C]`` (-1: none) in the kernel's order: propagation, neighbours of
    neighbours, random texels."""
    n, top = idx.shape
    ys, xs = np.divmod(np.arange(n), w)
    parts = []
    for o in range(8):
        o += o >= 4
        dy, dx = spread * (o // 3 - 1), spread * (o % 3 - 1)
        qy, qx = ys + dy, xs + dx
        inside = (qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)
        j = np.where(inside[:, None], idx[np.where(inside, qy * w + qx, 0)], -1)
        jy, jx = np.divmod(np.maximum(j, 0), w)
        cy, cx = jy - dy, jx - dx
        ok = (j >= 0) & (cy >= 0) & (cy < h) & (cx >= 0) & (cx < w)
        parts.append(np.where(ok, cy * w + cx, -1))
    nn = min(nn, top)
    own = idx[:, :nn]
    matched = idx[np.maximum(own, 0)][:, :, :nn]                        # [N, nn, nn]
    parts.append(np.where((own >= 0)[:, :, None], matched, -1).reshape(n, nn * nn))
    if n_random:
        r = np.arange(n_random, dtype=_U32)[None, :]
        p = np.arange(n, dtype=_U32)[:, None]
        inner = mix_hash(_U32(step) * _U32(0x10001) + r)
        parts.append((mix_hash(_U32(seed) ^ mix_hash(p * _U32(0x9e3779b1) ^ inner)) % _U32(n)).astype(np.int64))
    return np.concatenate(parts, axis=1).astype(np.int64)


def improve_numpy(vectors: np.ndarray, h: int, w: int, exclude: int, allowed: np.ndarray, idx: np.ndarray,
                  dist: np.ndarray, seed: int, step: int, n_random: int, nn: int = NN,
                  spread: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``selfjoin_step``: the ``TOPK`` smallest (distance, index) of the old list and the admissible
    candidates, distances summed in float32 one dimension after the other."""
    n, top = idx.shape
    cand = candidates_numpy(idx, h, w, seed, step, n_random, nn, spread)
    ys, xs = np.divmod(np.arange(n), w)
    cy, cx = np.divmod(np.maximum(cand, 0), w)
    near = np.maximum(np.abs(cy - ys[:, None]), np.abs(cx - xs[:, None])) <= exclude
    cand = np.where((cand >= 0) & allowed[np.maximum(cand, 0)] & ~near, cand, -1)
    acc = np.zeros(cand.shape, np.float32)
    rows = vectors[np.maximum(cand, 0)]
    with np.errstate(over="ignore", invalid="ignore"):
        for k in range(vectors.shape[1]):
            t = vectors[:, None, k] - rows[:, :, k]
            acc += t * t
    all_i = np.concatenate([idx.astype(np.int64), cand], axis=1)
    all_d = np.concatenate([dist, np.where(cand >= 0, acc, np.float32(np.inf))], axis=1)
    key = np.where(all_i < 0, np.iinfo(np.int64).max, all_i)
    by_index = np.lexsort((all_d, key), axis=1)
    key_sorted = np.take_along_axis(key, by_index, axis=1)
    repeat = np.zeros(key.shape, bool)
    repeat[:, 1:] = key_sorted[:, 1:] == key_sorted[:, :-1]
    dup = np.zeros(key.shape, bool)
    np.put_along_axis(dup, by_index, repeat, axis=1)
    all_d = np.where(dup, np.float32(np.inf), all_d)
    key = np.where(dup, np.iinfo(np.int64).max, key)
    order = np.lexsort((key, all_d), axis=1)[:, :top]
    best_i = np.take_along_axis(np.where(key == np.iinfo(np.int64).max, -1, key), order, axis=1)
    return best_i.astype(np.int32), np.take_along_axis(all_d, order, axis=1).astype(np.float32)


class _Steps:
    """``selfjoin_step`` over one image's vectors, the lists kept on the device between launches."""

    def __init__(self, vectors: np.ndarray, h: int, w: int, exclude: int, allowed: np.ndarray, top: int,
                 nn: int = NN):
        self.backend = get_backend()
        cl = self.backend.cl
        self.n, self.h, self.w, self.exclude, self.top = len(vectors), h, w, exclude, top
        self.kernel = self.backend.kernel(KERNELS, "selfjoin_step", (f"-DDIM={vectors.shape[1]}", f"-DTOPK={top}",
                                                                      f"-DNN={min(nn, top)}"))
        self.vectors = self.backend.host_input(np.ascontiguousarray(vectors, np.float32))
        self.allowed = self.backend.host_input(np.ascontiguousarray(allowed, np.uint8))
        mf = cl.mem_flags
        self.lists = [[cl.Buffer(self.backend.context, mf.READ_WRITE, size=4 * self.n * top) for _ in range(2)]
                      for _ in range(2)]

    def load(self, idx: np.ndarray, dist: np.ndarray) -> None:
        cl = self.backend.cl
        cl.enqueue_copy(self.backend.queue, self.lists[0][0], np.ascontiguousarray(idx, np.int32))
        cl.enqueue_copy(self.backend.queue, self.lists[0][1], np.ascontiguousarray(dist, np.float32))

    def step(self, seed: int, step: int, n_random: int, spread: int = 1) -> None:
        (idx_in, d_in), (idx_out, d_out) = self.lists
        self.kernel.set_args(self.vectors, np.int32(self.h), np.int32(self.w), np.int32(self.exclude), self.allowed,
                             idx_in, d_in, idx_out, d_out, np.uint32(seed), np.uint32(step), np.int32(n_random),
                             np.int32(spread))
        self.backend.cl.enqueue_nd_range_kernel(self.backend.queue, self.kernel, (-(-self.n // 64) * 64,), (64,))
        self.lists.reverse()

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        idx_dev, d_dev = self.lists[0]
        return (self.backend.from_device(idx_dev, (self.n, self.top), np.int32),
                self.backend.from_device(d_dev, (self.n, self.top), np.float32))


def improve_opencl(vectors, h, w, exclude, allowed, idx, dist, seed, step, n_random, nn=NN, spread=1):
    """One ``selfjoin_step`` launch (the twin's signature): the improved lists."""
    steps = _Steps(vectors, h, w, exclude, allowed, idx.shape[1], nn)
    steps.load(idx, dist)
    steps.step(seed, step, n_random, spread)
    return steps.read()


def self_join(vectors: np.ndarray, h: int, w: int, m: int, *, exclude: int = 0, allowed: np.ndarray | None = None,
              steps: int = STEPS, device: str = "opencl") -> tuple[np.ndarray, np.ndarray]:
    """For every texel of an ``h x w`` grid of neighbourhood vectors ``[h * w, D]``, the ``m`` allowed texels more
    than ``exclude`` (Chebyshev) away with the nearest vectors, as far as the steps find them.

    Returns ``[h * w, m]`` int64 texels sorted by (full squared distance, index), -1 where none was found, and
    their ``[h * w, m]`` float32 squared distances (inf where missing).  ``device`` ``numpy`` runs the twin.
    """
    n = h * w
    allowed = np.ones(n, bool) if allowed is None else np.asarray(allowed, bool).ravel()
    projection = principal_projection(vectors, max_dims=REDUCED_DIMS, min_dims=min(REDUCED_DIMS, 8), sample=SAMPLE)
    reduced = projection.apply(vectors)
    top = max(MIN_LIST, LIST_FACTOR * m)
    idx = np.full((n, top), -1, np.int32)
    dist = np.full((n, top), np.inf, np.float32)
    schedule = [(s, FIRST_RANDOM if s == 0 else STEP_RANDOM, spread_at(s, steps, max(h, w)))
                for s in range(steps + 1)]
    if device == "numpy":
        for s, n_random, spread in schedule:
            idx, dist = improve_numpy(reduced, h, w, exclude, allowed, idx, dist, SEED, s, n_random, NN, spread)
        full = _full_distances_numpy(vectors, idx)
    else:
        runner = _Steps(reduced, h, w, exclude, allowed, top)
        runner.load(idx, dist)
        for s, n_random, spread in schedule:
            runner.step(SEED, s, n_random, spread)
        idx, _ = runner.read()
        full = candidate_distances_opencl(vectors, vectors, idx.astype(np.int64))
    idx = idx.astype(np.int64)
    key = np.where(idx < 0, np.iinfo(np.int64).max, idx)
    order = np.lexsort((key, full), axis=1)[:, :m]
    return np.take_along_axis(idx, order, axis=1), np.take_along_axis(full, order, axis=1)


def spread_at(step: int, steps: int, side: int) -> int:
    """The propagation spread of a step: 2^(n-1), ..., 2, 1 over steps 1 .. n, n = min(steps / 2, log2(side) - 2)
    (a jump flood: coherent matches cross the image in log steps), then 1."""
    halvings = max(0, min(steps // 2, int(np.log2(max(side, 1))) - 2))
    return 1 << max(0, halvings - step) if step else 1


def _full_distances_numpy(vectors, idx):
    from .search import candidate_distances_numpy
    return candidate_distances_numpy(vectors, vectors, idx.astype(np.int64))
