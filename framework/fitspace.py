"""Which space a fit of an 8-bit capture works in: linear radiance or the display values the capture holds.

Shared by every representation with a ``space`` parameter (``auto``: whichever predicts held-out lights of a
sample of texels better); the representation supplies only how to fit and predict.
"""
from __future__ import annotations

import math

import numpy as np

from .buffers import SampleStack, linear_to_srgb


AUTO_TEXELS = 4096       # texels (a regular grid over the capture) on which `auto` compares the spaces
AUTO_HOLD_EVERY = 5      # ... in five folds, each holding out every fifth light
AUTO_MIN_LIGHTS = 10     # fewer lights than this: no held-out test, 8-bit captures are fitted in display space


def held_out_space(stack: SampleStack, predict) -> str:
    """``auto``'s choice for an 8-bit capture: the space whose fit predicts held-out lights better.

    ``predict(fit_stack, space, lights, views)`` fits ``fit_stack`` in ``space`` and returns linear radiance
    ``[V, L, h, w, C]`` at the held-out lights.  On a regular grid of at most ``AUTO_TEXELS`` texels, every
    light is held out once (in ``AUTO_HOLD_EVERY`` folds), both spaces are fitted to the rest, and the one with
    the lower mean squared error of the held-out display values (the bytes the capture holds) wins
    (:func:`best_held_out`).  Neither space wins
    everywhere: real captures (camera tone curves, gloss) fit better as display values, a computer-generated matte relief
    (SynthRTI: radiance linear in n . l, then sRGB-encoded) as linear radiance.  A linear capture is fitted
    linearly; one with fewer than ``AUTO_MIN_LIGHTS`` lights in display space.
    """
    if stack.encoding != "srgb8":
        return "linear"
    if stack.n_light < AUTO_MIN_LIGHTS:
        return "srgb"
    return space_from_grid(held_out_grid(stack), stack, predict)


def auto_grid_step(height: int, width: int) -> int:
    """The stride of the texel grid ``auto`` judges on: at most about ``AUTO_TEXELS`` texels."""
    return max(1, math.ceil(math.sqrt(height * width / AUTO_TEXELS)))


def space_from_grid(grid: np.ndarray, like: SampleStack, predict) -> str:
    """:func:`held_out_space` on 8-bit samples ``[V, L, h, w, C]`` of a texel grid (lights, views and channels
    those of ``like``): whoever read the grid - a whole stack, or a pass over a capture's images - gets the
    same answer."""
    return best_held_out(grid, like, ("srgb", "linear"), predict)[0]


def best_held_out(grid: np.ndarray, like: SampleStack, candidates, predict) -> tuple[object, dict]:
    """The candidate whose fits predict held-out lights of a texel grid best, and every candidate's error.

    ``grid [V, L, h, w, C]`` holds samples of ``like``'s lights, views and channels in ``like``'s encoding;
    ``predict(fit_stack, candidate, lights, views)`` fits ``fit_stack`` and returns linear radiance
    ``[V, L', h, w, C]`` at ``lights``.  Every light is held out once: fold ``k`` holds out the lights whose index
    is ``k`` modulo ``AUTO_HOLD_EVERY`` and fits the rest.  The error is the mean squared error over all held-out
    samples of display values for an 8-bit capture (what it holds, and what held-out PSNR is scored on) and of
    linear radiance otherwise.  One fold alone judges on a fifth of the lights, and a few lights at one
    elevation can then pick the wrong candidate; all folds together judge on every light.  Ties go to the
    earlier candidate.
    """
    display = like.encoding == "srgb8"
    errors = dict.fromkeys(candidates, 0.0)
    for held in held_out_folds(like.n_light):
        fit = SampleStack(np.ascontiguousarray(grid[:, ~held]), like.lights[~held], like.views, like.channels,
                          like.encoding)
        target = scored(np.ascontiguousarray(grid[:, held]), like.encoding)
        for candidate in candidates:
            predicted = predict(fit, candidate, like.lights[held], like.views)
            predicted = linear_to_srgb(predicted) if display else predicted
            errors[candidate] += float(np.sum((predicted - target) ** 2, dtype=np.float64))
    return best_of(errors, grid.size)


