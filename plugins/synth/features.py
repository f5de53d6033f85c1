"""Per-texel appearance vectors that synthesizers compare: one entry point shared by every synthesizer.

Each buffer class says what its appearance vectors are (``appearance_features``), so that distances between
them approximate L2 distances between the texels' reflectance functions: a PTM gives its orthonormal Legendre
coefficients (Hel-Or et al. 2003), a stack its radiance under every light and view, any other reflectance model
its values at a fixed set of lights spread over the hemisphere, and other per-texel buffers their records.

Long vectors are reduced by PCA (an orthogonal projection, so distances shrink only by the discarded energy).

Where those vectors are linear radiance, or functions that evaluate to it (a stack, a model of light only fitted to
linear radiance), a texel is compared as ``synth.score`` and the eye compare it instead: its radiance at
:data:`FEATURE_LIGHTS` lights, each light exposed by the exemplar's white point and sRGB-encoded
(:func:`perceptual_samples`).  In linear radiance a step in a shadow is a small number, so the search and the cuts
put seams there, where the eye sees them first: on a smooth exemplar with dark craters (``procedural:bumps``) the
straight seams left were 1.43 x the exemplar's own steps with quilting (version 18) and with the jump map (25),
1.28 and 1.06 with these vectors (Benchmarks, "Texels compared as a screen shows them").  Models
fitted to display values (an sRGB PTM, SH or HSH fit, a ``.ptm`` file) keep their coefficients: those are already
linear in what a screen shows.
"""
from __future__ import annotations

import numpy as np

from btforge.buffers import (APPEARANCE_PROBE_LIGHTS, Buffer, ReflectanceModel, SampleStack,
                             appearance_probe_lights)

FEATURE_LIGHTS = APPEARANCE_PROBE_LIGHTS  # lights at which models of unknown form are sampled
#: Each light is exposed so that this percentile of the exemplar's radiance maps to 1 (the scores' exposure too).
WHITE_PERCENTILE = 99.5
#: Principal components kept of the perceptual vectors (:func:`perceptual_samples`, 75 values per texel at 25
#: lights in colour): the leading 16 hold 99.6-99.9 % of the variance on the procedural exemplars (12: 99.0-99.7 %,
#: and at 12 the jump map's patch statistics on the SynthRTI relief missed, 1.63 x the shuffled blocks' over seeds
#: 0-3 against 1.33 at 16).  The synthesizers' searches cost in proportion to the length (a PTM's own vectors: 9).
PERCEPTUAL_DIMS = 16


def probe_lights(n: int = FEATURE_LIGHTS) -> np.ndarray:
    """``n`` unit directions spread over the upper hemisphere (a Fibonacci spiral above 10 degrees)."""
    return appearance_probe_lights(n)


def texel_features(buffer: Buffer, max_dims: int | None = 32, seed: int = 0) -> np.ndarray:
    """Appearance vectors ``[H, W, D]`` float32 of any per-texel buffer (see the module docstring): at most
    ``max_dims`` long (None: all of the buffer's own), perceptual ones at most :data:`PERCEPTUAL_DIMS`."""
    seen = perceptual_samples(buffer)
    if seen is not None:
        dims = PERCEPTUAL_DIMS if max_dims is None else min(max_dims, PERCEPTUAL_DIMS)
        return pca_reduce(seen, dims, seed) if seen.shape[2] > dims else seen
    features = np.ascontiguousarray(buffer.appearance_features(), dtype=np.float32)
    if max_dims is not None and features.shape[2] > max_dims:
        features = pca_reduce(features, max_dims, seed)
    return features


def perceptual_samples(buffer: Buffer) -> np.ndarray | None:
    """``[H, W, S * C]`` float32: what a screen shows of each texel in the ``S`` images of a stack, or of a model of
    light only fitted to linear radiance at :data:`FEATURE_LIGHTS` probe lights, each image exposed by its white
    point (:func:`white_points`) and sRGB-encoded (:func:`encoded`); None for other buffers (models fitted to
    display values, view-dependent models, per-texel data that is not radiance)."""
    if isinstance(buffer, SampleStack):
        linear = buffer.linear()
        frames = linear.reshape(-1, *linear.shape[2:])
    elif (isinstance(buffer, ReflectanceModel) and not buffer.view_dependent
          and getattr(buffer, "space", "linear") == "linear"):
        frames = buffer.evaluate(probe_lights())[0]
    else:
        return None
    seen = encoded(np.asarray(frames, np.float32), white_points(frames), "srgb")
    return np.ascontiguousarray(np.moveaxis(seen, 0, 2).reshape(buffer.height, buffer.width, -1))


def encoded(linear: np.ndarray, white: np.ndarray, domain: str) -> np.ndarray:
    """Exposure-normalised perceptual values of ``linear [L, ...]``: ``linear / white`` per light, then sRGB-encoded
    (``domain`` srgb) or log (log); linear: only exposed."""
    y = np.maximum(linear / white.reshape(-1, *([1] * (linear.ndim - 1))), 0.0).astype(np.float32)
    if domain == "srgb":
        # The sRGB curve, not clipped above 1, so highlights brighter than the white point still differ.
        return np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055).astype(np.float32)
    if domain == "log":
        return (np.log2(y + 2.0 ** -8) / 8 + 1).astype(np.float32)
    return y


def white_points(linear: np.ndarray) -> np.ndarray:
    """``[L]`` float32: per light of ``linear [L, ...]``, the radiance shown as white (:data:`WHITE_PERCENTILE` of
    its values, on at most 2^20 of them; the largest where that is 0, and 1 for a black image)."""
    whites = []
    for frame in linear:
        flat = np.asarray(frame).reshape(-1)
        if flat.size > 1 << 20:
            flat = flat[:: flat.size // (1 << 20) + 1]
        white = float(np.percentile(flat, WHITE_PERCENTILE))
        if not white > 1e-12:
            white = float(flat.max())
        whites.append(white if white > 1e-12 else 1.0)
    return np.array(whites, np.float32)


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


def appearance_variance(features: np.ndarray) -> float:
    """The summed variance of the appearance vectors ``features [h, w, D]`` (their mean squared distance from
    their mean), in float64."""
    flat = np.asarray(features, np.float64).reshape(-1, features.shape[-1])
    return float(((flat - flat.mean(axis=0)) ** 2).sum(axis=1).mean())


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
