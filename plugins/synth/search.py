"""The neighbourhood search every synthesizer shares: k nearest exemplar vectors of many query vectors.

:func:`knn` is the one entry point (its signature is agreed across the synthesizer families)::

    indices, squared_distances = knn(exemplar, queries, k, engine="fast")   # or engine="exact"

Engines
    ``exact``
        Brute force on OpenCL (``search.cl``): one work-item per query keeps its k best in registers while
        the exemplar is streamed past in tiles, one launch per tile, so memory stays O((M + N) D) and the
        lists are exactly those of sorting all distances by (distance, index).  ``knn_exact_numpy`` is its
        NumPy twin (the same float32 operations in the same order).
    ``fast``
        The exemplar vectors are rotated onto their principal axes and cut to the leading ones (enough for
        :data:`FAST_ENERGY` of the variance, at most :data:`FAST_MAX_DIMS`); an HNSW graph (hnswlib, Apache-2.0)
        over the reduced vectors nominates :data:`FAST_OVERSAMPLE` x k candidates per query, whose distances are
        then computed in full and re-ranked.  Returned distances are always full-dimensional and exact for the
        rows returned; what can be missed is a true neighbour the graph did not nominate.  Measured recall
        (share of the true k nearest found) and distance ratio are in the README and tested against
        :data:`FAST_RECALL_FLOOR`.  hnswlib rather than scipy's cKDTree: on 9-D PTM neighbourhoods of real
        captures (5 x 5 windows, 225-D, cut to 24) it was 2-3x faster at 192^2 and 5-10x at 439 x 487 for
        the same recall; a kd-tree degrades past ~10 dimensions.  The graph is built single-threaded with a
        fixed seed, so results do not depend on timing; queries run on every core.

Self-joins
    :func:`similar_texels` (every texel of one image against the same image: the k-coherence sets, the jump
    targets) with the fast engine runs :func:`.selfjoin.self_join`: a kd-tree over a few principal components
    of the windows seeds every texel's list, then steps on OpenCL improve the lists by coherence at full
    dimension (a texel tries its four neighbours' matches shifted back and its nearest matches' own nearest)
    until few lists change.  Distances are the full window distances, so what is found is exact.

Reuse
    The fast engine's index is kept per exemplar content (:func:`fast_index`, a small LRU), so repeated
    :func:`knn` calls on one exemplar build it once; a caller querying one exemplar very often can keep
    ``index = fast_index(exemplar)`` and call ``index.query(queries, k)``, which skips hashing the exemplar.

Windows
    Neighbourhood vectors of any ``[H, W, D]`` feature image over any window of offsets: :func:`square_window`
    (n x n), :func:`causal_window` (the part of n x n before the centre in scanline order), and
    :func:`band_window` / :func:`l_shaped_window` (the overlap strips of a block, as quilting compares).
"""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from btforge.backend import get_backend
from btforge.errors import BtforgeInputError

# the windows are part of this module's interface (quilting, the tests); the lists and projections are used here
from .search_base import (band_window, causal_window, cores, empty_lists, l_shaped_window, packed,  # noqa: F401
                          principal_projection, smallest, square_window)

KERNELS = Path(__file__).with_name("search.cl")
ENGINES = ("fast", "exact")
MAX_EXACT_K = 64            #: longest list the exact kernel keeps in registers
TILE_BYTES = 1 << 20        #: exemplar bytes per launch of the exact kernel (a tile stays in cache)
QUERY_CHUNK = 1 << 14       #: queries per chunk of the exact search (bounds the running lists' memory)
LOCAL = 64

FAST_OVERSAMPLE = 4         #: candidates nominated per neighbour asked for, re-ranked at full dimension
FAST_MIN_CANDIDATES = 16
HNSW_M = 12
HNSW_EF_CONSTRUCTION = 48
HNSW_SEED = 100
FAST_RECALL_FLOOR = 0.95    #: recall at k = 6 the tests demand of the fast engine on texture neighbourhoods (0.999 measured)
SELF_RECALL_FLOOR = 0.95    #: recall the tests demand of the fast self-join (similar_texels) on texture neighbourhoods (0.98 measured at 48 x 48)
FAST_BELOW = 2048           #: exemplars of at most this many vectors are searched exactly (it is as fast)
INDEX_CACHE = 4             #: fast indices kept, keyed by the exemplar's content (re-synthesis skips the build)


