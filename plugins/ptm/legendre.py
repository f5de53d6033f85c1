"""PTM coefficients in an orthonormal 2D Legendre basis over [-1, 1]^2 (Hel-Or, Malzbender & Gelb 2003).

In this basis the Euclidean distance between two texels' coefficient vectors equals the L2 distance between
their reflectance functions over the square, and blending coefficients blends the functions - which is what
block synthesis needs to compare and join texels meaningfully.

The orthonormal functions are products of normalised Legendre polynomials of total degree <= 2::

    psi = (1/2, (sqrt3/2) u, (sqrt3/2) v, (3/2) u v, (sqrt45/4) u^2 - sqrt45/12, (sqrt45/4) v^2 - sqrt45/12)

Writing each psi_j in the raw PTM terms t = (u^2, v^2, uv, u, v, 1) as ``psi = R t`` gives
``f = b . psi = (R^T b) . t``, so raw coefficients are ``a = R^T b`` and orthonormal ones ``b = R^{-T} a``.
(The paper prints R itself as the coefficient map; that matrix transforms the basis, not the coefficients,
and fails the isometry test in ``tests/test_ptm_basis.py``.)
"""
from __future__ import annotations

import numpy as np

_S3 = np.sqrt(3.0)
_S45 = np.sqrt(45.0)

# Rows: orthonormal functions; columns: raw terms (u^2, v^2, uv, u, v, 1).
BASIS_IN_RAW_TERMS = np.array([
    [0, 0, 0, 0, 0, 0.5],
    [0, 0, 0, _S3 / 2, 0, 0],
    [0, 0, 0, 0, _S3 / 2, 0],
    [0, 0, 1.5, 0, 0, 0],
    [_S45 / 4, 0, 0, 0, 0, -_S45 / 12],
    [0, _S45 / 4, 0, 0, 0, -_S45 / 12],
])

RAW_FROM_ORTHONORMAL = BASIS_IN_RAW_TERMS.T                    # a = R^T b
ORTHONORMAL_FROM_RAW = np.linalg.inv(RAW_FROM_ORTHONORMAL)     # b = R^{-T} a


def to_orthonormal(raw: np.ndarray) -> np.ndarray:
    """Raw PTM coefficients ``[..., 6]`` -> orthonormal Legendre coefficients ``[..., 6]`` (float32)."""
    return np.einsum("ji,...i->...j", ORTHONORMAL_FROM_RAW, raw.astype(np.float64)).astype(np.float32)


def to_raw(orthonormal: np.ndarray) -> np.ndarray:
    """Orthonormal Legendre coefficients ``[..., 6]`` -> raw PTM coefficients ``[..., 6]`` (float32)."""
    return np.einsum("ji,...i->...j", RAW_FROM_ORTHONORMAL, orthonormal.astype(np.float64)).astype(np.float32)
