"""Fitting light-table bases: build the table (HSH terms, or PCA of the light responses), then project every
texel's samples on it by one shared regularised least-squares inverse.

The table (:mod:`.model`) is evaluated at the capture's lights, giving per light ``g0 [3]`` (the mean) and
``G [P, 3]`` (the planes), in RGB.  A texel's coefficients minimise

    sum_{l, k} (g0[l, k] + sum_p c[p] G[l, p, k] - y[l, k])^2 + lambda |c|^2

over its samples ``y [L, 3]`` (display values, or for ``space: linear`` the linear radiance of an 8-bit
capture), with ``lambda = ridge * s_max^2`` for ``s_max`` the largest singular value of ``G`` and ``ridge`` at
least ``RIDGE^2``: negligible for a well-spread light set, and a bound on the coefficients (``|c| <= |y - g0| /
(2 RIDGE s_max)``) when few, clustered or grazing lights leave directions undetermined.  hsh.fit chooses
``ridge`` by closed-form leave-one-out (:func:`table_ridge`), leaves its constant terms unpenalised and leaves
out lights below the elevation its basis clamps to (:func:`fitting_light_weights`).  The solution is one matrix
``proj [P, L, 3]`` and an ``offset [P]`` shared by all texels; kernel ``basis_project`` applies them (NumPy twin
:func:`project_numpy`), reading an 8-bit capture's bytes in place for a display-value fit.

PCA (rbf, bilinear) follows relight: the responses of up to :data:`PCA_SAMPLES` texels (display values or linear
radiance, over the lights or resampled onto the bilinear grid) are centred on their mean, clipped to [0, 1] so that the web
layout's 8-bit basis holds it, and the leading eigenvectors of their second moments about it become the
planes; ``ycc`` runs one PCA per YCoCg component.  relight's projection (coefficients = the resampled
responses, centred, projected on the planes: :func:`pca_projection`) is the other way to get coefficients;
it is the default for bilinear, whose resampling already fits the samples.

The rbf table can be solved to interpolate (:func:`interpolating_table`), and rbf's ``sigma`` and the grid
resamplings' ``resolution`` can be chosen by held-out lights (:func:`held_out_choice`), each together with
``space: auto``.  bilinear's default spline resampling chooses its smoothing and space by exact leave-one-out
(:func:`spline_settings`) and its grid side by how closely the grid reproduces the spline (:func:`spline_side`);
its PCA is solved in the span of the resampling (:func:`_principal`).
"""
from __future__ import annotations

import math

import numpy as np

from btforge.backend import get_backend, single_threaded_blas
from btforge.buffers import SRGB8_TO_LINEAR, SampleStack, linear_to_srgb
from btforge.errors import BtforgeInputError
from btforge.fitspace import (AUTO_HOLD_EVERY, AUTO_MIN_LIGHTS, RIDGE_WEIGHTS, held_out_grid, held_out_space,
                              ridge_by_leave_one_out, ridge_solve)
from btforge.plugins.web.hsh import MIN_ELEVATION as HSH_MIN_ELEVATION

from .lightfuncs import (RGB_TO_YCC, bilinear_weights, colour_matrix, octa_directions, rbf_weights,
                         resample_matrix, smooth_resample_matrix, spline_inverse, spline_weights, table_weights)
from .model import KERNELS, LightTableModel

SIGMA_FACTORS = (0.7, 1.0, 1.4, 2.0, 2.8)  # sigma auto: these multiples of the lights' spacing are tried
# resolution auto tries every side from 4 to 12: the held-out error is far from smooth in the side (where a
# capture's rings of lights fall against the grid lines decides it), so a side skipped can be the best by dB
RESOLUTIONS = tuple(range(4, 13))
# resampling spline: its smoothing weight (space auto: and the space) is chosen by leave-one-out among these, and
# resolution 0 is the smallest side from SPLINE_SIDES whose grid reproduces the spline between the lights to
# within SPLINE_SIDE_TOLERANCE (RMS, display levels of 1/255) - finer grids cost PCA time and gain little
SPLINE_SMOOTHNESS = (1e-3, 3e-3, 1e-2, 3e-2, 1e-1)
SPLINE_SIDES = tuple(range(8, 25))
SPLINE_SIDE_TOLERANCE = 0.5 / 255.0
SIDE_JUDGE_STEP = 8      # ... on every eighth value of the judged texels (a smooth error: 1536 values judge it)
SPLINE_PROBE_SIDE = 41  # the directions the side is judged at: the nodes of this finer grid the lights cover
# planes 0: the fewest planes (at most AUTO_PLANES) whose truncation of the resampled grid stays within
# SPLINE_SIDE_TOLERANCE at the fitting lights, the tolerance the grid side is held to
AUTO_PLANES = 27
SMOOTH_RESAMPLING = 0.003  # resampling smooth: the grid's bending weight when smoothness is 0
TABLE_DAMPING = 0.1   # the interpolating rbf table stays this close (relatively) to the components at the lights
RIDGE = 1e-3          # lambda = (RIDGE x the largest singular value)^2
PCA_SAMPLES = 1 << 16  # texels whose responses the PCA sees (relight samples 65536 by default)


