"""Where a surface sample reads its texture: the bilinear texel corners of a UV position, with wrapping."""
from __future__ import annotations

import numpy as np

SNAP = 1e-3            # texel-coordinate fractions this close to a texel centre are snapped onto it


def _wrap(i: np.ndarray, n: int, mode: str) -> np.ndarray:
    if mode == "repeat":
        return np.mod(i, n)
    if mode == "clamp":
        return np.clip(i, 0, n - 1)
    m = np.mod(i, 2 * n)
    return np.where(m < n, m, 2 * n - 1 - m)


def texel_corners(uv: np.ndarray, height: int, width: int, wrap: str):
    """Bilinear lookup on an ``height x width`` texel grid: ``rows, cols [4, N]`` int64 and ``weights [4, N]``.

    Texel ``(r, c)`` has its centre at ``u = (c + 0.5) / width``, ``v = 1 - (r + 0.5) / height`` (row 0 at the top).
    Fractions within :data:`SNAP` of a texel centre are snapped onto it, so a texel centre reads that texel alone.
    """
    x = uv[:, 0] * width - 0.5
    y = (1.0 - uv[:, 1]) * height - 0.5
    corners = []
    for t in (x, y):
        t0 = np.floor(t)
        f = t - t0
        up = f > 1 - SNAP
        t0 = np.where(up, t0 + 1, t0)
        f = np.where(up | (f < SNAP), 0.0, f)
        corners.append((t0.astype(np.int64), f))
    (x0, fx), (y0, fy) = corners
    cols = np.stack([x0, x0 + 1, x0, x0 + 1])
    rows = np.stack([y0, y0, y0 + 1, y0 + 1])
    weights = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    return _wrap(rows, height, wrap), _wrap(cols, width, wrap), weights
