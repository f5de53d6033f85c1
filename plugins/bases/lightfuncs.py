"""How each basis turns a light direction into weights over its light table, and the luma-chroma transform.

Every basis here is *linear in a light table*: a table ``T [P + 1, D, 3]`` (row 0 the mean response, row
``p + 1`` plane ``p``'s response, over ``D`` table directions and 3 colour components) and a weight function
``w(l) -> [D]``.  The relit display value of a texel with coefficients ``c [P]`` is
``(w(l) @ T)[0] + sum_p c[p] (w(l) @ T)[p + 1]``, then converted from the table's colour space to RGB.

- ``hsh``: ``D`` = the 4 or 9 hemispherical harmonics, ``w(l)`` their values (the HSH functions RTI viewers use,
  :func:`btforge.plugins.web.hsh.hsh_basis`), and the table selects one (term, channel) per plane;
- ``rbf``: ``D`` = the capture's lights, ``w(l)`` normalised Gaussian weights ``exp(-|l - l_i|^2 / sigma^2)``
  (weights below 0.001 of the total dropped and the rest renormalised, as relight does);
- ``bilinear``: ``D`` = a ``resolution x resolution`` grid over the octahedral map of the hemisphere, ``w(l)``
  the four bilinear weights of the cell holding ``l``'s octahedral coordinates.
"""
from __future__ import annotations

import numpy as np

from btforge.plugins.web.hsh import hsh_basis

RBF_DROP = 0.001      # relight drops interpolation weights below this share of the total, then renormalises
RESAMPLE_DROP = 0.005  # ... and, building the bilinear grid, weights below this share
MEAN_PULL = 1e-4      # smooth resampling: weight pulling every grid node towards the texel's mean response

# ridge on the slope of the spline's affine part: the same as adding the linear kernel l.l' / SLOPE_RIDGE to the
# polyharmonic one (at most 8 for the cubic): a slope the lights determine stays, one a tight cluster of
# lights would extrapolate from their noise shrinks
SLOPE_RIDGE = 1e-2

# YCoCg (relight's and OpenLIME's "ycc"): Y = (r + 2g + b) / 4, Co = r - b, Cg = g - (r + b) / 2.
RGB_TO_YCC = np.array([[0.25, 0.5, 0.25], [1.0, 0.0, -1.0], [-0.5, 1.0, -0.5]])
YCC_TO_RGB = np.linalg.inv(RGB_TO_YCC)


def colour_matrix(colorspace: str) -> np.ndarray:
    """``M [3, 3]`` taking the table's colour components to RGB: identity for rgb, YCoCg -> RGB for ycc."""
    return YCC_TO_RGB if colorspace == "ycc" else np.eye(3)


def rbf_weights(lights: np.ndarray, table_lights: np.ndarray, sigma: float) -> np.ndarray:
    """Normalised Gaussian weights ``[L, D]`` of query ``lights [L, 3]`` over ``table_lights [D, 3]``.

    Computed relative to the nearest table light, so a query far from every table light (where every plain
    ``exp`` underflows) still gets finite weights, all on its nearest lights.
    """
    q = np.asarray(lights, np.float64)
    t = np.asarray(table_lights, np.float64)
    d2 = (q * q).sum(1)[:, None] + (t * t).sum(1)[None, :] - 2.0 * q @ t.T
    d2 = np.maximum(d2, 0.0)
    w = np.exp(-(d2 - d2.min(axis=1, keepdims=True)) / (sigma * sigma))
    w /= w.sum(axis=1, keepdims=True)
    w = np.where(w > RBF_DROP, w, 0.0)
    return w / w.sum(axis=1, keepdims=True)