def held_out_folds(n_light: int) -> list[np.ndarray]:
    """The folds of :func:`best_held_out`: boolean masks of the lights each holds out (fold ``k``: the lights
    whose index is ``k`` modulo ``AUTO_HOLD_EVERY``), so that every light is held out exactly once."""
    lights = np.arange(n_light)
    return [lights % AUTO_HOLD_EVERY == fold for fold in range(min(AUTO_HOLD_EVERY, n_light))]


def best_of(squared_errors: dict, count: int) -> tuple[object, dict]:
    """The candidate with the least summed squared error over ``count`` held-out samples, and every candidate's
    mean squared error; ties go to the earlier candidate."""
    errors = {candidate: error / max(count, 1) for candidate, error in squared_errors.items()}
    return min(errors, key=errors.get), errors


def scored(samples: np.ndarray, encoding: str) -> np.ndarray:
    """Held-out samples as scored: an 8-bit capture's display values in [0, 1], a linear one's radiance."""
    if encoding == "srgb8":
        return samples.astype(np.float64) / 255.0
    return samples.astype(np.float64)


def held_out_grid(stack: SampleStack) -> np.ndarray:
    """The samples ``[V, L, h, w, C]`` of the regular texel grid (at most about ``AUTO_TEXELS`` texels) that
    ``auto`` choices judge on."""
    return stack.texel_grid(auto_grid_step(stack.height, stack.width))


def resolve_space(stack: SampleStack, space: str, predict=None) -> str:
    """The space to fit: ``space`` itself, or for ``auto`` :func:`held_out_space` (display values for an 8-bit
    capture when no ``predict`` is given)."""
    if space != "auto":
        return space
    if predict is None:
        return "srgb" if stack.encoding == "srgb8" else "linear"
    return held_out_space(stack, predict)


# ----------------------------------------------------------------------------------------------- ridge weights


RIDGE_WEIGHTS = (0.0, 1e-4, 3e-4, 1e-3, 3e-3, 1e-2)  # ``ridge: auto`` tries these multiples of |A|_2^2
LEVERAGE_FLOOR = 1e-9  # 1 - h_ii below this: the fit passes through that light whatever it holds (no LOO test)


def ridge_solve(design: np.ndarray, ridge: float, rcond: float = 0.0, free: tuple[int, ...] = ()) -> np.ndarray:
    """``(A^T A + lambda P)^-1 A^T`` ``[k, L]`` for ``design`` ``A [L, k]``, ``lambda = ridge * s_max^2`` (``s_max``
    the largest singular value of ``A``) and ``P`` the identity but for the columns ``free`` (e.g. a constant
    term, so that a constant texel is fitted exactly whatever the weight).  Singular directions below ``rcond *
    s_max`` get weight 0 (the directions the lights leave undetermined stay at zero, as in a truncated
    pseudo-inverse); the solve runs in the kept directions."""
    return ridge_solves(design, (ridge,), rcond, free)[0]


def ridge_solves(design: np.ndarray, ridges, rcond: float = 0.0, free: tuple[int, ...] = ()) -> list[np.ndarray]:
    """:func:`ridge_solve` at each weight of ``ridges``, from one singular value decomposition of ``design``."""
    a = np.asarray(design, np.float64)
    u, s, vt = np.linalg.svd(a, full_matrices=False)
    if not s.size or s[0] <= 0:
        return [np.zeros(a.shape[::-1]) for _ in ridges]
    kept = s >= rcond * s[0]
    u, s, v = u[:, kept], s[kept], vt[kept].T
    penalty = np.ones(a.shape[1])
    penalty[np.asarray(free, dtype=np.int64)] = 0.0
    solves = []
    for ridge in ridges:
        system = np.diag(s * s) + ridge * s[0] ** 2 * (v.T * penalty) @ v     # in the kept directions
        solves.append(v @ np.linalg.solve(system, s[:, None] * u.T))
    return solves


