"""Appearance features for Wang-tile synthesis.

Distances between tiles' texels are taken in each representation's compressed domain, through per-texel vectors
whose Euclidean distance is the L2 distance of the texels' reflectance functions:

- a double-SH model (``SHModel.appearance_features``): its coefficients weighted by the square root of the
  Gram matrix of the SH basis over the upper hemisphere (lights and views), so ``|F(x) - F(y)|^2 = int_H int_H (f_x - f_y)^2``: the functions are
  fitted on the hemisphere only, and the orthonormality of the full-sphere basis would count the unmeasured
  lower half too;
- an orthonormal PTM, a stack, or anything else: :func:`btforge.plugins.synth.features.texel_features`
  (orthonormal Legendre coefficients, radiance, or a model evaluated at probe lights).

Each buffer class declares its vectors (``appearance_features``); this module only reduces them for the search.
"""
from __future__ import annotations

import numpy as np

from btforge.buffers import PerTexel


def appearance_features(buffer: PerTexel) -> np.ndarray:
    """Full-dimensional appearance vectors ``[H, W, D]`` float32 of any per-texel buffer: its class's own
    ``appearance_features`` (a double-SH model's are Gram-weighted, see the module docstring)."""
    from btforge.plugins.synth.features import texel_features
    return texel_features(buffer, max_dims=None)


def search_features(full: np.ndarray, dims: int, seed: int = 0) -> np.ndarray:
    """The leading ``dims`` principal components of ``full`` (an orthogonal projection: distances only shrink)."""
    from btforge.plugins.synth.features import pca_reduce
    if full.shape[2] <= dims:
        return np.ascontiguousarray(full, np.float32)
    return pca_reduce(full, dims, seed)

