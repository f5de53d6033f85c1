"""Math that several stage families share: real spherical harmonics, Fibonacci direction sets, texel chunking.

One home for each, so a fix or a speed-up lands everywhere at once.
"""
from __future__ import annotations

import math
from typing import Iterator

import numpy as np

from .errors import BtforgeInputError

FOUR_PI = 4.0 * math.pi
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))  # radians between successive points of a Fibonacci spiral


def real_sh(order: int, dirs) -> np.ndarray:
    """Orthonormal real spherical harmonics of bands ``0 .. order-1`` at ``dirs [..., 3]`` -> ``[..., order^2]``
    float64 (directions are normalised first).

    Index ``l^2 + l + m`` holds ``Y_l^m``, ``-l <= m <= l``; no Condon-Shortley phase, so band 1 is
    ``sqrt(3 / 4 pi) * (y, z, x)`` and ``Y_0 = 1 / sqrt(4 pi)``.  ``m > 0`` uses ``cos(m phi)``, ``m < 0``
    ``sin(|m| phi)``.  Computed from Cartesian coordinates (no angles), so it is exact at the poles.
    """
    if not isinstance(order, (int, np.integer)) or order < 0:
        raise BtforgeInputError("real_sh 'order'", f"must be an int >= 0, got {order!r}")
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim < 1 or d.shape[-1] != 3:
        raise BtforgeInputError("real_sh 'dirs'", f"must be (..., 3), got {d.shape}")
    lead = d.shape[:-1]
    d = d.reshape(-1, 3)
    norms = np.linalg.norm(d, axis=1, keepdims=True)
    d = d / np.where(norms > 0, norms, 1.0)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = np.zeros((d.shape[0], order * order), dtype=np.float64)
    cos_m, sin_m = np.ones_like(x), np.zeros_like(x)   # Re, Im of (x + i y)^m = sin^m(theta) e^{i m phi}
    p_mm = 1.0                                         # (2m - 1)!!: P_m^m(z) / sin^m(theta)
    for m in range(order):
        if m > 0:
            cos_m, sin_m = x * cos_m - y * sin_m, x * sin_m + y * cos_m
            p_mm *= 2 * m - 1
        p_prev, p_cur = None, np.full_like(z, p_mm)
        for l in range(m, order):
            if l == m + 1:
                p_prev, p_cur = p_cur, (2 * m + 1) * z * p_cur
            elif l > m + 1:
                p_prev, p_cur = p_cur, ((2 * l - 1) * z * p_cur - (l + m - 1) * p_prev) / (l - m)
            norm = math.sqrt((2 * l + 1) / FOUR_PI * math.factorial(l - m) / math.factorial(l + m))
            if m == 0:
                out[:, l * l + l] = norm * p_cur
            else:
                out[:, l * l + l + m] = math.sqrt(2.0) * norm * p_cur * cos_m
                out[:, l * l + l - m] = math.sqrt(2.0) * norm * p_cur * sin_m
    return out.reshape(lead + (order * order,))


def fibonacci_directions(n: int, lowest_z: float = -1.0, *, rising: bool = False, turn: float = 0.5,
                         azimuth: float = 0.0) -> np.ndarray:
    """``n`` unit directions ``[n, 3]`` float64 of a Fibonacci spiral over the cap ``z >= lowest_z``.

    Point ``i`` sits at the centre of the ``i``-th of ``n`` equal-area bands (so each stands for the same solid
    angle), from the pole down (``rising``: from the cap's edge up), at azimuth ``(i + turn)`` golden angles plus
    ``azimuth`` radians.
    """
    i = np.arange(int(n), dtype=np.float64)
    t = (i + 0.5) / max(int(n), 1)
    z = lowest_z + (1.0 - lowest_z) * t if rising else 1.0 - (1.0 - lowest_z) * t
    phi = (i + turn) * GOLDEN_ANGLE + azimuth
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1)


def texel_chunks(n_texels: int, bytes_per_texel: int, budget_bytes: int = 256 << 20) -> Iterator[slice]:
    """Split ``range(n_texels)`` into slices whose working set stays under ``budget_bytes``."""
    step = max(1, min(n_texels, budget_bytes // max(1, bytes_per_texel)))
    for start in range(0, n_texels, step):
        yield slice(start, min(n_texels, start + step))