# ----------------------------------------------------------------------------------------------- tables


def hsh_table(terms: int, colorspace: str) -> tuple[np.ndarray, tuple[int, int, int]]:
    """The one-hot table of an HSH fit: rgb has plane ``3k + c`` = term k of channel c; ycc gives luma all
    ``terms`` and each chroma component the order below (9 luma terms: 4 chroma terms; 4: 1), in relight's
    order: (Y, Co, Cg) triplets of the terms chroma has, then the remaining luma terms."""
    if colorspace == "rgb":
        table = np.zeros((3 * terms + 1, terms, 3))
        for k in range(terms):
            for c in range(3):
                table[3 * k + c + 1, k, c] = 1.0
        return table, (0, 0, 0)
    chroma = 4 if terms == 9 else 1
    table = np.zeros((terms + 2 * chroma + 1, terms, 3))
    for k in range(chroma):
        for c in range(3):
            table[3 * k + c + 1, k, c] = 1.0
    for k in range(chroma, terms):
        table[2 * chroma + k + 1, k, 0] = 1.0
    return table, (terms, chroma, chroma)


def ycc_split(planes: int, yplanes: int) -> tuple[int, int, int]:
    """(Y, Co, Cg) plane counts for ``planes`` in all; ``yplanes`` 0 picks about half for Y."""
    y = yplanes or planes - 2 * (planes // 4)
    if not 1 <= y <= planes or (planes - y) % 2:
        raise BtforgeInputError("param 'yplanes'", f"expected Y planes in [1, {planes}] leaving an even number for "
                                f"the two chroma components, found {y} of {planes}",
                                "give yplanes with planes - yplanes even (or 0 for the default split)")
    return y, (planes - y) // 2, (planes - y) // 2


def _leading(second_moments: np.ndarray, count: int, basis: np.ndarray | None = None) -> np.ndarray:
    """The ``count`` leading unit eigenvectors ``[count, dim]`` of ``second_moments`` (taken to the full space by
    the orthonormal ``basis [dim, k]`` when they are given in its coordinates), each signed so its largest
    component is positive (deterministic)."""
    values, vectors = np.linalg.eigh(second_moments)
    top = vectors[:, np.argsort(values)[::-1][:count]]
    top = (top if basis is None else basis @ top).T
    pivot = top[np.arange(count), np.argmax(np.abs(top), axis=1)]
    return top * np.where(pivot < 0, -1.0, 1.0)[:, None]


def _principal(x: np.ndarray, count: int, mapping: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(mean [dim], components [count, dim])``: the mean of the rows ``x @ mapping.T`` (``mapping`` None: the
    identity) clipped to [0, 1], and the leading eigenvectors of their second moments about it.

    With a ``mapping [dim, k]`` from fewer values (a texel's samples resampled onto a finer grid) the rows lie
    in its column space plus the clipped mean's offset, so the eigenproblem is solved there (``k + 1`` values
    instead of ``dim``) and taken back: the same components, at a fraction of the time."""
    mean_x = x.mean(axis=0, dtype=np.float64)
    centred = np.ascontiguousarray(x - mean_x.astype(x.dtype), np.float32)
    # float32 products (half the time of float64; display values in [0, 1] lose nothing an eigenvector notices)
    moments = (centred.T @ centred).astype(np.float64) / max(len(x), 1)
    if mapping is None:
        mean = np.clip(mean_x, 0.0, 1.0)
        return mean, _leading(moments + np.outer(mean_x - mean, mean_x - mean), count)
    full_mean = mapping @ mean_x
    mean = np.clip(full_mean, 0.0, 1.0)
    # rows - mean = [mapping | offset] @ [x - mean_x; 1]: their second moments in an orthonormal basis of that span
    basis, tri = np.linalg.qr(np.c_[mapping, full_mean - mean])
    extended = np.zeros((len(mean_x) + 1,) * 2)
    extended[:-1, :-1] = moments
    extended[-1, -1] = 1.0
    return mean, _leading(tri @ extended @ tri.T, count, basis)


def pca_table(responses: np.ndarray, planes: int, colorspace: str, yccplanes: tuple[int, int, int],
              resample: np.ndarray | None = None) -> np.ndarray:
    """Table ``[planes + 1, D, 3]`` from display ``responses [N, D, 3]``, or given ``resample [D, L]``, from
    responses ``[N, L, 3]`` at the lights resampled by it onto the ``D`` table directions (relight's plane
    order for ycc: (Y, Co, Cg) triplets while chroma planes last, then the remaining Y planes)."""
    n = responses.shape[0]
    d = responses.shape[1] if resample is None else resample.shape[0]
    # The stored mean must lie in [0, 1] (the web layout keeps it as bytes); the components are taken about that
    # clipped mean, so whatever the clipping removed is a direction of the data they capture.
    if colorspace == "rgb":
        mapping = None if resample is None else np.kron(resample, np.eye(3))
        mean, vectors = _principal(responses.reshape(n, -1), planes, mapping)
        return np.concatenate([mean.reshape(1, d, 3), vectors.reshape(planes, d, 3)])
    ycc = responses @ RGB_TO_YCC.T.astype(responses.dtype)
    table = np.zeros((planes + 1, d, 3))
    for comp, count in enumerate(yccplanes):
        table[0, :, comp], vectors = _principal(ycc[:, :, comp], count, resample)
        for yp in range(count):
            p = 3 * yp + comp if yp < yccplanes[1] else 3 * yccplanes[1] + yp - yccplanes[1]
            table[p + 1, :, comp] = vectors[yp]
    return table


def display_values(stack: SampleStack, rows=slice(None), cols=slice(None), step: int = 1) -> np.ndarray:
    """Display values ``[L, h, w, 3]`` float32 of a single-view stack (an 8-bit capture's bytes / 255)."""
    raw = np.asarray(stack.samples[0, :, rows, cols][:, ::step, ::step])
    if stack.encoding == "srgb8":
        return np.divide(raw, np.float32(255.0), dtype=np.float32)
    return linear_to_srgb(raw).astype(np.float32)


def fitted_values(stack: SampleStack, space: str, rows=slice(None), cols=slice(None), step: int = 1) -> np.ndarray:
    """The values ``[L, h, w, 3]`` float32 a fit in ``space`` fits: display values, or (``linear``, an 8-bit
    capture) the linear radiance its bytes stand for."""
    if space == "linear" and stack.encoding == "srgb8":
        return SRGB8_TO_LINEAR[np.asarray(stack.samples[0, :, rows, cols][:, ::step, ::step])]
    return display_values(stack, rows, cols, step)


def pca_responses(stack: SampleStack, space: str = "srgb") -> np.ndarray:
    """Responses ``[N, L, 3]`` float32 (in ``space``) of at most :data:`PCA_SAMPLES` texels on a regular grid."""
    step = max(1, math.ceil(math.sqrt(stack.height * stack.width / PCA_SAMPLES)))
    y = fitted_values(stack, space, step=step)
    return np.ascontiguousarray(np.moveaxis(y, 0, 2).reshape(-1, stack.n_light, 3), np.float32)


def resolve_table_space(stack: SampleStack, space: str, fit) -> str:
    """The space a light-table fit works in: ``space``, or for ``auto`` on an 8-bit capture the one whose fits
    (``fit(part, candidate)`` -> model) predict held-out lights of a grid of texels better
    (:func:`btforge.fitspace.held_out_space`); other captures, and those whose held-out folds keep too few
    lights for the planes, are fitted as display values."""
    if space != "auto":
        return space
    if stack.encoding != "srgb8":
        return "srgb"
    try:
        return held_out_space(stack, lambda part, candidate, lights, views: fit(part, candidate).evaluate(lights))
    except BtforgeInputError:  # the lights a fold keeps cannot hold that many planes: nothing to judge
        return "srgb"


def _design(lw: np.ndarray) -> np.ndarray:
    """The least-squares design ``[L * 3, P]`` of the basis ``lw [L, P + 1, 3]``: row ``(l, k)``, column ``p``."""
    n_light, n_plane = lw.shape[0], lw.shape[1] - 1
    return lw[:, 1:, :].transpose(0, 2, 1).reshape(n_light * 3, n_plane)


def least_squares(lw: np.ndarray, ridge: float = RIDGE ** 2, free: tuple[int, ...] = ()
                  ) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(proj [P, L, 3], offset [P], stats)`` of the fit to the basis ``lw [L, P + 1, 3]`` (RGB) with the ridge
    weight ``ridge`` (at least ``RIDGE^2``) on every plane but ``free`` (:func:`btforge.fitspace.ridge_solve`)."""
    n_light, n_plane = lw.shape[0], lw.shape[1] - 1
    a = _design(lw)
    s = np.linalg.svd(a, compute_uv=False)
    inverse = ridge_solve(a, max(ridge, RIDGE ** 2), 0.0, free) if s.size and s[0] > 0 else np.zeros(a.shape[::-1])
    offset = inverse @ lw[:, 0, :].reshape(-1)
    stats = {"condition_number": float(s[0] / s[-1]) if s.size and s[-1] > 0 else math.inf,
             "rank": int(np.count_nonzero(s > 1e-6 * s[0])) if s.size and s[0] > 0 else 0,
             "ridge": float(max(ridge, RIDGE ** 2))}
    return inverse.reshape(n_plane, n_light, 3), offset, stats


def table_ridge(stack: SampleStack, lw: np.ndarray, free: tuple[int, ...] = (), space: str = "srgb") -> float:
    """``ridge: auto`` for a light-table fit: the weight whose fits best predict each sample left out, judged in
    closed form (:func:`btforge.fitspace.ridge_by_leave_one_out`) on the values (in ``space``) of a grid of at
    most 4096 texels."""
    grid = held_out_grid(stack)[0]                                         # [L, h, w, 3]
    like = SampleStack(grid[None], stack.lights, stack.views, stack.channels, stack.encoding)
    y = np.moveaxis(fitted_values(like, space).astype(np.float64), 3, 1)  # [L, 3, h, w]
    y = y.reshape(stack.n_light * 3, -1) - lw[:, 0, :].reshape(-1, 1)
    ridges = tuple(max(r, RIDGE ** 2) for r in RIDGE_WEIGHTS)
    return ridge_by_leave_one_out(_design(lw), y, ridges, 0.0, free)[0]


def pca_projection(table: np.ndarray, resample: np.ndarray, colorspace: str) -> tuple[np.ndarray, np.ndarray]:
    """``(proj [P, L, 3], offset [P])`` of relight's PCA projection: a texel's samples resampled onto the table
    (``resample [D, L]``; the identity for rbf), taken to the table's colour space, centred on the mean row and
    projected on each plane (the planes are orthonormal, so this is the least-squares fit on the table)."""
    to_space = RGB_TO_YCC if colorspace == "ycc" else np.eye(3)
    planes = table[1:].astype(np.float64)                                 # [P, D, 3] in the table's space
    proj = np.einsum("pdc,dl,ck->plk", planes, resample, to_space, optimize=True)
    offset = np.einsum("pdc,dc->p", planes, table[0].astype(np.float64))
    return proj, offset


def project_numpy(samples: np.ndarray, proj: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Twin of kernel ``basis_project``: ``samples [L, T, 3]`` -> ``coeffs [T, P]`` float32."""
    return (np.einsum("ltk,plk->tp", samples.astype(np.float64), proj.astype(np.float64)) - offset).astype(np.float32)


def project_opencl(samples: np.ndarray, proj: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Kernel ``basis_project``; uint8 samples are read as bytes (``proj`` must then carry the 1/255)."""
    backend = get_backend()
    n_light, n_texel, _ = samples.shape
    n_plane = proj.shape[0]
    out = np.empty((n_texel, n_plane), np.float32)
    if out.size == 0:
        return out
    options = ("-DBYTES",) if samples.dtype == np.uint8 else ()
    kernel = backend.kernel(KERNELS, "basis_project", options)
    o_dev = backend.host_output(out)
    data = samples if samples.dtype == np.uint8 else samples.astype(np.float32, copy=False)
    backend.run(kernel, (n_texel, n_plane), backend.host_input(np.ascontiguousarray(data)),
                backend.to_device(np.ascontiguousarray(proj, np.float32)),
                backend.to_device(np.ascontiguousarray(offset, np.float32)), np.int32(n_light), np.int32(n_texel),
                np.int32(n_plane), o_dev)
    backend.finish_output(o_dev, out)
    return out


def project_stack(stack: SampleStack, proj: np.ndarray, offset: np.ndarray, engine: str = "opencl",
                  budget_bytes: int = 64 << 20, space: str = "srgb") -> np.ndarray:
    """Coefficients ``[H, W, P]`` of every texel, band by band (an 8-bit capture's bytes read in place for a
    display-value fit)."""
    run = project_numpy if engine == "numpy" else project_opencl
    coeffs = np.empty((stack.height, stack.width, proj.shape[0]), np.float32)
    for rows, cols in stack.texel_blocks(budget_bytes):
        if stack.encoding == "srgb8" and space == "srgb":
            block = np.asarray(stack.samples[0, :, rows, cols])
            scaled = proj / 255.0
        else:
            block, scaled = fitted_values(stack, space, rows, cols), proj
        h, w = block.shape[1:3]
        samples = np.ascontiguousarray(block).reshape(stack.n_light, h * w, 3)
        coeffs[rows, cols] = run(samples, scaled, offset).reshape(h, w, -1)
    return coeffs


# ----------------------------------------------------------------------------------------------- the fits


def _check_stack(stack: SampleStack, stage: str) -> None:
    if stack.n_view != 1 or stack.n_channel != 3:
        raise BtforgeInputError(f"{stage} 'stack'", f"expected a single-view RGB stack, found {stack.n_view} view(s) "
                                f"and {stack.n_channel} channel(s)", "select one view with stackio.select")


def table_light_weights(model_args: dict, lights: np.ndarray) -> np.ndarray:
    """The basis ``lw [L, P + 1, 3]`` (float64, RGB) of the table in ``model_args`` at ``lights``."""
    table = np.asarray(model_args["table"], np.float32)
    probe = LightTableModel(coeffs=np.zeros((0, 0, table.shape[0] - 1), np.float32), **{**model_args, "table": table})
    return probe.light_weights(lights).astype(np.float64)


def fitting_light_weights(model_args: dict, lights: np.ndarray) -> np.ndarray:
    """:func:`table_light_weights` with zero rows for the lights a least-squares fit leaves out: an hsh basis is
    evaluated with the light's elevation clamped to at least ``MIN_ELEVATION`` (as RTI viewers evaluate it), so a
    sample lit from lower down is not what the basis says at its light, and fitting it pulls the whole function
    towards a grazing response at the clamped direction.  Such lights are left out while at least two lights per
    term remain."""
    lw = table_light_weights(model_args, lights)
    if model_args["kind"] != "hsh":
        return lw
    unit = np.asarray(lights, np.float64) / np.linalg.norm(lights, axis=1, keepdims=True)
    below = np.arcsin(np.clip(unit[:, 2], -1.0, 1.0)) < HSH_MIN_ELEVATION
    terms = np.asarray(model_args["table"]).shape[1]
    if np.count_nonzero(~below) >= 2 * terms:
        lw[below] = 0.0
    return lw


def fit_table(stack: SampleStack, model_args: dict, engine: str = "opencl",
              resample: np.ndarray | None = None, ridge=RIDGE ** 2,
              free: tuple[int, ...] = ()) -> tuple[LightTableModel, dict]:
    """Fit coefficients over the table in ``model_args`` (LightTableModel fields but coeffs) to ``stack``: by
    least squares against the table at the capture's lights (with the ridge weight ``ridge``, or ``auto``:
    :func:`table_ridge`; planes ``free`` unpenalised), or, given ``resample``, by relight's projection."""
    args = {**model_args, "table": np.asarray(model_args["table"], np.float32)}
    space = args.get("space", "srgb")
    lw = fitting_light_weights(args, stack.lights)
    if resample is None and ridge == "auto":
        ridge = table_ridge(stack, lw, free, space)
    proj, offset, stats = least_squares(lw, 0.0 if ridge == "auto" else ridge, free)
    if resample is not None:
        proj, offset = pca_projection(args["table"], resample, args.get("colorspace", "rgb"))
    with single_threaded_blas():
        coeffs = project_stack(stack, proj, offset, engine, space=space)
    stats["planes"] = args["table"].shape[0] - 1
    stats["space"] = space
    return LightTableModel(coeffs=coeffs, **args), stats


HSH_FREE = (0, 1, 2)  # the planes of the constant HSH term (one per colour component): not penalised


def hsh_args(planes: int, colorspace: str, space: str = "srgb") -> dict:
    table, ycc = hsh_table(planes // 3, colorspace)
    return {"kind": "hsh", "table": table, "colorspace": colorspace, "yccplanes": ycc, "space": space}


def hsh_settings(stack: SampleStack, planes: int = 27, colorspace: str = "rgb", ridge="auto", space: str = "auto",
                 engine: str = "opencl") -> tuple[str, float | str]:
    """hsh.fit's space and ridge weight on ``stack``: the given ones, or ``auto``'s choices
    (:func:`resolve_table_space`, then :func:`table_ridge` in that space)."""
    space = resolve_table_space(stack, space, lambda part, candidate: fit_hsh(
        part, planes, colorspace, engine, ridge, candidate)[0])
    if ridge == "auto":
        lw = fitting_light_weights(hsh_args(planes, colorspace, space), stack.lights)
        ridge = table_ridge(stack, lw, HSH_FREE, space)
    return space, ridge


def fit_hsh(stack: SampleStack, planes: int = 27, colorspace: str = "rgb", engine: str = "opencl", ridge="auto",
            space: str = "auto"):
    """hsh.fit: the HSH terms fitted by ridge least squares in ``space`` (auto: :func:`hsh_settings`); the
    constant term of each colour component is left unpenalised, so a constant texel is fitted exactly."""
    _check_stack(stack, "hsh.fit")
    space, ridge = hsh_settings(stack, planes, colorspace, ridge, space, engine)
    return fit_table(stack, hsh_args(planes, colorspace, space), engine, ridge=ridge, free=HSH_FREE)


def _pca_planes(stack: SampleStack, stage: str, planes: int, colorspace: str, yplanes: int, dims: int):
    ycc = ycc_split(planes, yplanes) if colorspace == "ycc" else (0, 0, 0)
    limit = dims * 3 if colorspace == "rgb" else dims
    if (planes if colorspace == "rgb" else max(ycc)) > limit:
        raise BtforgeInputError(f"{stage} 'planes'", f"expected at most {limit} planes per PCA for {dims} table "
                                f"directions, found {planes} ({colorspace}, split {ycc})",
                                "lower planes (or use more lights / a finer resolution)")
    return ycc


def light_spacing(lights: np.ndarray) -> float:
    """The median distance from a light to its nearest neighbour (unit directions)."""
    d = np.asarray(lights, np.float64)
    if len(d) < 2:
        return 1.0
    dist = np.linalg.norm(d[:, None] - d[None], axis=2)
    np.fill_diagonal(dist, np.inf)
    return float(max(np.median(dist.min(axis=1)), 1e-3))


def _fold(stack: SampleStack, fold: int = AUTO_HOLD_EVERY // 2) -> tuple[SampleStack, SampleStack]:
    """``(part, held)``: the grid of at most 4096 texels ``auto`` choices judge on, split into the lights kept
    and those held out (every fifth light, from ``fold``)."""
    grid = held_out_grid(stack)
    held = np.arange(stack.n_light) % AUTO_HOLD_EVERY == fold

    def select(mask):
        return SampleStack(np.ascontiguousarray(grid[:, mask]), stack.lights[mask], stack.views, stack.channels,
                           stack.encoding)
    return select(~held), select(held)


def _held_out_error(model, held: SampleStack) -> float:
    """Mean squared error of ``model``'s display values at the lights of ``held``."""
    return float(np.mean((linear_to_srgb(model.evaluate(held.lights)[0]) - display_values(held)) ** 2))


def held_out_choice(stack: SampleStack, spaces, values, fit) -> tuple[str, object]:
    """The (space, value) pair whose ``fit(part, space, value)`` model predicts held-out lights best: on a grid
    of at most 4096 texels, every fifth light held out (one of the folds ``space: auto`` judges on), mean squared
    error of display values.  Space and value are judged together: a grid side or interpolation width that suits
    display values need not suit linear radiance.  With fewer than 10 lights nothing is held out, and when the
    fold keeps too few lights for the planes nothing can be judged: the first space and the middle value."""
    fallback = (spaces[0], values[len(values) // 2])
    if stack.n_light < AUTO_MIN_LIGHTS or len(spaces) * len(values) == 1:
        return fallback
    part, held = _fold(stack)
    candidates = [(space, value) for space in spaces for value in values]
    errors = []
    for candidate in candidates:
        try:
            errors.append(_held_out_error(fit(part, *candidate), held))
        except BtforgeInputError:  # the lights left for fitting cannot hold that many planes: nothing to judge
            return fallback
    return candidates[int(np.argmin(errors))]


def candidate_spaces(stack: SampleStack, space: str) -> tuple[str, ...]:
    """The spaces ``space`` allows a light-table fit of ``stack``: both for ``auto`` on an 8-bit capture, display
    values for ``auto`` on any other (see :func:`resolve_table_space`)."""
    if space != "auto":
        return (space,)
    return ("srgb", "linear") if stack.encoding == "srgb8" else ("srgb",)


def interpolating_table(table: np.ndarray, lights: np.ndarray, sigma: float, damping: float) -> np.ndarray:
    """The table whose Gaussian interpolation passes (nearly) through ``table`` at ``lights``: ``T`` minimising
    ``|W T - table|^2 + damping^2 |T - table|^2`` per plane and component, ``W`` the interpolation weights
    between the lights (relight's viewer then reproduces the components at the lights and blends them smoothly
    between, instead of averaging neighbours)."""
    w = rbf_weights(lights, lights, sigma)
    n = len(lights)
    lhs = w.T @ w + damping ** 2 * np.eye(n)
    flat = table.transpose(1, 0, 2).reshape(n, -1)                   # [L, (P + 1) * 3]
    solved = np.linalg.solve(lhs, w.T @ flat + damping ** 2 * flat)
    out = solved.reshape(n, table.shape[0], 3).transpose(1, 0, 2)
    out[0] = np.clip(out[0], 0.0, 1.0)
    return out


def fit_rbf(stack: SampleStack, planes: int = 9, colorspace: str = "rgb", yplanes: int = 0, sigma: float = 0.0,
            coefficients: str = "lsq", table_mode: str = "interpolating", engine: str = "opencl",
            space: str = "auto"):
    """rbf.fit: PCA table over the lights (``sigma`` 0 and ``space`` auto: chosen together on held-out lights,
    :func:`held_out_choice`; see the stage's docs)."""
    _check_stack(stack, "rbf.fit")
    ycc = _pca_planes(stack, "rbf.fit", planes, colorspace, yplanes, stack.n_light)
    if space == "auto" or not sigma:
        sigmas = [factor * light_spacing(stack.lights) for factor in SIGMA_FACTORS] if not sigma else [sigma]
        space, sigma = held_out_choice(stack, candidate_spaces(stack, space), sigmas, lambda part, sp, value: fit_rbf(
            part, planes, colorspace, yplanes, value, coefficients, table_mode, engine, sp)[0])
    table = pca_table(pca_responses(stack, space), planes, colorspace, ycc)
    if table_mode == "interpolating":
        table = interpolating_table(table, stack.lights, sigma, TABLE_DAMPING)
    projection = coefficients == "projection" and table_mode == "responses"
    model, stats = fit_table(stack, {"kind": "rbf", "table": table, "colorspace": colorspace, "yccplanes": ycc,
                                     "table_lights": stack.lights.astype(np.float32), "sigma": sigma,
                                     "space": space}, engine,
                             np.eye(stack.n_light) if projection else None)
    return model, {**stats, "sigma": sigma}


def _judged_values(stack: SampleStack, space: str) -> tuple[np.ndarray, np.ndarray]:
    """``(y [L, T], truth [L, T])`` float64: the values in ``space`` and the display values of the grid of texels
    ``auto`` choices judge on (colour components folded into ``T``)."""
    grid = held_out_grid(stack)[0]
    like = SampleStack(grid[None], stack.lights, stack.views, stack.channels, stack.encoding)
    y = fitted_values(like, space).reshape(stack.n_light, -1).astype(np.float64)
    return y, display_values(like).reshape(stack.n_light, -1).astype(np.float64)


def _as_display(values: np.ndarray, space: str) -> np.ndarray:
    return np.clip(values if space != "linear" else linear_to_srgb(np.clip(values, 0.0, None)), 0.0, 1.0)


def spline_settings(stack: SampleStack, spaces, smoothness: float) -> tuple[str, float]:
    """(space, smoothing weight) of bilinear.fit's spline resampling: ``smoothness`` (0: each of
    :data:`SPLINE_SMOOTHNESS`) in each of ``spaces``, whichever predicts every fitting light best from the
    others (exact leave-one-out of the linear smoother: the residual over one minus the light's leverage),
    judged on display values of a grid of at most 4096 texels."""
    weights = (smoothness,) if smoothness else SPLINE_SMOOTHNESS
    if stack.n_light < AUTO_MIN_LIGHTS or len(spaces) * len(weights) == 1:
        return spaces[0], smoothness or SPLINE_SMOOTHNESS[len(SPLINE_SMOOTHNESS) // 2]
    scores = {}
    for space in spaces:
        y, truth = _judged_values(stack, space)
        for weight in weights:
            hat = spline_weights(stack.lights, stack.lights, weight)
            leverage = 1.0 - np.diag(hat)
            judged = leverage > 1e-6  # a light the spline passes through whatever it holds cannot be judged
            left_out = y[judged] - (y[judged] - (hat @ y)[judged]) / leverage[judged, None]
            scores[(space, weight)] = float(np.mean((_as_display(left_out, space) - truth[judged]) ** 2))
    return min(scores, key=scores.get)


def spline_side(stack: SampleStack, space: str, smoothness: float, sides=SPLINE_SIDES) -> int:
    """The smallest grid side whose bilinear interpolation of the spline's node values reproduces the spline
    itself to within :data:`SPLINE_SIDE_TOLERANCE` at the directions the lights cover (elevations from the lowest
    light's up), on every eighth texel of the judged grid; the largest side when none does."""
    y = _judged_values(stack, space)[0][:, ::SIDE_JUDGE_STEP]
    unit = stack.lights / np.linalg.norm(stack.lights, axis=1, keepdims=True)
    probes = octa_directions(SPLINE_PROBE_SIDE)
    probes = probes[probes[:, 2] >= unit[:, 2].min() - 1e-9]
    inverse = spline_inverse(stack.lights, smoothness)
    exact = _as_display(spline_weights(stack.lights, probes, smoothness, inverse=inverse) @ y, space)
    for side in sides:
        nodes = spline_weights(stack.lights, octa_directions(side), smoothness, inverse=inverse) @ y
        approx = _as_display(bilinear_weights(probes, side) @ nodes, space)
        if math.sqrt(float(np.mean((approx - exact) ** 2))) <= SPLINE_SIDE_TOLERANCE:
            return side
    return sides[-1]


def nested_split(yccplanes: tuple[int, int, int], count: int) -> tuple[int, int, int] | None:
    """The (Y, Co, Cg) plane counts of the first ``count`` planes of a ycc table split ``yccplanes`` (relight's
    order: (Y, Co, Cg) triplets while chroma planes last, then luma), or None when they end inside a triplet."""
    chroma = yccplanes[1]
    if count <= 3 * chroma:
        return (count // 3,) * 3 if count % 3 == 0 else None
    return (count - 2 * chroma, chroma, chroma) if count - 2 * chroma <= yccplanes[0] else None


def truncation_errors(table: np.ndarray, args: dict, resample: np.ndarray, y: np.ndarray, lights: np.ndarray,
                      space: str) -> np.ndarray:
    """RMS ``[P + 1]`` (display values) by which the first ``p`` planes of ``table`` (relight's projection of the
    values ``y [L, T, 3]`` resampled by ``resample [D, L]``) miss the resampled grid itself at ``lights``: what
    truncating the principal components costs at the fitting lights, for p = 0 .. P."""
    side = int(args["resolution"])
    exact = np.einsum("ld,dm,mtk->ltk", bilinear_weights(lights, side), resample, y, optimize=True)
    lw = table_light_weights(args, lights)                                  # [L, P + 1, 3]
    proj, offset = pca_projection(table, resample, args["colorspace"])
    coeffs = np.einsum("ltk,plk->tp", y, proj) - offset                   # [T, P]
    values = np.broadcast_to(lw[:, None, 0, :], exact.shape).copy()
    target = _as_display(exact, space)
    errors = [math.sqrt(float(np.mean((_as_display(values, space) - target) ** 2)))]
    for p in range(proj.shape[0]):
        values += coeffs[None, :, p, None] * lw[:, None, p + 1, :]
        errors.append(math.sqrt(float(np.mean((_as_display(values, space) - target) ** 2))))
    return np.asarray(errors)


def fewest_planes(stack: SampleStack, table: np.ndarray, args: dict, resample: np.ndarray
                  ) -> tuple[np.ndarray, tuple[int, int, int]]:
    """``planes: 0``: the fewest leading planes of ``table`` (and their ycc split) whose truncation of the
    resampled grid stays within :data:`SPLINE_SIDE_TOLERANCE` RMS at the fitting lights, on the grid of texels
    ``auto`` choices judge on; all of them when none does."""
    space = args["space"]
    grid = held_out_grid(stack)[0]
    like = SampleStack(grid[None], stack.lights, stack.views, stack.channels, stack.encoding)
    y = fitted_values(like, space).reshape(stack.n_light, -1, 3).astype(np.float64)
    errors = truncation_errors(table, args, resample, y, stack.lights, space)
    ycc = args["yccplanes"]
    for count in range(1, table.shape[0]):
        split = nested_split(ycc, count) if args["colorspace"] == "ycc" else (0, 0, 0)
        if split is not None and errors[count] <= SPLINE_SIDE_TOLERANCE:
            return table[:count + 1], split
    return table, ycc


def _planes_needed(planes: int, colorspace: str, yplanes: int) -> int:
    """Grid values one PCA must hold for ``planes`` (0: :data:`AUTO_PLANES`) in ``colorspace``, over 3."""
    count = planes or AUTO_PLANES
    return count if colorspace == "rgb" else 3 * max(ycc_split(count, yplanes))


def auto_plane_cap(colorspace: str, yplanes: int, values: int) -> int:
    """The most planes ``planes: 0`` may keep (at most :data:`AUTO_PLANES`) when one PCA sees ``values``
    independent values per texel and colour component (the fewer of the grid's nodes and the lights)."""
    if colorspace == "rgb":
        return max(1, min(AUTO_PLANES, 3 * values))
    for count in range(AUTO_PLANES, 0, -1):
        try:
            if max(ycc_split(count, yplanes)) <= values:
                return count
        except BtforgeInputError:  # yplanes leaves an odd number of chroma planes: not a count to keep
            continue
    return AUTO_PLANES  # nothing fits: the plane check names the problem


def bilinear_resample(stack: SampleStack, resampling: str, resolution: int, smoothness: float, sigma: float,
                      regularization: float) -> tuple[np.ndarray, float]:
    """``(resample [D, L], smoothness as used)``: how each texel's samples become the grid's values."""
    if resampling == "spline":
        return spline_weights(stack.lights, octa_directions(resolution), smoothness), smoothness
    if resampling == "smooth":
        smoothness = smoothness or SMOOTH_RESAMPLING
        return smooth_resample_matrix(stack.lights, resolution, smoothness), smoothness
    return resample_matrix(stack.lights, resolution, sigma, regularization), smoothness


def fit_bilinear(stack: SampleStack, planes: int = 0, resolution: int = 8, colorspace: str = "rgb", yplanes: int = 0,
                 sigma: float = 0.125, regularization: float = 0.1, coefficients: str = "projection",
                 resampling: str = "spline", smoothness: float = 0.0, engine: str = "opencl", space: str = "auto"):
    """bilinear.fit: PCA table on the light grid (spline resampling: space and smoothing by leave-one-out,
    :func:`spline_settings`, ``resolution`` 0 by :func:`spline_side`; the others: ``resolution`` 0 and ``space``
    auto chosen together on held-out lights, :func:`held_out_choice`; ``planes`` 0 by :func:`fewest_planes`)."""
    _check_stack(stack, "bilinear.fit")
    need = _planes_needed(planes, colorspace, yplanes)
    if resampling == "spline":
        space, smoothness = spline_settings(stack, candidate_spaces(stack, space), smoothness)
        resolution = resolution or spline_side(stack, space, smoothness,
                                               tuple(r for r in SPLINE_SIDES if need <= 3 * r * r) or SPLINE_SIDES[-1:])
    elif space == "auto" or not resolution:
        sides = [resolution] if resolution else [r for r in RESOLUTIONS if need <= 3 * r * r] or [RESOLUTIONS[-1]]
        space, resolution = held_out_choice(stack, candidate_spaces(stack, space), sides, lambda part, sp, value:
                                            fit_bilinear(part, planes, value, colorspace, yplanes, sigma,
                                                         regularization, coefficients, resampling, smoothness,
                                                         engine, sp)[0])
    count = planes or auto_plane_cap(colorspace, yplanes, min(resolution * resolution, stack.n_light))
    ycc = _pca_planes(stack, "bilinear.fit", count, colorspace, yplanes, resolution * resolution)
    resample, smoothness = bilinear_resample(stack, resampling, resolution, smoothness, sigma, regularization)
    table = pca_table(pca_responses(stack, space), count, colorspace, ycc, resample)
    args = {"kind": "bilinear", "table": table, "colorspace": colorspace, "yccplanes": ycc, "resolution": resolution,
            "space": space}
    if not planes:
        args["table"], args["yccplanes"] = fewest_planes(stack, table, args, resample)
    model, stats = fit_table(stack, args, engine, resample if coefficients == "projection" else None)
    return model, {**stats, "resolution": resolution, "smoothness": smoothness, "resampling": resampling}


__all__ = ["fit_hsh", "fit_rbf", "fit_bilinear", "fit_table", "least_squares", "project_numpy", "project_opencl",
           "hsh_table", "pca_table", "octa_directions", "table_weights", "colour_matrix"]
