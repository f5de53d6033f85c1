"""Per-texel appearance vectors that synthesizers compare: one entry point shared by every synthesizer.

Each buffer class says what its appearance vectors are (``appearance_features``), so that distances between
them approximate L2 distances between the texels' reflectance functions: a PTM gives its orthonormal Legendre
coefficients (Hel-Or et al. 2003), a stack its radiance under every light and view, any other reflectance model
its values at a fixed set of lights spread over the hemisphere, and other per-texel buffers their records.

Long vectors are reduced by PCA (an orthogonal projection, so distances shrink only by the discarded energy).
"""
from __future__ import annotations

import numpy as np

from btforge.buffers import APPEARANCE_PROBE_LIGHTS, Buffer, appearance_probe_lights

FEATURE_LIGHTS = APPEARANCE_PROBE_LIGHTS  # lights at which models of unknown form are sampled


def probe_lights(n: int = FEATURE_LIGHTS) -> np.ndarray:
    """``n`` unit directions spread over the upper hemisphere (a Fibonacci spiral above 10 degrees)."""
    return appearance_probe_lights(n)


def texel_features(buffer: Buffer, max_dims: int | None = 32, seed: int = 0) -> np.ndarray:
    """Appearance vectors ``[H, W, D]`` float32 of any per-texel buffer (see the module docstring)."""
    features = np.ascontiguousarray(buffer.appearance_features(), dtype=np.float32)
    if max_dims is not None and features.shape[2] > max_dims:
        features = pca_reduce(features, max_dims, seed)
    return features


def pca_reduce(features: np.ndarray, dims: int, seed: int = 0, sample: int = 20000) -> np.ndarray:
    """Project ``[H, W, D]`` vectors onto their ``dims`` leading principal axes (fitted on a texel sample)."""
    h, w, d = features.shape
    flat = features.reshape(-1, d).astype(np.float64)
    rng = np.random.default_rng(seed)
    pick = flat if len(flat) <= sample else flat[rng.choice(len(flat), sample, replace=False)]
    mean = pick.mean(axis=0)
    # Principal axes from the small D x D covariance: cheaper and steadier than an SVD of the samples.
    centred = pick - mean
    eigenvalues, axes = np.linalg.eigh(centred.T @ centred)
    dims = min(dims, len(pick))  # a tiny exemplar has fewer axes than asked for
    leading = axes[:, ::-1][:, :dims]
    return ((flat - mean) @ leading).astype(np.float32).reshape(h, w, dims)


def downsample(image: np.ndarray, mode: str = "mirror") -> np.ndarray:
    """One Gaussian-pyramid step of ``[H, W, ...]``: a 5-tap binomial blur, then every second texel (half the
    size, rounded up), float32.

    ``mode`` is how the blur continues past the edges (:func:`scipy.ndimage.convolve1d`): ``mirror`` or
    ``reflect`` for an exemplar, ``wrap`` for a texture meant to tile.  Summed in float64, so the result does not
    depend on the order of the two passes' rounding.
    """
    from scipy.ndimage import convolve1d
    kernel = np.array([1, 4, 6, 4, 1], np.float64) / 16.0
    blurred = convolve1d(np.asarray(image, np.float64), kernel, axis=0, mode=mode)
    blurred = convolve1d(blurred, kernel, axis=1, mode=mode)
    return np.ascontiguousarray(blurred[::2, ::2], dtype=np.float32)


def window_sums(values: np.ndarray, window: tuple[int, int]) -> np.ndarray:
    """Sum of ``values [H, W, ...]`` over every placement of a ``window = (rows, cols)`` inside it,
    ``[H - rows + 1, W - cols + 1, ...]``, from one summed-area table (float64 for float values, int64 for integer
    or boolean ones; the running sums in the values' own type)."""
    ph, pw = window
    running = values.cumsum(0).cumsum(1)
    table = np.zeros((values.shape[0] + 1, values.shape[1] + 1) + values.shape[2:],
                     np.float64 if running.dtype.kind == "f" else np.int64)
    table[1:, 1:] = running
    return table[ph:, pw:] - table[:-ph, pw:] - table[ph:, :-pw] + table[:-ph, :-pw]


def edge_padded(texels: np.ndarray) -> np.ndarray:
    """``texels [eh, ew, d]`` padded by one texel of its own edge on every side, flat ``[(eh + 2) * (ew + 2), d]``
    (read through :func:`beside`)."""
    return np.pad(texels, ((1, 1), (1, 1), (0, 0)), mode="edge").reshape(-1, texels.shape[2])


def beside(padded: np.ndarray, source_size: tuple[int, int], rows: np.ndarray, cols: np.ndarray, dy: int,
           dx: int) -> np.ndarray:
    """The exemplar texels ``(dy, dx)`` away from ``(rows, cols)`` (any of -1, 0, 1), the exemplar's edge standing
    in beyond its border; ``padded`` is :func:`edge_padded` of the exemplar."""
    eh, ew = source_size
    return padded[(np.clip(rows + dy, -1, eh) + 1) * (ew + 2) + np.clip(cols + dx, -1, ew) + 1]
