"""The block search of Liu's block copy: one index per reference and block size, queried once per round.

``fast`` keeps a scipy cKDTree over the blocks' leading principal components, built once and queried many
times; it is (1 + ``FAST_EPS``)-approximate: each neighbour it returns is at most that factor farther than the
true one (k-d trees in 8 dimensions spend most of their time proving the last few percent).  ``exact`` is the
shared search's OpenCL brute force (:func:`btforge.plugins.synth.search.knn`).

Why not the shared ``fast`` engine: the block copy builds a fresh index for every warped reference and block
size (~30 000 8-D vectors) and then asks it ~100 small batches of queries.  Measured on this machine
(30 000 x 8, 250 queries per batch): cKDTree builds in 0.01 s and answers a batch in 0.002 s CPU; the shared
HNSW index takes 1.2 s to build and 0.008 s per batch, and the exact OpenCL search 0.08 s per batch.  The shared
engines pay off when one exemplar is searched by very many queries, which is not this case.
"""
from __future__ import annotations

import numpy as np

FAST_EPS = 1.0
PARALLEL_QUERIES = 2000   # batches at least this large are searched on every core (smaller: threads cost more)
ENGINES = ("fast", "exact")


class BlockIndex:
    """Nearest rows of ``vectors (N, D)`` float32 for many batches of queries, with ``engine`` ``fast`` or
    ``exact`` (see module)."""

    def __init__(self, vectors: np.ndarray, engine: str = "fast"):
        if engine not in ENGINES:
            raise ValueError(f"engine must be 'fast' or 'exact', got {engine!r}")
        self.vectors = np.ascontiguousarray(vectors, np.float32)
        self.engine = engine
        self._tree = None
        if engine == "fast":
            from scipy.spatial import cKDTree
            # sliding-midpoint splits (not medians): built in about half the time, searched as fast on these blocks
            self._tree = cKDTree(self.vectors, balanced_tree=False)

    def query(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(indices (M, k) int64, squared_distances (M, k) float32)`` of the ``k`` nearest rows, nearest
        first (``k`` is cut to the number of rows)."""
        queries = np.ascontiguousarray(queries, np.float32)
        k = int(min(k, len(self.vectors)))
        if self._tree is None:
            from btforge.plugins.synth.search import knn
            return knn(self.vectors, queries, k, engine="exact")
        workers = -1 if len(queries) >= PARALLEL_QUERIES else 1
        d, i = self._tree.query(queries, k=k, eps=FAST_EPS, workers=workers)
        d, i = np.asarray(d).reshape(len(queries), k), np.asarray(i).reshape(len(queries), k)
        return i.astype(np.int64), (d * d).astype(np.float32)
