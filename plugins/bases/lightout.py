"""Leave-one-light-out scores of PCA light-table fits, with the table rebuilt for every light left out.

A PCA table fit (bilinear) is linear in a texel's samples once its table is fixed, but the table itself - the
mean response and the principal components over the grid - is learnt from the samples of every texel at every
light, so a light left out of the coefficients but not of the table is not really left out: the table's nodes
next to it still hold its mean response.  Rebuilding the table for each light left out costs little, because
the table needs only the first and second moments of the texels' samples: the resampled responses are ``x = R~
y`` (``R~`` the resampling ``R [D, L]`` applied to each colour component, ``y`` a texel's ``3 L`` samples), so
their mean is ``R~ mean(y)`` and their second moments about the (clipped) mean ``m`` are ``B S B^T`` for ``B = [R~,
-m]`` and ``S`` the second moments of ``z = [y; 1]``.  Leaving light ``i`` out zeroes column ``i`` of ``R`` (the
resampling of the other lights), so one ``3 L + 1`` square moment matrix serves every fold, and each fold's
components are the leading left singular vectors of ``B F`` for ``S = F F^T``: a ``3 D x (3 L + 1)`` problem
instead of one over every texel.

This judges a fit of all lights but one, as close to the final fit of every light as a held-out test can be:
folds that hold out a fifth of a dome's lights leave holes a finer grid cannot bridge, and so prefer coarse
grids that the fit of every light does not need.
"""
from __future__ import annotations

import numpy as np

from btforge.buffers import linear_to_srgb

from .lightfuncs import RGB_TO_YCC


def sample_moments(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(mean [3 L], second [3 L + 1, 3 L + 1])`` of texels' samples ``values [N, L, 3]``: the mean of ``y`` (a
    texel's samples flattened light-major) and the second moments of ``z = [y; 1]``."""
    n = len(values)
    y = np.asarray(values, np.float64).reshape(n, -1)
    z = np.concatenate([y, np.ones((n, 1))], axis=1)
    return y.mean(axis=0), z.T @ z / max(n, 1)


def _factor(second: np.ndarray) -> np.ndarray:
    """``F`` with ``F F^T = second`` (a positive semi-definite moment matrix; tiny negative eigenvalues of
    rounding are dropped)."""
    values, vectors = np.linalg.eigh(second)
    keep = values > values[-1] * 1e-12
    return vectors[:, keep] * np.sqrt(values[keep])


def _leading(basis: np.ndarray, factor: np.ndarray, count: int) -> np.ndarray:
    """The ``count`` leading unit eigenvectors ``[count, rows]`` of ``A A^T`` for ``A = basis factor``, from the
    small side (``A^T A`` has as many rows as the samples have dimensions, far fewer than the grid's).  Beyond
    the samples' rank the vectors are zero (no direction of the data is left for them)."""
    a = basis @ factor
    values, vectors = np.linalg.eigh(a.T @ a)
    top = np.argsort(values)[::-1][:count]
    u = a @ vectors[:, top]
    norms = np.linalg.norm(u, axis=0)
    kept = norms > 1e-9 * max(float(norms.max(initial=0.0)), 1e-300)
    out = np.zeros((count, len(a)))
    out[:len(top)] = np.where(kept, u / np.where(kept, norms, 1.0), 0.0).T
    return out


def place_ycc_planes(table: np.ndarray, comp: int, vectors: np.ndarray, yccplanes: tuple[int, int, int]) -> None:
    """Put YCoCg component ``comp``'s components ``vectors [count, D]`` into ``table`` in relight's plane order:
    (Y, Co, Cg) triplets while chroma planes last, then the remaining Y planes."""
    for yp in range(len(vectors)):
        p = 3 * yp + comp if yp < yccplanes[1] else 3 * yccplanes[1] + yp - yccplanes[1]
        table[p + 1, :, comp] = vectors[yp]


def moment_table(mean: np.ndarray, factors, resample: np.ndarray, planes: int, colorspace: str,
                 yccplanes: tuple[int, int, int]) -> np.ndarray:
    """The table ``[planes + 1, D, 3]`` :func:`btforge.plugins.bases.fit.pca_table` builds from the responses
    ``resample @ y`` of texels whose samples have the ``mean [3 L]`` (RGB) and the moment factors ``factors``
    (:func:`table_factors`), up to the signs of the components."""
    d, n_light = resample.shape
    if colorspace == "rgb":
        wide = np.kron(resample, np.eye(3))                                   # [3 D, 3 L]
        m = np.clip(wide @ mean, 0.0, 1.0)
        vectors = _leading(np.concatenate([wide, -m[:, None]], axis=1), factors, planes)
        return np.concatenate([m.reshape(1, d, 3), vectors.reshape(planes, d, 3)])
    ycc_mean = (mean.reshape(n_light, 3) @ RGB_TO_YCC.T)                       # [L, 3]
    table = np.zeros((planes + 1, d, 3))
    for comp, count in enumerate(yccplanes):
        m = np.clip(resample @ ycc_mean[:, comp], 0.0, 1.0)
        table[0, :, comp] = m
        vectors = _leading(np.concatenate([resample, -m[:, None]], axis=1), factors[comp], count)
        place_ycc_planes(table, comp, vectors, yccplanes)
    return table


def table_factors(second: np.ndarray, colorspace: str):
    """The moment factors :func:`moment_table` takes: of ``z = [y; 1]`` for rgb, of ``[y_c; 1]`` for each YCoCg
    component ``c`` for ycc."""
    if colorspace == "rgb":
        return _factor(second)
    n_light = (len(second) - 1) // 3
    to_ycc = np.zeros((len(second), len(second)))
    to_ycc[:-1, :-1] = np.kron(np.eye(n_light), RGB_TO_YCC)
    to_ycc[-1, -1] = 1.0
    ycc = to_ycc @ second @ to_ycc.T
    factors = []
    for comp in range(3):
        pick = np.append(np.arange(comp, 3 * n_light, 3), 3 * n_light)
        factors.append(_factor(ycc[np.ix_(pick, pick)]))
    return factors


def to_display(predicted: np.ndarray, space: str) -> np.ndarray:
    """A light-table fit's value in ``space`` as the display value its evaluation gives (clipped to [0, 1],
    then sRGB-encoded when linear)."""
    clipped = np.clip(predicted, 0.0, 1.0)
    return linear_to_srgb(clipped) if space == "linear" else clipped
