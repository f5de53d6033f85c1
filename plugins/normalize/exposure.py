"""Per-image light intensity of a multi-light capture, and near-light fall-off across the frame.

A hand-held flash or lamp gives neither the same intensity in every shot nor the same light across the frame.
We model the capture (linear luminance, block means of the frame) as

    I_i(p) = g_i(p) * f_p(l_i),    log g_i(p) = sum_k G[i, k] b_k(p)

with, per pixel ``p``, a low-order function of the light direction ``f_p`` (the six PTM terms), and per image
``i`` a gain: a constant (``b_0 = 1``: the shot's intensity) or, for fall-off, a quadratic in the frame
position (``1, x, y, x^2, xy, y^2``: a light close to the surface lights one side more).  Fit and gains
alternate; each gain update is a weighted least-squares fit of the log residual ratio, and Tukey weights on the
residuals keep shadows, highlights and clipped pixels from steering them.

A gain that varies with the light direction as the PTM terms do cannot be told apart from the reflectance (a
surface is brighter under some lights, and one side of it brighter when the light is on that side), so after
every update each gain coefficient, as a function of the image, loses its part that the PTM terms of ``l_i``
explain.  What stays is what no reflectance function could explain: the shot-to-shot jitter.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from btforge.buffers import SampleStack, linear_to_srgb8
from btforge.errors import BtforgeInputError
from btforge.plugins.ptm.model import ptm_terms

WORK_SIDE = 64          # the fit runs on block means of at most this many pixels per side
ITERATIONS = 10
TUKEY_C = 4.685         # Tukey's biweight constant, in robust standard deviations
DARK, CLIPPED = 1e-3, 0.98
FIELD_RIDGE = 0.02      # ridge weight of the fall-off field's terms, per unit of pixel weight


@dataclasses.dataclass(frozen=True)
class Exposure:
    """Per-image gains: ``coeffs [L, K]`` of ``log g_i`` over the frame basis (K = 1: a scale; 6: with fall-off)
    and the robust relative residual of the fit without and with them."""

    coeffs: np.ndarray
    rms_before: float
    rms_after: float

    @property
    def scales(self) -> np.ndarray:
        """Each image's gain at the frame centre (its intensity relative to the capture's median image)."""
        return np.exp(self.coeffs[:, 0])

    def gain(self, light: int, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.exp(frame_basis(x, y, self.coeffs.shape[1]) @ self.coeffs[light]).astype(np.float32)


def frame_basis(x: np.ndarray, y: np.ndarray, k: int) -> np.ndarray:
    """``[..., k]``: 1 (k = 1), or 1, x, y, x^2, xy, y^2 (k = 6), at frame coordinates in frame widths."""
    terms = [np.ones_like(x), x, y, x * x, x * y, y * y][:k]
    return np.stack(terms, axis=-1)


def frame_coordinates(height: int, width: int, rows=None, cols=None):
    """Pixel (or block) centres in frame widths from the frame centre, x right and y up."""
    rows = np.arange(height) + 0.5 if rows is None else rows
    cols = np.arange(width) + 0.5 if cols is None else cols
    return np.meshgrid((cols - width / 2) / width, -(rows - height / 2) / width)


def _block_means(stack: SampleStack, region):
    """Luminance ``[L, P]`` of block means of the frame (or of ``region`` = row, col, h, w) and their centres."""
    r0, c0, h, w = region if region else (0, 0, stack.height, stack.width)
    if r0 < 0 or c0 < 0 or h < 1 or w < 1 or r0 + h > stack.height or c0 + w > stack.width:
        raise BtforgeInputError("normalize.stack 'reference'", f"expected [row, col, height, width] inside the "
                                f"{stack.height} x {stack.width} frame, found {list(region)}",
                                "give the white target's or matte patch's top-left corner and size in pixels")
    factor = max(1, int(math.ceil(max(h, w) / WORK_SIDE)))
    bh, bw = max(1, h // factor), max(1, w // factor)
    factor = min(factor, h // bh, w // bw)
    lum = np.empty((stack.n_light, bh * bw), np.float64)
    for l in range(stack.n_light):
        image = stack.image(0, l)[r0:r0 + bh * factor, c0:c0 + bw * factor].mean(axis=2)
        lum[l] = image.reshape(bh, factor, bw, factor).mean(axis=(1, 3)).ravel()
    x, y = frame_coordinates(stack.height, stack.width, r0 + (np.arange(bh) + 0.5) * factor,
                             c0 + (np.arange(bw) + 0.5) * factor)
    return lum, x.ravel(), y.ravel()


def _pixel_fit(values: np.ndarray, terms: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted least-squares PTM of every pixel: ``values [L, P]`` -> model ``[L, P]``."""
    a = np.einsum("lp,li,lj->pij", weights, terms, terms) + 1e-9 * np.eye(terms.shape[1])
    b = np.einsum("lp,li,lp->pi", weights, terms, values)
    coeffs = np.linalg.solve(a, b[..., None])[..., 0]
    return terms @ coeffs.T


