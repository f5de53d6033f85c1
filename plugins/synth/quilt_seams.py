"""Joining quilted blocks: the minimum-error boundary cut through an overlap, or linear blending across it."""
from __future__ import annotations

import numpy as np


def min_cut(err: np.ndarray) -> np.ndarray:
    """Minimum-error path down the rows of ``err [rows, width]``: one column per row, moving at most one per row.

    Plain Python dynamic programming: overlap strips are a few texels wide, where this beats array operations.
    Ties go to the smallest column.
    """
    n, w = err.shape
    if w == 1:
        return np.zeros(n, np.int64)
    rows = err.tolist()
    cost = rows[0]
    back = []
    for y in range(1, n):
        row = rows[y]
        new = [0.0] * w
        choice = [0] * w
        for x in range(w):
            best_x = x - 1 if x and cost[x - 1] <= cost[x] else x
            if x + 1 < w and cost[x + 1] < cost[best_x]:
                best_x = x + 1
            new[x] = row[x] + cost[best_x]
            choice[x] = best_x
        cost = new
        back.append(choice)
    x = min(range(w), key=cost.__getitem__)
    path = [x]
    for choice in reversed(back):
        x = choice[x]
        path.append(x)
    return np.array(path[::-1], np.int64)


def cut_mask(err: np.ndarray, key: tuple[int, int, int, int]) -> np.ndarray:
    """Boolean ``[B, B]``: True where the new block shows, from a minimum-error cut through each overlap strip.

    Vertical cuts run through the left/right strips and horizontal ones through the top/bottom strips; a texel
    shows the new block when it lies on the new block's side of every cut (in corners that is the intersection).
    """
    t, b, l, r = key
    size = err.shape[0]
    ar = np.arange(size)
    mask = np.ones((size, size), bool)
    if l:
        mask &= ar[None, :] >= min_cut(err[:, :l])[:, None]
    if r:
        mask &= ar[None, :] <= (size - 1 - min_cut(err[:, size - r:][:, ::-1]))[:, None]
    if t:
        mask &= ar[:, None] >= min_cut(err[:t, :].T)[None, :]
    if b:
        mask &= ar[:, None] <= (size - 1 - min_cut(err[size - b:, :][::-1].T))[None, :]
    return mask


def blend_alpha(size: int, key: tuple[int, int, int, int]) -> np.ndarray:
    """Weight ``[B, B]`` of the new block: linear ramps across each overlap strip, 1 outside them."""
    t, b, l, r = key
    ar = np.arange(size, dtype=np.float64)
    ramp_x = np.ones(size)
    ramp_y = np.ones(size)
    if l:
        ramp_x = np.minimum(ramp_x, np.minimum((ar + 1) / (l + 1), 1))
    if r:
        ramp_x = np.minimum(ramp_x, np.minimum((size - ar) / (r + 1), 1))
    if t:
        ramp_y = np.minimum(ramp_y, np.minimum((ar + 1) / (t + 1), 1))
    if b:
        ramp_y = np.minimum(ramp_y, np.minimum((size - ar) / (b + 1), 1))
    return (ramp_y[:, None] * ramp_x[None, :]).astype(np.float32)


def _span(start: int, block: int, n: int):
    return slice(start, start + block) if start + block <= n else (start + np.arange(block)) % n


def _region(rows, cols):
    if isinstance(rows, slice) and isinstance(cols, slice):
        return rows, cols
    as_index = [np.arange(s.start, s.stop) if isinstance(s, slice) else s for s in (rows, cols)]
    return np.ix_(*as_index)
