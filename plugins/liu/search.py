"""Nearest-neighbour search with the signature of the shared synthesis search (issue 10's
``plugins/synth/search.py``), which replaces this module at merge: scipy's cKDTree, or brute force."""
from __future__ import annotations

import numpy as np

FAST_EPS = 1.0


def knn(exemplar: np.ndarray, queries: np.ndarray, k: int, *, engine: str = "fast") -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` rows of ``exemplar (N, D)`` nearest to each row of ``queries (M, D)``, nearest first:
    ``(indices (M, k) int64, squared_distances (M, k) float32)``.  ``engine``: ``fast`` (k-d tree) or ``exact``
    (all pairs, chunked).  ``fast`` is (1 + ``FAST_EPS``)-approximate: each neighbour it returns is at most that
    factor farther than the true one (k-d trees in 8-10 dimensions spend most of their time proving the last
    few percent)."""
    exemplar = np.ascontiguousarray(exemplar, np.float32)
    queries = np.ascontiguousarray(queries, np.float32)
    k = int(min(k, len(exemplar)))
    if engine == "fast":
        from scipy.spatial import cKDTree
        d, i = cKDTree(exemplar).query(queries, k=k, eps=FAST_EPS)
        d, i = np.asarray(d).reshape(len(queries), k), np.asarray(i).reshape(len(queries), k)
        return i.astype(np.int64), (d * d).astype(np.float32)
    if engine != "exact":
        raise ValueError(f"engine must be 'fast' or 'exact', got {engine!r}")
    norms = (exemplar.astype(np.float64) ** 2).sum(1)
    out_i = np.empty((len(queries), k), np.int64)
    out_d = np.empty((len(queries), k), np.float32)
    for start in range(0, len(queries), 1024):
        q = queries[start:start + 1024].astype(np.float64)
        d = np.maximum(norms[None] - 2 * np.einsum("md,nd->mn", q, exemplar) + (q * q).sum(1)[:, None], 0)
        part = np.argpartition(d, k - 1, axis=1)[:, :k] if k < d.shape[1] else np.tile(np.arange(d.shape[1]), (len(q), 1))
        order = np.take_along_axis(d, part, 1).argsort(1, kind="stable")
        out_i[start:start + len(q)] = np.take_along_axis(part, order, 1)
        out_d[start:start + len(q)] = np.take_along_axis(d, out_i[start:start + len(q)], 1)
    return out_i, out_d