def leave_one_out_errors(design: np.ndarray, samples: np.ndarray, ridges=RIDGE_WEIGHTS,
                         rcond: float = 0.0, free: tuple[int, ...] = ()) -> np.ndarray:
    """The leave-one-out mean squared error of the ridge fit at each weight of ``ridges``, over all columns.

    ``design A [L, k]`` is shared by every column of ``samples [L, N]`` (the texels of a capture see the same
    lights), so the hat matrix ``H = A (A^T A + lambda P)^-1 A^T`` (:func:`ridge_solve`) is one ``L x L`` matrix, and the residual of
    sample ``i`` when light ``i`` is left out of the fit is ``r_i / (1 - H_ii)`` for ``r`` the residual of the fit
    to all lights: scoring every weight costs a few matrix products instead of ``L`` fits per texel.  The sum of
    squares of light ``i``'s residuals over all columns is ``[(I - H) G (I - H)^T]_ii`` for the ``L x L`` Gram matrix
    ``G = Y Y^T`` of the samples, formed once: each weight then costs products of ``L x L`` matrices, whatever
    the number of columns.  A light the fit must pass through (``H_ii`` = 1: fewer lights than coefficients, or an
    isolated light, without a ridge) leaves no test; its weight scores ``inf``.
    """
    from .backend import single_threaded_blas
    with single_threaded_blas():  # small products: BLAS threads only spin against busy cores
        return _leave_one_out_errors(np.asarray(design, np.float64), samples, ridges, rcond, free)


def _leave_one_out_errors(a: np.ndarray, samples: np.ndarray, ridges, rcond: float, free) -> np.ndarray:
    y = np.asarray(samples, np.float64).reshape(len(a), -1)
    return leave_one_out_errors_of_gram(a, y @ y.T, y.shape[1], ridges, rcond, free)


def leave_one_out_errors_of_gram(a: np.ndarray, gram: np.ndarray, n_column: int, ridges=RIDGE_WEIGHTS,
                                 rcond: float = 0.0, free: tuple[int, ...] = ()) -> np.ndarray:
    """:func:`leave_one_out_errors` of samples ``Y [L, n_column]`` given only their Gram matrix ``G = Y Y^T``
    ``[L, L]``: the Gram matrix of a subset of lights is the block of a larger one, so one product serves fits
    to several subsets of the same samples.  Call it with BLAS on one thread (``single_threaded_blas``)."""
    a = np.asarray(a, np.float64)
    errors = np.empty(len(ridges))
    for index, solve in enumerate(ridge_solves(a, ridges, rcond, free)):
        residual_map = np.eye(len(a)) - a @ solve           # I - H: samples to residuals
        slack = np.diag(residual_map)                       # 1 - H_ii
        if n_column == 0:
            errors[index] = 0.0
            continue
        if np.any(slack < LEVERAGE_FLOOR):
            errors[index] = math.inf
            continue
        squares = np.einsum("ij,ij->i", residual_map @ gram, residual_map)  # each light's sum over columns
        # rounding can leave a residual of exactly fitted samples a hair below zero
        errors[index] = float(np.sum(np.maximum(squares, 0.0) / (slack * slack))) / (len(a) * n_column)
    return errors


def ridge_by_leave_one_out(design: np.ndarray, samples: np.ndarray, ridges=RIDGE_WEIGHTS,
                           rcond: float = 0.0, free: tuple[int, ...] = ()) -> tuple[float, dict]:
    """The weight of ``ridges`` whose fits predict each left-out light best (:func:`leave_one_out_errors`), and
    every weight's error; ties go to the smaller weight.  A ridge pulls each texel's coefficients towards zero
    where the lights determine them poorly (grazing, clustered or few lights, noisy or saturated samples), at the
    cost of a small bias where they determine them well; the samples decide how much."""
    return best_ridge(leave_one_out_errors(design, samples, ridges, rcond, free), ridges)


def best_ridge(errors: np.ndarray, ridges=RIDGE_WEIGHTS) -> tuple[float, dict]:
    """:func:`ridge_by_leave_one_out`'s choice from the errors of ``ridges``."""
    finite = np.where(np.isfinite(errors), errors, np.inf)
    best = int(np.argmin(finite)) if np.isfinite(finite).any() else len(ridges) - 1
    return float(ridges[best]), {float(r): float(e) for r, e in zip(ridges, errors)}