def _robust_weights(lum, model, valid):
    if not valid.any():  # a black or clipped capture: nothing to weigh
        return valid.astype(np.float64), 0.0
    residual = (lum - model) / np.maximum(np.abs(model), DARK)
    sigma = 1.4826 * float(np.median(np.abs(residual[valid]))) + 1e-9
    u = residual / (TUKEY_C * sigma)
    return np.where(valid & (np.abs(u) < 1), (1 - u * u) ** 2, 0.0), sigma


def fit_gains(lum: np.ndarray, x: np.ndarray, y: np.ndarray, lights: np.ndarray, k: int) -> Exposure:
    """Alternate per-pixel PTMs and per-image log-gains with ``k`` frame terms (see the module docs)."""
    terms = ptm_terms(lights)
    explained = terms @ np.linalg.pinv(terms)            # projects a per-image quantity onto the PTM terms of l_i
    basis = frame_basis(x, y, k)                          # [P, K]
    valid = (lum > DARK) & (lum < CLIPPED)               # black and clipped pixels say nothing about the gain
    weights = valid.astype(np.float64)
    _, before = _robust_weights(lum, _pixel_fit(lum, terms, weights), valid)
    coeffs = np.zeros((len(lum), k))
    ridge = np.diag([1e-9] + [1.0] * (k - 1))
    for _ in range(ITERATIONS):
        gain = np.exp(coeffs @ basis.T)
        model = _pixel_fit(lum / gain, terms, weights)
        log_ratio = np.log(np.maximum(lum, DARK) / np.maximum(gain * model, DARK))
        for i in range(len(lum)):
            w = weights[i] * (model[i] > DARK)
            if w.sum() > k:
                # ridge on the field terms: a field needs the evidence of many pixels, not of a dark corner
                a = (basis * w[:, None]).T @ basis + FIELD_RIDGE * w.sum() * ridge
                coeffs[i] += np.linalg.solve(a, (basis * w[:, None]).T @ log_ratio[i])
        coeffs -= explained @ coeffs
        coeffs[:, 0] -= np.median(coeffs[:, 0])
        weights, after = _robust_weights(lum, np.exp(coeffs @ basis.T) * model, valid)
    return Exposure(coeffs.astype(np.float32), before, after)


FIELD_TERMS = (1, 3, 6)  # fall-off fields tried: none, a log-linear gradient, a log-quadratic


def heldout_error(lum: np.ndarray, lights: np.ndarray, exposure: Exposure, x, y, folds: int = 5) -> float:
    """Mean squared error, on sRGB display values, of PTMs fitted to the corrected block means without every
    ``folds``-th light and evaluated at those lights: how well the corrected capture predicts unseen lights."""
    from btforge.buffers import linear_to_srgb
    terms = ptm_terms(lights)
    gain = np.exp(exposure.coeffs.astype(np.float64) @ frame_basis(x, y, exposure.coeffs.shape[1]).T)
    values = lum / gain
    error, count = 0.0, 0
    for start in range(folds):
        test = np.zeros(len(lum), bool)
        test[start::folds] = True
        coeffs = np.linalg.lstsq(terms[~test], values[~test], rcond=None)[0]
        predicted = terms[test] @ coeffs
        error += float(((linear_to_srgb(predicted) - linear_to_srgb(values[test])) ** 2).sum())
        count += predicted.size
    return error / count


