"""Minimum cuts on pixel grids with ``scipy.sparse.csgraph.maximum_flow`` (BSD; never PyMaxflow).

A cut separates an ``h x w`` window into pixels that keep the *old* content (source side) and pixels that take
the *new* one (sink side).  The edge between 4-neighbours ``s, t`` costs Kwatra et al.'s (2003) matching cost
``|A(s) - B(s)| + |A(t) - B(t)|`` (``A`` old, ``B`` new): what a seam between them would show.  Pixels marked
``keep`` are tied to the source and ``take`` to the sink with capacities no cut can afford.
"""
from __future__ import annotations

import numpy as np

from btforge.lazy import lazy_module

sparse = lazy_module("scipy.sparse")
csgraph = lazy_module("scipy.sparse.csgraph")

CAPACITY_SCALE = 1 << 16   # the largest finite edge maps to this many integer units (maximum_flow takes int32)
TIED = 1 << 30             # the capacity of a terminal tie


def grid_edges(shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices ``(s, t)`` of every horizontal and vertical 4-neighbour pair of an ``h x w`` grid."""
    h, w = shape
    index = np.arange(h * w).reshape(h, w)
    s = np.concatenate([index[:, :-1].ravel(), index[:-1, :].ravel()])
    t = np.concatenate([index[:, 1:].ravel(), index[1:, :].ravel()])
    return s, t


def min_cut(difference: np.ndarray, keep: np.ndarray, take: np.ndarray) -> tuple[np.ndarray, float]:
    """The cheapest split of a window: ``(new [h, w] bool, cost)``.

    ``difference [h, w]`` is ``|A - B|`` per pixel; ``keep`` / ``take`` are the pixels tied to the old / new
    side (a pixel in both counts as kept).  ``cost`` is the summed matching cost of the neighbour pairs the cut
    separates, in the units of ``difference``.
    """
    flat = np.asarray(difference, np.float64).ravel()
    s, t = grid_edges(difference.shape)
    return min_cut_edges(difference.shape, flat[s] + flat[t], keep, take)


def min_cut_edges(shape: tuple[int, int], cost: np.ndarray, keep: np.ndarray, take: np.ndarray) -> tuple[np.ndarray, float]:
    """:func:`min_cut` with the cost of each neighbour pair of :func:`grid_edges` given directly."""
    h, w = shape
    n = h * w
    s, t = grid_edges((h, w))
    cost = np.asarray(cost, np.float64)
    top = cost.max() if cost.size else 0.0
    scale = CAPACITY_SCALE / top if top > 0 else 0.0
    cap = np.rint(cost * scale).astype(np.int64) + 1       # +1: a free edge still counts, so ties cut short
    keep_flat, take_flat = np.asarray(keep).ravel(), np.asarray(take).ravel() & ~np.asarray(keep).ravel()
    source, sink = n, n + 1
    rows = [s, t, np.full(keep_flat.sum(), source), np.flatnonzero(take_flat)]
    cols = [t, s, np.flatnonzero(keep_flat), np.full(take_flat.sum(), sink)]
    caps = [cap, cap, np.full(keep_flat.sum(), TIED), np.full(take_flat.sum(), TIED)]
    graph = sparse.csr_matrix((np.concatenate(caps).astype(np.int32), (np.concatenate(rows), np.concatenate(cols))),
                              shape=(n + 2, n + 2))
    flow = csgraph.maximum_flow(graph, source, sink).flow
    residual = (graph - flow).tocsr()
    residual.data = np.where(residual.data > 0, 1, 0).astype(np.int32)
    residual.eliminate_zeros()
    reached = csgraph.breadth_first_order(residual, source, directed=True, return_predecessors=False)
    old = np.zeros(n + 2, bool)
    old[reached] = True
    new = ~old[:n]
    separated = old[s] != old[t]
    return new.reshape(h, w), float(cost[separated].sum())