def octa_coordinates(lights: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous grid coordinates ``(x, y)`` in ``[0, resolution - 1]`` of ``lights [L, 3]`` on the octahedral
    map rotated by 45 degrees (relight's layout: the hemisphere fills the square)."""
    d = np.asarray(lights, np.float64)
    z = np.maximum(d[:, 2], 0.0)
    s = np.abs(d[:, 0]) + np.abs(d[:, 1]) + z
    s = np.where(s > 0, s, 1.0)
    x = ((d[:, 0] + d[:, 1]) / s + 1.0) * 0.5 * (resolution - 1)
    y = ((d[:, 1] - d[:, 0]) / s + 1.0) * 0.5 * (resolution - 1)
    return np.clip(x, 0, resolution - 1), np.clip(y, 0, resolution - 1)


def octa_directions(resolution: int) -> np.ndarray:
    """The unit directions ``[resolution^2, 3]`` of the grid nodes (node ``x + y * resolution``)."""
    g = np.arange(resolution) * 2.0 / (resolution - 1) - 1.0
    ox, oy = np.meshgrid(g, g)                      # ox varies along x (columns), oy along y (rows)
    x, y = (ox - oy) / 2.0, (ox + oy) / 2.0
    d = np.stack([x, y, np.maximum(1.0 - np.abs(x) - np.abs(y), 0.0)], axis=-1).reshape(-1, 3)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def bilinear_weights(lights: np.ndarray, resolution: int) -> np.ndarray:
    """Weights ``[L, resolution^2]`` of ``lights`` over the grid nodes: bilinear in the octahedral map."""
    x, y = octa_coordinates(lights, resolution)
    sx = np.clip(np.floor(x), 0, resolution - 2).astype(np.int64)
    sy = np.clip(np.floor(y), 0, resolution - 2).astype(np.int64)
    dx, dy = x - sx, y - sy
    w = np.zeros((len(x), resolution * resolution))
    rows = np.arange(len(x))
    for ox, oy, share in ((0, 0, (1 - dx) * (1 - dy)), (1, 0, dx * (1 - dy)), (0, 1, (1 - dx) * dy), (1, 1, dx * dy)):
        np.add.at(w, (rows, (sx + ox) + (sy + oy) * resolution), share)
    return w


def resample_matrix(lights: np.ndarray, resolution: int, sigma: float, regularization: float) -> np.ndarray:
    """``R [resolution^2, L]``: a capture's samples at ``lights`` resampled onto the grid nodes.

    As relight builds it: ``R = B + (A^T A + k I)^-1 A^T (I - A B)``, with ``B`` the Gaussian (RBF) interpolation
    from the lights to the nodes and ``A`` the bilinear interpolation from the nodes back to the lights, i.e.
    the grid whose bilinear interpolation best reproduces the samples, pulled towards the RBF estimate by
    ``k = regularization`` where the lights leave nodes undetermined.
    """
    b = rbf_weights(octa_directions(resolution), lights, sigma)
    b = np.where(b > RESAMPLE_DROP, b, 0.0)
    b /= b.sum(axis=1, keepdims=True)
    a = bilinear_weights(lights, resolution)
    n = resolution * resolution
    inverse = np.linalg.inv(a.T @ a + regularization * np.eye(n))
    return b + inverse @ (a.T @ (np.eye(len(lights)) - a @ b))


def grid_laplacian(resolution: int) -> np.ndarray:
    """The 4-neighbour graph Laplacian ``[n, n]`` of the ``resolution x resolution`` grid (free borders)."""
    n = resolution * resolution
    lap = np.zeros((n, n))
    for y in range(resolution):
        for x in range(resolution):
            i = x + y * resolution
            for nx, ny in ((x + 1, y), (x - 1, y), (x, y + 1), (x, y - 1)):
                if 0 <= nx < resolution and 0 <= ny < resolution:
                    lap[i, i] += 1.0
                    lap[i, nx + ny * resolution] -= 1.0
    return lap


def smooth_resample_matrix(lights: np.ndarray, resolution: int, smoothness: float) -> np.ndarray:
    """``R [resolution^2, L]``: the grid whose bilinear interpolation best reproduces the samples at ``lights``
    while bending least, ``argmin |A g - y|^2 + smoothness |Lap g|^2 + MEAN_PULL |g - mean(y)|^2`` (a thin plate
    through the samples).
    Nodes no light reaches take the smooth continuation of their neighbours, where relight's Gaussian pull
    (:func:`resample_matrix`) leaves them at a local average - a visible error between rings of lights."""
    a = bilinear_weights(lights, resolution)
    lap = grid_laplacian(resolution)
    n = resolution * resolution
    # A faint pull (MEAN_PULL) of every node towards the texel's mean response keeps nodes far from clustered
    # lights from extrapolating without bound; a constant response still gives the constant grid exactly.
    system = a.T @ a + smoothness * lap.T @ lap + MEAN_PULL * np.eye(n)
    return np.linalg.solve(system, a.T + MEAN_PULL / len(lights))


def _polyharmonic(a: np.ndarray, b: np.ndarray, power: int) -> np.ndarray:
    """The polyharmonic kernel ``|a_i - b_j|^power`` ``[A, B]`` between unit directions (chordal distance)."""
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
    return np.maximum(d2, 0.0) ** (0.5 * power)


def _unit(directions: np.ndarray) -> np.ndarray:
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.where(norm > 0, norm, 1.0)


def spline_inverse(lights: np.ndarray, smoothness: float, power: int = 3) -> np.ndarray:
    """``[L + 4, L]``: the spline's kernel and affine coefficients per sample (see :func:`spline_weights`)."""
    light = _unit(lights)
    n = len(light)
    poly = np.c_[np.ones(n), light]
    system = np.zeros((n + 4, n + 4))
    system[:n, :n] = _polyharmonic(light, light, power) + smoothness * np.eye(n)
    system[:n, n:] = poly
    system[n:, :n] = poly.T
    system[n + 1:, n + 1:] = -SLOPE_RIDGE * np.eye(3)
    return np.linalg.pinv(system, rcond=1e-10, hermitian=True)[:, :n]


def spline_weights(lights: np.ndarray, queries: np.ndarray, smoothness: float, power: int = 3,
                   inverse: np.ndarray | None = None) -> np.ndarray:
    """``S [Q, L]``: the smoothing spline through samples at ``lights`` evaluated at ``queries`` (``S @ y``).

    A polyharmonic spline over the unit directions (kernel ``|l - l_i|^power``, the chordal distance; the
    cubic by default) plus an affine function of the direction, minimising its bending energy plus
    ``1 / smoothness`` times the squared misfit at the lights.  An affine response (Lambertian shading of a lit
    texel in linear radiance) is reproduced exactly; between and beyond the lights the spline continues as
    smoothly as it can, on the sphere itself, so its values at grid nodes do not depend on where the grid lines
    fall.  The affine part's slope carries a faint ridge (:data:`SLOPE_RIDGE`): where the lights leave it
    undetermined (all on one ring, or in one tight cluster) it is flat instead of a ramp extrapolated without
    bound.  ``inverse``: the lights' own
    :func:`spline_inverse`, when several sets of queries share it.
    """
    if inverse is None:
        inverse = spline_inverse(lights, smoothness, power)
    query = _unit(queries)
    return np.c_[_polyharmonic(query, _unit(lights), power), np.ones(len(query)), query] @ inverse


def table_weights(kind: str, lights: np.ndarray, *, terms: int = 9, table_lights: np.ndarray | None = None,
                  sigma: float = 0.125, resolution: int = 8) -> np.ndarray:
    """``w(l) [L, D]`` of basis ``kind`` at unit ``lights [L, 3]``."""
    if kind == "hsh":
        return hsh_basis(lights, terms)
    if kind == "rbf":
        return rbf_weights(lights, table_lights, sigma)
    return bilinear_weights(lights, resolution)