def reference_gains(stack: SampleStack, reference) -> Exposure:
    """Scales from a matte reference facing up (a white target on the object plane): its mean luminance over
    the cosine of each light's elevation angle from the surface, relative to the median image."""
    lum, _, _ = _block_means(stack, reference)
    usable = (lum > DARK) & (lum < CLIPPED)
    if not usable.any(axis=1).all():
        bad = [stack.names[i] if stack.names else f"light {i}" for i in np.flatnonzero(~usable.any(axis=1))]
        raise BtforgeInputError("normalize.stack 'reference'", f"expected the region to be neither black nor "
                                f"clipped, found it so in {', '.join(bad[:5])}", "choose a mid-grey or white patch "
                                "that no light saturates")
    mean = np.array([row[ok].mean() for row, ok in zip(lum, usable)])
    cosine = np.clip(stack.lights[:, 2].astype(np.float64), 0.05, None)
    log_scale = np.log(mean / cosine)
    coeffs = (log_scale - np.median(log_scale))[:, None]
    spread = float(1.4826 * np.median(np.abs(log_scale - np.median(log_scale))))
    return Exposure(coeffs.astype(np.float32), spread, 0.0)


def estimate_exposure(stack: SampleStack, reference=None, with_falloff: bool = False) -> Exposure:
    """Gains of a single-view stack from the whole frame or from a ``reference`` region [row, col, h, w].

    With a reference and fall-off, the fall-off field comes from the whole frame and the scale from the region:
    the field is divided by its mean over the region before the region's own scale is applied.
    """
    if stack.n_view != 1:
        raise BtforgeInputError("normalize.stack 'stack'", f"expected a single-view capture, found {stack.n_view} views")
    if stack.n_light < 8:
        raise BtforgeInputError("normalize.stack 'stack'", f"expected at least 8 lights to tell intensity from "
                                f"reflectance, found {stack.n_light}", "normalize the whole capture, before any split")
    lights = stack.lights.astype(np.float64)
    whole = _block_means(stack, None)
    if reference is None and not with_falloff:
        return fit_gains(*whole, lights, 1)
    region = reference_gains(stack, reference) if reference is not None else None
    if not with_falloff:
        return region
    # The field's order is chosen by how well the corrected capture predicts lights left out of the fit: a
    # richer field must earn its place (on a dome it may only absorb what a PTM cannot fit).
    fields = [fit_gains(*whole, lights, k) for k in FIELD_TERMS]
    field = min(fields, key=lambda e: heldout_error(whole[0], lights, e, whole[1], whole[2]))
    if region is None:
        return field
    _, rx, ry = _block_means(stack, reference)
    coeffs = field.coeffs.astype(np.float64).copy()
    mean_log = np.log(np.exp(frame_basis(rx, ry, coeffs.shape[1]) @ coeffs.T).mean(axis=0))  # level on the region
    coeffs[:, 0] += region.coeffs[:, 0] - mean_log
    return Exposure(coeffs.astype(np.float32), region.rms_before, field.rms_after)


def corrected(stack: SampleStack, exposure: Exposure) -> SampleStack:
    """The stack with image ``i`` divided by its gain.  8-bit stacks stay 8-bit (re-encoded, clipped at 1)."""
    x, y = frame_coordinates(stack.height, stack.width)
    out = np.empty_like(stack.samples)
    for l in range(stack.n_light):
        gain = exposure.gain(l, x, y)[..., None]
        for v in range(stack.n_view):
            image = stack.image(v, l) / gain
            out[v, l] = linear_to_srgb8(image) if stack.encoding == "srgb8" else image
    return SampleStack(out, stack.lights, stack.views, stack.channels, stack.encoding, stack.names)
