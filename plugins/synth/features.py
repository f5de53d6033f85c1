"""Per-texel appearance vectors that synthesizers compare: one definition shared by every synthesizer.

Distances between these vectors should approximate L2 distances between the texels' reflectance functions:

- a PTM is expressed in the orthonormal Legendre basis (Hel-Or et al. 2003), where that holds exactly for the
  luminance/colour polynomials, with the colour of an ``lrgb`` model appended;
- a stack uses its radiance under every light and view;
- any other reflectance model is evaluated at a fixed set of lights spread over the hemisphere.

Long vectors are reduced by PCA (an orthogonal projection, so distances shrink only by the discarded energy).
"""
from __future__ import annotations

import numpy as np

from btforge.buffers import PerTexel, ReflectanceModel, SampleStack, unit_directions

FEATURE_LIGHTS = 25  # lights at which models of unknown form are sampled


def probe_lights(n: int = FEATURE_LIGHTS) -> np.ndarray:
    """``n`` unit directions spread over the upper hemisphere (a Fibonacci spiral above 10 degrees)."""
    i = np.arange(n) + 0.5
    z = np.sin(np.radians(10)) + (1 - np.sin(np.radians(10))) * i / n
    phi = i * np.pi * (3 - np.sqrt(5))
    r = np.sqrt(1 - z * z)
    return unit_directions("probe lights", np.column_stack([r * np.cos(phi), r * np.sin(phi), z]))


def texel_features(buffer: PerTexel, max_dims: int | None = 32, seed: int = 0) -> np.ndarray:
    """Appearance vectors ``[H, W, D]`` float32 for any per-texel buffer (see the module docstring)."""
    from btforge.plugins.ptm.model import PTMModel
    if isinstance(buffer, PTMModel):
        ortho = buffer.with_basis("orthonormal")
        parts = [ortho.coeffs.reshape(buffer.height, buffer.width, -1)]
        if ortho.albedo.size:
            parts.append(ortho.albedo)
        features = np.concatenate(parts, axis=2)
    elif isinstance(buffer, SampleStack):
        features = np.moveaxis(buffer.linear(), (2, 3), (0, 1)).reshape(buffer.height, buffer.width, -1)
    elif isinstance(buffer, ReflectanceModel):
        relit = buffer.evaluate(probe_lights())
        features = np.moveaxis(relit, (2, 3), (0, 1)).reshape(buffer.height, buffer.width, -1)
    else:
        features = buffer.appearance_features()
    features = np.ascontiguousarray(features, dtype=np.float32)
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
