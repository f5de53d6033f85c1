"""Appearance features for Wang-tile synthesis.

Distances between tiles' texels are taken in each representation's compressed domain, through per-texel vectors
whose Euclidean distance is the L2 distance of the texels' reflectance functions:

- a double-SH model: its coefficients weighted by the square root of the Gram matrix of the SH basis over the
  upper hemisphere (lights and views), so ``|F(x) - F(y)|^2 = int_H int_H (f_x - f_y)^2``: the functions are
  fitted on the hemisphere only, and the orthonormality of the full-sphere basis would count the unmeasured
  lower half too;
- an orthonormal PTM, a stack, or anything else: :func:`btforge.plugins.synth.features.texel_features`
  (orthonormal Legendre coefficients, radiance, or a model evaluated at probe lights).

A buffer class that defines ``appearance_features()`` (the method issue 9 puts on every per-texel class) is
asked first, so once the classes carry it this module only adds the SH weighting until SHModel has its own.
"""
from __future__ import annotations

import numpy as np

from btforge.buffers import PerTexel

GRAM_QUADRATURE = 4096  # hemisphere directions of the Gram-matrix quadrature


def hemisphere_gram(order: int, n: int = GRAM_QUADRATURE) -> np.ndarray:
    """``int_H Y_i Y_j`` over the upper hemisphere for SH bands ``0 .. order-1``: ``[order^2, order^2]`` float64.

    A Fibonacci spiral of ``n`` equal-area points over the hemisphere (weight ``2 pi / n`` each).
    """
    from btforge.plugins.sh.model import real_sh
    i = np.arange(n) + 0.5
    z = i / n
    phi = i * np.pi * (3 - np.sqrt(5))
    r = np.sqrt(1 - z * z)
    y = real_sh(order, np.column_stack([r * np.cos(phi), r * np.sin(phi), z]))
    return (y.T @ y) * (2 * np.pi / n)


def _sqrt_psd(gram: np.ndarray) -> np.ndarray:
    """``S`` with ``S S^T = gram`` (symmetric square root, negative rounding clipped)."""
    values, vectors = np.linalg.eigh(gram)
    return vectors * np.sqrt(np.clip(values, 0.0, None))


def sh_gram_features(model) -> np.ndarray:
    """``[H, W, C * k_v * k_l]`` float32 coefficients of a double-SH model in a hemisphere-orthonormal frame."""
    coeffs = model.dequantized().astype(np.float64)                     # [H, W, C, k_v, k_l]
    s_light = _sqrt_psd(hemisphere_gram(model.light_order))
    s_view = _sqrt_psd(hemisphere_gram(model.view_order))
    weighted = np.einsum("hwcab,ai,bj->hwcij", coeffs, s_view, s_light)
    return np.ascontiguousarray(weighted.reshape(model.height, model.width, -1), np.float32)


def appearance_features(buffer: PerTexel) -> np.ndarray:
    """Full-dimensional appearance vectors ``[H, W, D]`` float32 of any per-texel buffer (module docstring)."""
    from btforge.plugins.sh.model import SHModel
    from btforge.plugins.synth.features import texel_features
    own = getattr(type(buffer), "appearance_features", None)
    if own is not None and not isinstance(buffer, SHModel):
        return np.ascontiguousarray(own(buffer), np.float32)
    if isinstance(buffer, SHModel):
        return sh_gram_features(buffer)
    return texel_features(buffer, max_dims=None)


def search_features(full: np.ndarray, dims: int, seed: int = 0) -> np.ndarray:
    """The leading ``dims`` principal components of ``full`` (an orthogonal projection: distances only shrink)."""
    from btforge.plugins.synth.features import pca_reduce
    if full.shape[2] <= dims:
        return np.ascontiguousarray(full, np.float32)
    return pca_reduce(full, dims, seed)

