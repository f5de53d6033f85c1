"""Scan order of pixel-by-pixel synthesis: wavefronts, output neighbours, window order, pyramid sizes, coherence.

Causal synthesis visits pixels in anti-diagonal wavefronts ``x + step * y = t``: a pixel needs only pixels of
earlier wavefronts, so one wavefront is synthesized in parallel.  These helpers are the one definition the
synthesizers' kernels and NumPy twins follow.
"""
from __future__ import annotations

import numpy as np


def search_offsets(radius: int) -> np.ndarray:
    """Window offsets ``[(2r+1)^2, 2]`` (dy, dx), centre first, then by growing distance (early termination)."""
    dy, dx = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    offs = np.column_stack([dy.ravel(), dx.ravel()])
    order = np.lexsort((offs[:, 1], offs[:, 0], np.abs(offs).max(axis=1), (offs ** 2).sum(axis=1)))
    return offs[order].astype(np.int32)


def pad_textons(labels: np.ndarray, pad: int) -> np.ndarray:
    """The texton map edge-extended by ``pad`` texels on every side (int32, C-contiguous)."""
    return np.ascontiguousarray(np.pad(labels, pad, mode="edge"), dtype=np.int32)


def level_sizes(height: int, width: int, levels: int) -> list[tuple[int, int]]:
    """Sizes of a pyramid, finest first: each level half the previous, rounded up."""
    return [(-(-height // 2 ** l), -(-width // 2 ** l)) for l in range(levels)]


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


def hilbert_curve(side: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of the Hilbert curve over a ``side x side`` square (side a power of two), in the curve's
    order: it starts at (0, 0), ends at (0, side - 1), and each step moves to a 4-neighbour."""
    t = np.arange(side * side, dtype=np.int64)
    y = np.zeros_like(t)
    x = np.zeros_like(t)
    s = 1
    while s < side:
        rx = (t // 2) & 1
        ry = (t ^ rx) & 1
        flip = (ry == 0) & (rx == 1)
        x, y = np.where(flip, s - 1 - x, x), np.where(flip, s - 1 - y, y)
        x, y = np.where(ry == 0, y, x), np.where(ry == 0, x, y)
        x, y = x + s * rx, y + s * ry
        t //= 4
        s *= 2
    return y, x


def hilbert_order(ho: int, wo: int) -> np.ndarray:
    """Flat indices of an ``ho x wo`` grid in Hilbert-curve order: squares as wide as the shorter side (rounded up
    to a power of two), one after another along the longer side, each walked by :func:`hilbert_curve` (turned so
    that it ends beside the next square); texels past the grid are skipped."""
    side = 1 << max(0, (min(ho, wo) - 1).bit_length())
    y, x = hilbert_curve(side)
    if ho > wo:
        y, x = x, y   # ends at (side - 1, 0), above the next square
    squares = np.arange(-(-max(ho, wo) // side))[:, None] * side
    ys = (y[None] + squares * (ho > wo)).ravel()
    xs = (x[None] + squares * (ho <= wo)).ravel()
    keep = (ys < ho) & (xs < wo)
    return (ys[keep] * wo + xs[keep]).astype(np.int32)