# ============================================================================================ windows


def neighbourhood_vectors(features: np.ndarray, window: np.ndarray, *, boundary: str = "edge",
                          weights: np.ndarray | None = None) -> np.ndarray:
    """Every texel's neighbourhood as one vector ``[H * W, len(window) * D]`` float32 (offset-major).

    ``window`` holds (dy, dx) offsets; beyond the image the features continue by ``boundary`` (``edge``,
    ``reflect``, ``wrap``, as :func:`numpy.pad`).  ``weights`` (one per offset) scale each offset's features by
    their square root, so squared vector distances are the weighted sums of texel distances.
    """
    f = np.asarray(features, np.float32)
    if f.ndim == 2:
        f = f[..., None]
    h, w, d = f.shape
    offs = np.asarray(window, np.int64).reshape(-1, 2)
    pad = int(np.abs(offs).max()) if offs.size else 0
    padded = np.pad(f, ((pad, pad), (pad, pad), (0, 0)), mode=boundary) if pad else f
    out = np.empty((h, w, len(offs), d), np.float32)
    for i, (dy, dx) in enumerate(offs):
        out[:, :, i] = padded[pad + dy:pad + dy + h, pad + dx:pad + dx + w]
    if weights is not None:
        out *= np.sqrt(np.asarray(weights, np.float32))[None, None, :, None]
    return out.reshape(h * w, len(offs) * d)


# ============================================================================================ the search


def knn(exemplar: np.ndarray, queries: np.ndarray, k: int, *, engine: str = "fast") -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest exemplar rows of every query row, nearest first.

    Parameters
    ----------
    exemplar
        ``[N, D]`` float32 vectors searched.
    queries
        ``[M, D]`` float32 vectors whose neighbours are wanted.
    k
        Neighbours per query; when the exemplar has fewer rows, the missing ones are -1 with distance inf.
    engine
        ``fast`` (PCA-reduced HNSW graph, re-ranked exactly) or ``exact`` (OpenCL brute force).

    Returns
    -------
    (indices, squared_distances)
        ``[M, k]`` int64 exemplar rows sorted by (squared distance, index) and ``[M, k]`` float32 squared
        Euclidean distances at full dimension.
    """
    exemplar, queries = _checked(exemplar, queries, k, engine)
    if engine == "exact" or len(exemplar) <= FAST_BELOW:
        return knn_exact_opencl(exemplar, queries, k)
    try:
        return fast_index(exemplar).query(queries, k)
    except RuntimeError:
        # hnswlib cannot fill every list when many vectors coincide (a flat exemplar); brute force can
        return knn_exact_opencl(exemplar, queries, k)


def _checked(exemplar, queries, k, engine):
    problems = []
    if engine not in ENGINES:
        problems.append(f"engine: expected one of {ENGINES}, found {engine!r}")
    ex, qs = np.asarray(exemplar), np.asarray(queries)
    if ex.ndim != 2 or qs.ndim != 2 or ex.shape[1] != qs.shape[1] or ex.shape[1] < 1:
        problems.append(f"vectors: expected exemplar [N, D] and queries [M, D] with the same D >= 1, found "
                        f"{list(ex.shape)} and {list(qs.shape)}")
    if not isinstance(k, (int, np.integer)) or k < 1:
        problems.append(f"k: expected an int >= 1, found {k!r}")
    if not problems and not (np.isfinite(ex).all() and np.isfinite(qs).all()):
        problems.append("vectors: expected finite values, found NaN or inf")
    if problems:
        raise BtforgeInputError("neighbourhood search (knn)", "; ".join(problems),
                                "pass finite float32 arrays [N, D], [M, D], k >= 1, engine 'fast' or 'exact'")
    return np.ascontiguousarray(ex, np.float32), np.ascontiguousarray(qs, np.float32)


def tile_rows(dims: int) -> int:
    """Exemplar rows per launch of the exact search: about :data:`TILE_BYTES` of them."""
    return max(64, TILE_BYTES // (4 * dims))


def knn_exact_opencl(exemplar: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact :func:`knn` on OpenCL (``knn_tile``); lists longer than :data:`MAX_EXACT_K` are filled in steps."""
    if k > MAX_EXACT_K:
        return knn_exact_numpy(exemplar, queries, k)
    backend = get_backend()
    cl = backend.cl
    n, d = exemplar.shape
    m = len(queries)
    kernel = backend.kernel(KERNELS, "knn_tile", (f"-DDIM={d}", f"-DTOPK={k}"))
    exemplar_dev = backend.host_input(exemplar)
    queries_dev = backend.host_input(queries)
    idx, dist = empty_lists(m, k)
    rows = tile_rows(d)
    for q0 in range(0, m, QUERY_CHUNK):
        count = min(QUERY_CHUNK, m - q0)
        mf = cl.mem_flags
        idx_dev = cl.Buffer(backend.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=idx[q0:q0 + count].copy())
        dist_dev = cl.Buffer(backend.context, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=dist[q0:q0 + count].copy())
        glob = (-(-count // LOCAL) * LOCAL,)
        for e0 in range(0, n, rows):
            kernel.set_args(exemplar_dev, np.int32(e0), np.int32(min(rows, n - e0)), queries_dev, np.int32(q0),
                            np.int32(count), idx_dev, dist_dev)
            cl.enqueue_nd_range_kernel(backend.queue, kernel, glob, (LOCAL,))
        idx[q0:q0 + count] = backend.from_device(idx_dev, (count, k), np.int32)
        dist[q0:q0 + count] = backend.from_device(dist_dev, (count, k), np.float32)
    return idx.astype(np.int64), dist


def knn_exact_numpy(exemplar: np.ndarray, queries: np.ndarray, k: int, chunk: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``knn_tile``: the same tiles, the same float32 sums, lists merged by (distance, index)."""
    n, d = exemplar.shape
    m = len(queries)
    idx, dist = empty_lists(m, k)
    rows = tile_rows(d)
    for q0 in range(0, m, chunk):
        q = queries[q0:q0 + chunk]
        best_i, best_d = idx[q0:q0 + chunk].astype(np.int64), dist[q0:q0 + chunk]
        for e0 in range(0, n, rows):
            e = exemplar[e0:e0 + rows]
            acc = np.zeros((len(q), len(e)), np.float32)
            with np.errstate(over="ignore", invalid="ignore"):
                for j in range(d):
                    t = q[:, j, None] - e[None, :, j]
                    acc += t * t
            all_d = np.concatenate([best_d, acc], axis=1)
            all_i = np.concatenate([best_i, np.broadcast_to(np.arange(e0, e0 + len(e)), acc.shape)], axis=1)
            key_i = np.where(all_i < 0, np.iinfo(np.int64).max, all_i)
            order = np.lexsort((key_i, all_d), axis=1)[:, :k] if all_d.shape[1] else None
            best_d = np.take_along_axis(all_d, order, axis=1)
            best_i = np.take_along_axis(all_i, order, axis=1)
        missing = ~np.isfinite(best_d)
        idx[q0:q0 + chunk] = np.where(missing, -1, best_i)
        dist[q0:q0 + chunk] = np.where(missing, np.float32(np.inf), best_d)
    return idx.astype(np.int64), dist


def candidate_distances_opencl(exemplar: np.ndarray, queries: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Full squared distances ``[M, C]`` float32 of each query to its candidate exemplar rows (-1: inf), on
    OpenCL (``knn_distances``): the sums ``knn_tile`` forms, so both engines agree on every neighbour found."""
    backend = get_backend()
    cl = backend.cl
    m, c = rows.shape
    out = np.empty((m, c), np.float32)
    if not out.size:
        return out
    kernel = backend.kernel(KERNELS, "knn_distances", (f"-DDIM={exemplar.shape[1]}", "-DTOPK=1"))
    exemplar_dev, queries_dev = backend.host_input(exemplar), backend.host_input(queries)
    for q0 in range(0, m, QUERY_CHUNK):
        count = min(QUERY_CHUNK, m - q0)
        rows_dev = backend.to_device(np.ascontiguousarray(rows[q0:q0 + count], np.int32))
        out_dev = backend.empty(4 * count * c)
        kernel.set_args(exemplar_dev, queries_dev, np.int32(q0), np.int32(count), rows_dev, np.int32(c), out_dev)
        cl.enqueue_nd_range_kernel(backend.queue, kernel, (-(-c // 8) * 8, count), (8, 1))
        out[q0:q0 + count] = backend.from_device(out_dev, (count, c), np.float32)
    return out


def candidate_distances_numpy(exemplar: np.ndarray, queries: np.ndarray, rows: np.ndarray,
                              chunk: int = 1024) -> np.ndarray:
    """Twin of ``knn_distances``: the same float32 sums, one dimension after the other."""
    out = np.empty(rows.shape, np.float32)
    for start in range(0, len(queries), chunk):
        r = rows[start:start + chunk]
        e = exemplar[np.maximum(r, 0)]
        q = queries[start:start + chunk]
        acc = np.zeros(r.shape, np.float32)
        with np.errstate(over="ignore", invalid="ignore"):
            for j in range(exemplar.shape[1]):
                t = q[:, None, j] - e[:, :, j]
                acc += t * t
        out[start:start + chunk] = np.where(r >= 0, acc, np.float32(np.inf))
    return out


class FastIndex:
    """The fast engine's index over one exemplar: its principal projection and an HNSW graph of the result."""

    def __init__(self, exemplar: np.ndarray):
        import hnswlib
        self.exemplar = exemplar
        self.projection = principal_projection(exemplar)
        reduced = self.projection.apply(exemplar)
        self.graph = hnswlib.Index(space="l2", dim=reduced.shape[1])
        self.graph.init_index(max_elements=len(reduced), M=HNSW_M, ef_construction=HNSW_EF_CONSTRUCTION,
                              random_seed=HNSW_SEED)
        self.graph.set_num_threads(1)  # insertion order fixes the graph: results do not depend on timing
        self.graph.add_items(reduced, np.arange(len(reduced)))
        self.graph.set_num_threads(max(1, cores()))
        self._lock = threading.Lock()

    def nominate(self, queries: np.ndarray, count: int) -> np.ndarray:
        """The ``count`` exemplar rows ``[M, count]`` int64 nearest each query in the reduced space (graph order)."""
        count = min(len(self.exemplar), int(count))
        reduced = self.projection.apply(queries)
        with self._lock:  # ef is the graph's state: two queries at once must not change it under each other
            self.graph.set_ef(max(count, 2 * FAST_MIN_CANDIDATES))
            rows, _ = self.graph.knn_query(reduced, k=count)
        return rows.astype(np.int64)

    def query(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        rows = self.nominate(queries, max(FAST_OVERSAMPLE * k, FAST_MIN_CANDIDATES))
        return ranked(self.exemplar, queries, rows, k)


def ranked(exemplar: np.ndarray, queries: np.ndarray, rows: np.ndarray, k: int,
           device: str = "opencl") -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` candidate ``rows`` ``[M, C]`` (distinct per query, -1: none) nearest each query at full
    dimension, sorted by (squared distance, index); -1 and inf pad lists with fewer than ``k`` candidates."""
    distances = candidate_distances_numpy if device == "numpy" else candidate_distances_opencl
    return smallest(packed(distances(exemplar, queries, rows), rows), k)


def content_key(*arrays: np.ndarray, extra: object = ()) -> str:
    """A digest of arrays' shapes, types and bytes (and of ``extra``): equal content, equal key."""
    digest = hashlib.blake2b(repr(extra).encode(), digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        digest.update(f"{a.shape}{a.dtype}".encode())
        digest.update(a.view(np.uint8).reshape(-1))
    return digest.hexdigest()


class ContentCache:
    """A small thread-safe LRU of results keyed by :func:`content_key` (an analysis per exemplar).

    Every instance is listed, so :func:`clear_caches` can empty them all (a bench timing a cold analysis).
    """

    instances: list["ContentCache"] = []

    def __init__(self, size: int):
        self.size = size
        self._items: OrderedDict[str, object] = OrderedDict()
        self._lock = threading.Lock()
        ContentCache.instances.append(self)

    def get_or_make(self, key: str, make):
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value = make()
        with self._lock:
            self._items[key] = value
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return value

    def clear(self) -> None:
        with self._lock:
            self._items.clear()


def clear_caches() -> None:
    """Forget every cached index and analysis."""
    for cache in ContentCache.instances:
        cache.clear()


_indices = ContentCache(INDEX_CACHE)


def fast_index(exemplar: np.ndarray) -> FastIndex:
    """The :class:`FastIndex` of ``exemplar``, built once per content (a small LRU of :data:`INDEX_CACHE`)."""
    return _indices.get_or_make(content_key(exemplar), lambda: FastIndex(exemplar))


# ============================================================================================ similar exemplar texels


def similar_texels(features: np.ndarray, neighborhood: int, m: int, *, exclude: int = 0,
                   allowed: np.ndarray | None = None, search: str = "fast",
                   device: str = "opencl") -> tuple[np.ndarray, np.ndarray]:
    """For every texel of ``[H, W, D]`` features, the ``m`` texels with the most similar neighbourhoods.

    Two texels' distance is the squared distance of their ``neighborhood x neighborhood`` windows' features
    (the image edge-extended).  Texels within Chebyshev distance ``exclude`` of a texel are left out of its
    list (0: the texel itself; -1: none), and only texels where ``allowed`` ``[H, W]`` is true are listed.
    On more than :data:`FAST_BELOW` texels ``search`` ``fast`` runs the self-join :func:`.selfjoin.self_join`
    seeded by a kd-tree, and ``coherent`` the same seeded at random; ``exact`` (and every search of fewer texels)
    is the :func:`knn` brute force.  ``device`` ``numpy`` runs the twins.

    Returns ``[H * W, m]`` int32 row-major texel indices sorted by (distance, index), -1 where fewer than ``m``
    texels qualify, and ``[H * W, m]`` float32 squared distances (inf where missing).
    """
    h, w, _ = features.shape
    listed = np.arange(h * w) if allowed is None else np.flatnonzero(np.asarray(allowed, bool).ravel())
    idx_out = np.full((h * w, m), -1, np.int32)
    cost_out = np.full((h * w, m), np.inf, np.float32)
    if not len(listed):
        return idx_out, cost_out
    if search in ("fast", "coherent") and h * w > FAST_BELOW:
        from .selfjoin import self_join  # the grid's own coherence proposes the matches
        mask = None if allowed is None else np.asarray(allowed, bool).ravel()
        return self_join(features, neighborhood // 2, m, exclude=exclude, allowed=mask,
                         init="tree" if search == "fast" else "random", device=device)
    vectors = neighbourhood_vectors(features, square_window(neighborhood))
    candidates = vectors if allowed is None else np.ascontiguousarray(vectors[listed])
    # the nearest entries may be the excluded texels around the texel itself: ask for that many more
    ask = min(len(listed), m + (2 * exclude + 1) ** 2 if exclude >= 0 else m)
    if device == "numpy":
        idx, cost = knn_exact_numpy(candidates, vectors, ask)
    else:
        idx, cost = knn_exact_opencl(candidates, vectors, ask)
    texel = np.where(idx >= 0, listed[np.maximum(idx, 0)], -1)
    ys, xs = np.divmod(np.arange(h * w), w)
    ty, tx = np.divmod(np.maximum(texel, 0), w)
    keep = (texel >= 0) & (np.maximum(np.abs(ty - ys[:, None]), np.abs(tx - xs[:, None])) > exclude)
    # the first m kept entries of each row, in list order
    rank = np.cumsum(keep, axis=1) - 1
    rows, cols = np.nonzero(keep & (rank < m))
    idx_out[rows, rank[rows, cols]] = texel[rows, cols]
    cost_out[rows, rank[rows, cols]] = cost[rows, cols]
    return idx_out, cost_out


# ============================================================================================ quality of the fast engine


def recall(found: np.ndarray, truth: np.ndarray) -> float:
    """Share of the true neighbours ``truth`` ``[M, k]`` that ``found`` ``[M, k]`` contains (-1 entries ignored)."""
    hits = total = 0
    for f, t in zip(found, truth):
        t = t[t >= 0]
        hits += len(np.intersect1d(f[f >= 0], t))
        total += len(t)
    return hits / total if total else 1.0


def distance_ratio(found_d: np.ndarray, true_d: np.ndarray) -> float:
    """Mean distance (not squared) of the neighbours found over that of the true ones (1 = as near)."""
    ok = np.isfinite(found_d) & np.isfinite(true_d)
    truth = np.sqrt(true_d[ok].astype(np.float64)).sum()
    return float(np.sqrt(found_d[ok].astype(np.float64)).sum() / truth) if truth > 0 else 1.0
