"""The PTM reflectance model and its fit, with OpenCL kernels (``ptm.cl``) and their NumPy twins.

A polynomial texture map (Malzbender et al. 2001) stores per texel a biquadratic in the light's projected
direction ``(lu, lv)``: terms ``(lu^2, lv^2, lu*lv, lu, lv, 1)``.  Variant ``rgb`` has one polynomial per
channel; ``lrgb`` one luminance polynomial scaled by a per-texel colour.  ``space`` says what the polynomial
evaluates to: ``linear`` radiance, or ``srgb`` display values (what ``.ptm`` files hold) that are clipped to
[0, 1] and decoded to linear on evaluation.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import ClassVar

import numpy as np

from btforge.backend import get_backend
from btforge.buffers import (SRGB8_TO_LINEAR, ReflectanceModel, SampleStack, check_array, frozen,
                             linear_to_srgb, scattered_lookup, srgb_to_linear, unit_directions)
from btforge.errors import BtforgeInputError
from btforge.fitspace import (AUTO_MIN_LIGHTS, auto_grid_step, best_of, best_ridge, held_out_folds, held_out_grid,
                              leave_one_out_errors_of_gram, resolve_space, ridge_by_leave_one_out, ridge_solve,
                              scored)
from btforge.numerics import texel_chunks

from .legendre import to_orthonormal, to_raw

KERNELS = Path(__file__).with_name("ptm.cl")
N_TERMS = 6
MAX_CHANNELS = 4  # the kernels keep per-channel accumulators in registers
VARIANTS = ("lrgb", "rgb")
SPACES = ("linear", "srgb")
BASES = ("raw", "orthonormal")


def ptm_terms(lights: np.ndarray) -> np.ndarray:
    """The six PTM basis terms at each unit light ``[L, 3]`` -> ``[L, 6]`` float64."""
    u = np.asarray(lights, dtype=np.float64)[:, 0]
    v = np.asarray(lights, dtype=np.float64)[:, 1]
    return np.stack([u * u, v * v, u * v, u, v, np.ones_like(u)], axis=1)


@dataclasses.dataclass(frozen=True, eq=False)
class PTMModel(ReflectanceModel):
    """Per-texel polynomial texture map.

    ``coeffs`` is ``[H, W, K, 6]`` float32 (K = channels for ``rgb``, 1 for ``lrgb``); ``albedo`` is the
    ``[H, W, C]`` colour of an ``lrgb`` model (``[H, W, 0]`` for ``rgb``).
    """

    type_name: ClassVar[str] = "PTMModel"
    texel_fields: ClassVar[tuple[str, ...]] = ("coeffs", "albedo")

    coeffs: np.ndarray
    albedo: np.ndarray
    variant: str = "rgb"
    space: str = "linear"
    channel_names: tuple[str, ...] = ("R", "G", "B")
    basis: str = "raw"

    def __post_init__(self):
        owner = "PTMModel"
        if self.basis not in BASES:
            raise BtforgeInputError(f"{owner} 'basis'", f"must be one of {BASES}, got {self.basis!r}")
        if self.variant not in VARIANTS:
            raise BtforgeInputError(f"{owner} 'variant'", f"must be one of {VARIANTS}, got {self.variant!r}")
        if self.space not in SPACES:
            raise BtforgeInputError(f"{owner} 'space'", f"must be one of {SPACES}, got {self.space!r}")
        n_channel = len(self.channel_names)
        if not 1 <= n_channel <= MAX_CHANNELS:
            raise BtforgeInputError(f"{owner} 'channel_names'", f"must name 1 to {MAX_CHANNELS} channels, got {n_channel}")
        k = 1 if self.variant == "lrgb" else n_channel
        check_array("coeffs", self.coeffs, ("H", "W", k, N_TERMS), np.float32, finite=True, owner=owner)
        h, w = self.coeffs.shape[:2]
        albedo_channels = n_channel if self.variant == "lrgb" else 0
        check_array("albedo", self.albedo, (h, w, albedo_channels), np.float32, finite=True, owner=owner)
        object.__setattr__(self, "coeffs", frozen(self.coeffs))
        object.__setattr__(self, "albedo", frozen(self.albedo))
        object.__setattr__(self, "channel_names", tuple(self.channel_names))

    @property
    def channels(self) -> tuple[str, ...]:
        return self.channel_names

    @property
    def blendable(self) -> bool:
        # An lrgb texel is colour x polynomial: blending the two separately is not blending the functions.  An
        # srgb polynomial is decoded per light after evaluation, so its coefficients do not mix like radiance.
        return self.variant == "rgb" and self.space == "linear"

    @property
    def mixes_records(self) -> bool:
        # rgb coefficients are linear in each channel's value before the clip and decode: an srgb mix cross-fades
        # the display values, as a viewer that filters the coefficient planes does.
        return self.variant == "rgb"

    def mixing_form(self) -> "PTMModel | None":
        """An lrgb PTM as the rgb PTM of the same functions (each channel's polynomial is its colour times the
        luminance polynomial, in the same space), whose coefficients mix as the functions' values do."""
        if self.variant != "lrgb":
            return super().mixing_form()   # itself
        coeffs = self.albedo[:, :, :, None] * self.coeffs  # [H, W, C, 6]: albedo [H, W, C] x luminance [H, W, 1, 6]
        empty = np.zeros(self.coeffs.shape[:2] + (0,), np.float32)
        return dataclasses.replace(self, coeffs=coeffs.astype(np.float32), albedo=empty, variant="rgb")

    def with_basis(self, basis: str) -> "PTMModel":
        """The same functions with coefficients in the ``raw`` or ``orthonormal`` (Legendre) basis."""
        if basis == self.basis:
            return self
        convert = to_orthonormal if basis == "orthonormal" else to_raw
        return dataclasses.replace(self, coeffs=convert(self.coeffs), basis=basis)

    def evaluate(self, lights: np.ndarray, views: np.ndarray | None = None, *, engine: str = "opencl") -> np.ndarray:
        lights = unit_directions("lights", lights, owner="PTM evaluation")
        raw = self.with_basis("raw")
        flat_coeffs = raw.coeffs.reshape(-1, self.coeffs.shape[2], N_TERMS)
        flat_albedo = self.albedo.reshape(self.height * self.width, self.albedo.shape[2])
        if engine == "numpy":
            flat = evaluate_ptm_numpy(flat_coeffs, flat_albedo, lights, self.variant, self.space)
        else:
            flat = evaluate_ptm_opencl(flat_coeffs, flat_albedo, lights, self.variant, self.space)
        return flat.reshape(1, len(lights), self.height, self.width, len(self.channel_names))


    def appearance_features(self) -> np.ndarray:
        """Coefficients in the orthonormal Legendre basis (Hel-Or et al. 2003), where their distances are the
        polynomials' L2 distances, with the colour of an ``lrgb`` model appended."""
        ortho = self.with_basis("orthonormal")
        parts = [ortho.coeffs.reshape(self.height, self.width, -1)]
        if ortho.albedo.size:
            parts.append(ortho.albedo)
        return np.concatenate(parts, axis=2)

    def evaluation_form(self) -> "PTMModel":
        return self.with_basis("raw")  # the raw terms evaluate without a change of basis

    def evaluate_texels(self, rows: np.ndarray, cols: np.ndarray, lights_local: np.ndarray,
                        views_local: np.ndarray | None = None, *, engine: str = "opencl") -> np.ndarray:
        """Linear radiance ``[N, C]`` float32 of texel ``(rows[i], cols[i])`` at its own light ``lights_local[i]``.

        For renderers: every item has its own texel and its own unit light in that texel's frame (x along the
        columns, y toward row 0, z out of the surface), e.g. one per pixel.  ``views_local`` is ignored: a PTM is
        a function of the light only.  Same arithmetic as :meth:`evaluate` (kernel ``ptm_eval_scattered``).
        """
        rows, cols, lights_local, _ = scattered_lookup(self, rows, cols, lights_local)
        texels = (rows.astype(np.int64) * self.width + cols).astype(np.int32)
        raw = self.with_basis("raw")
        flat_coeffs = raw.coeffs.reshape(-1, self.coeffs.shape[2], N_TERMS)
        flat_albedo = self.albedo.reshape(self.height * self.width, self.albedo.shape[2])
        if engine == "numpy":
            return evaluate_ptm_scattered_numpy(flat_coeffs, flat_albedo, texels, lights_local, self.variant, self.space)
        return evaluate_ptm_scattered_opencl(flat_coeffs, flat_albedo, texels, lights_local, self.variant, self.space)


# ----------------------------------------------------------------------------------------------- evaluation


def evaluate_ptm_numpy(coeffs: np.ndarray, albedo: np.ndarray, lights: np.ndarray, variant: str, space: str) -> np.ndarray:
    """Reference evaluation: ``coeffs [N, K, 6]``, ``albedo [N, C]`` -> ``[L, N, C]`` float32 linear."""
    terms = ptm_terms(lights).astype(np.float32)
    poly = np.einsum("li,nki->lnk", terms, coeffs, dtype=np.float32)
    value = albedo[None] * poly if variant == "lrgb" else poly
    value = np.maximum(value, 0.0)
    if space == "srgb":
        value = srgb_to_linear(np.minimum(value, 1.0)).astype(np.float32)
    return value.astype(np.float32)


SRGB_TABLE = srgb_to_linear(np.linspace(0.0, 1.0, 4097)).astype(np.float32)  # matches SRGB_TABLE_STEPS in ptm.cl


def evaluate_ptm_opencl(coeffs: np.ndarray, albedo: np.ndarray, lights: np.ndarray, variant: str, space: str,
                        budget_bytes: int = 256 << 20) -> np.ndarray:
    backend = get_backend()
    kernel = backend.kernel(KERNELS, "ptm_eval")
    n_texel, k, _ = coeffs.shape
    n_channel = albedo.shape[1] if variant == "lrgb" else k
    n_light = len(lights)
    out = np.empty((n_light, n_texel, n_channel), dtype=np.float32)
    lights_dev = backend.to_device(np.ascontiguousarray(lights, dtype=np.float32))
    table_dev = backend.to_device(SRGB_TABLE)
    # Chunk over texels so device buffers stay bounded whatever the image size.
    per_texel = 4 * (k * N_TERMS + max(albedo.shape[1], 1) + n_light * n_channel)
    albedo_src = albedo if albedo.shape[1] else np.zeros((n_texel, 1), np.float32)
    for chunk in texel_chunks(n_texel, per_texel, budget_bytes):
        n = chunk.stop - chunk.start
        c_dev = backend.to_device(coeffs[chunk])
        a_dev = backend.to_device(albedo_src[chunk])
        o_dev = backend.empty(n_light * n * n_channel * 4)
        backend.run(kernel, (n, n_light), c_dev, a_dev, lights_dev, np.int32(n_light),
                         np.int32(n), np.int32(n_channel), np.int32(variant == "lrgb"), np.int32(space == "srgb"), table_dev, o_dev)
        out[:, chunk] = backend.from_device(o_dev, (n_light, n, n_channel), np.float32)
    return out


def evaluate_ptm_scattered_numpy(coeffs: np.ndarray, albedo: np.ndarray, texels: np.ndarray, lights: np.ndarray,
                                 variant: str, space: str) -> np.ndarray:
    """Reference scattered evaluation: texel ``texels[i]`` of ``coeffs [T, K, 6]`` at ``lights[i]`` -> ``[N, C]``."""
    terms = ptm_terms(lights).astype(np.float32)
    poly = np.einsum("ni,nki->nk", terms, coeffs[texels], dtype=np.float32)
    value = albedo[texels] * poly if variant == "lrgb" else poly
    value = np.maximum(value, 0.0)
    if space == "srgb":
        value = srgb_to_linear(np.minimum(value, 1.0)).astype(np.float32)
    return value.astype(np.float32)


def evaluate_ptm_scattered_opencl(coeffs: np.ndarray, albedo: np.ndarray, texels: np.ndarray, lights: np.ndarray,
                                  variant: str, space: str) -> np.ndarray:
    """Scattered evaluation on OpenCL (kernel ``ptm_eval_scattered``); the model is read in place, not copied."""
    backend = get_backend()
    kernel = backend.kernel(KERNELS, "ptm_eval_scattered")
    n_channel = albedo.shape[1] if variant == "lrgb" else coeffs.shape[1]
    n = len(texels)
    out = np.empty((n, n_channel), dtype=np.float32)
    if n == 0:
        return out
    albedo_src = albedo if albedo.shape[1] else np.zeros(1, np.float32)
    o_dev = backend.host_output(out)
    backend.run(kernel, (n,), backend.host_input(coeffs), backend.host_input(albedo_src),
                backend.to_device(np.ascontiguousarray(texels, np.int32)), backend.to_device(lights),
                np.int32(n), np.int32(n_channel), np.int32(variant == "lrgb"), np.int32(space == "srgb"),
                backend.to_device(SRGB_TABLE), o_dev)
    backend.finish_output(o_dev, out)
    return out


# ----------------------------------------------------------------------------------------------- fitting


# Dome and hand-held captures keep every singular value above ~0.06 x the largest (even 8 random lights; real
# captures 0.14-0.2), while one-elevation, grazing-only and clustered sets fall below 0.01.
DEFAULT_RCOND = 1e-2


@dataclasses.dataclass(frozen=True)
class PTMSolve:
    """The per-light weights that turn samples into coefficients (a regularised pseudo-inverse)."""

    solve: np.ndarray   # [6, L]
    design: np.ndarray  # [L, 6]
    condition_number: float
    clamped: int        # how many singular values fell below the floor (their directions are left out)
    ridge: float = 0.0  # the ridge weight (times the largest squared singular value)
    penalty: float = 0.0  # lambda = ridge x the largest squared singular value

    def gram(self) -> np.ndarray:
        """``D^T D + lambda I`` (float64): with it, ``a^T G s_c`` of a projection ``s_c = solve y_c`` is the
        correlation ``(D a)^T y_c`` of the polynomial ``a`` with the samples, ridge or not."""
        design = self.design.astype(np.float64)
        return design.T @ design + self.penalty * np.eye(N_TERMS)


_SOLVERS: dict[tuple, PTMSolve] = {}  # the last few solvers: every band of a streamed fit asks for the same one


def ptm_solver(lights: np.ndarray, rcond: float = DEFAULT_RCOND, ridge: float = 0.0) -> PTMSolve:
    """Pseudo-inverse of the PTM design matrix, dropping singular values below ``rcond`` x the largest, with a
    ridge ``ridge x s_max^2`` (``btforge.fitspace.ridge_solve``; 0: plain least squares).

    Light sets that barely vary in one direction (all at one elevation, clustered, grazing) make the design
    matrix nearly singular.  The samples say almost nothing along such a direction, so its coefficient is left
    at zero (the minimum-norm solution) rather than fitted to noise: dividing by a small singular value - even
    one raised to the floor - would amplify that noise by up to 1 / rcond at lights that were not measured.
    """
    lights = np.asarray(lights, dtype=np.float64)
    if len(lights) < N_TERMS:
        raise BtforgeInputError(
            "ptm.fit", f"expected at least {N_TERMS} lights for a 6-coefficient PTM, found {len(lights)}",
            "capture more lights, or use a representation with fewer coefficients")
    key = (lights.shape, lights.tobytes(), float(rcond), float(ridge))
    solver = _SOLVERS.get(key)
    if solver is None:
        if len(_SOLVERS) >= 4:
            _SOLVERS.pop(next(iter(_SOLVERS)))
        solver = _SOLVERS[key] = _new_solver(lights, rcond, ridge)
    return solver


def _new_solver(lights: np.ndarray, rcond: float, ridge: float) -> PTMSolve:
    design = ptm_terms(lights)
    s = np.linalg.svd(design, compute_uv=False)
    floor = s[0] * rcond
    condition = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    clamped = int((s < floor).sum())
    solve = ridge_solve(design, ridge, rcond).astype(np.float32)
    design = design.astype(np.float32)
    solve.flags.writeable = design.flags.writeable = False  # shared by every caller with these lights
    return PTMSolve(solve, design, condition, clamped, float(ridge), float(ridge * s[0] ** 2))


def _kernel_input(stack: SampleStack, space: str):
    """How the kernel reads the samples: ``(lut, byte_scale, convert)``.

    An 8-bit capture is fitted in place: in display space its bytes are numbers scaled by ``byte_scale = 1 / 255``
    (folded into the weights), in linear space they are decoded by a 256-entry table (``lut``) inside the kernel.
    Only a linear stack fitted in display space needs its values converted, band by band.
    """
    if stack.encoding == "srgb8":
        if space == "srgb":
            return None, 1.0 / 255.0, None
        return np.ascontiguousarray(SRGB8_TO_LINEAR, np.float32), 1.0, None
    if space == "linear":
        return None, 1.0, None
    return None, 1.0, lambda band: linear_to_srgb(band).astype(np.float32)


BYTE_LEVELS = (np.arange(256, dtype=np.float32) / 255.0)


def fit_ptm_numpy(samples: np.ndarray, lut: np.ndarray | None, solver: PTMSolve, variant: str):
    """Reference fit of ``samples [L, N, C]`` -> ``(coeffs [N, K, 6], albedo [N, C or 0])`` float32."""
    values = (lut[samples] if lut is not None else samples).astype(np.float64)
    solve = solver.solve.astype(np.float64)
    if variant == "rgb":
        coeffs = np.einsum("kl,lnc->nck", solve, values)
        return coeffs.astype(np.float32), np.zeros((values.shape[1], 0), np.float32)
    luminance = values.mean(axis=2)                                   # [L, N]
    coeffs = solve @ luminance                                        # [6, N]
    poly = solver.design.astype(np.float64) @ coeffs                  # [L, N]
    # the polynomial's energy over the lights plus its ridge penalty: the colour scale is a ridge fit too
    pp = (poly * poly).sum(axis=0) + solver.penalty * (coeffs * coeffs).sum(axis=0)   # [N]
    cross = np.einsum("ln,lnc->nc", poly, values)
    scale = np.where(pp[:, None] > 1e-20, np.maximum(cross / np.where(pp > 1e-20, pp, 1.0)[:, None], 0.0), 1.0)
    norm = np.maximum(scale.max(axis=1), 1.0)
    albedo = scale / norm[:, None]
    coeffs = (coeffs * norm[None]).T[:, None, :]
    return coeffs.astype(np.float32), albedo.astype(np.float32)


def project_numpy(samples: np.ndarray, lut: np.ndarray | None, solver: PTMSolve, light_offset: int = 0) -> np.ndarray:
    """Twin of kernel ``ptm_project``: ``samples [B, N, C]`` of lights ``light_offset ..`` -> ``[N, C, 6]`` float32,
    the projections ``sum_l solve[k, l] * y[l, n, c]``."""
    values = (lut[samples] if lut is not None else samples).astype(np.float64)
    solve = solver.solve[:, light_offset:light_offset + len(samples)].astype(np.float64)
    return np.einsum("kl,lnc->nck", solve, values).astype(np.float32)


def finish_lrgb(sums: np.ndarray, solver: PTMSolve) -> tuple[np.ndarray, np.ndarray]:
    """Twin of kernel ``ptm_finish_lrgb`` (float64): an lrgb PTM from the per-channel projections ``sums [N, C, 6]``: ``(coeffs [N, 1, 6], albedo [N, C])``.

    The luminance polynomial ``a`` is the channel mean of the projections (the fit is linear), and with the Gram
    matrix ``G = D^T D + lambda I`` of the design ``D`` (:meth:`PTMSolve.gram`) its energy over the lights plus
    its ridge penalty is ``a^T G a`` and its correlation with channel ``c`` is ``a^T G s_c`` - the sums the kernel
    of the whole stack forms over every light, without the samples.  (``a`` lies in the span the regularised
    solve keeps, so ``G`` loses nothing there.)  The colour is
    then the non-negative least-squares scale per channel, kept in [0, 1] by moving any excess into ``a``.
    """
    gram = solver.gram()
    s64 = sums.astype(np.float64)
    luminance = s64.mean(axis=1)                                          # [N, 6]
    g_lum = luminance @ gram
    pp = (luminance * g_lum).sum(axis=1)                                  # [N]
    cross = np.einsum("nck,nk->nc", s64, g_lum)
    scale = np.where(pp[:, None] > 1e-20, np.maximum(cross / np.where(pp > 1e-20, pp, 1.0)[:, None], 0.0), 1.0)
    norm = np.maximum(scale.max(axis=1), 1.0)
    return (luminance * norm[:, None])[:, None, :].astype(np.float32), (scale / norm[:, None]).astype(np.float32)


class PTMProjection:
    """Sums of the PTM projections of ``n_texel`` texels, added a batch of lights at a time, then finished.

    ``add`` takes the samples of consecutive lights (an image or a few, as they decode, or a whole stack at once)
    and runs kernel ``ptm_project`` on them; the samples can be dropped afterwards.  An rgb PTM sums straight into
    its coefficients.  ``finish`` returns ``(coeffs [N, K, 6], albedo [N, C or 0])``.  ``lut`` decodes bytes to
    the fitted values; ``byte_scale`` (instead of a table) multiplies the weights, so bytes are read as numbers
    (display space: ``1 / 255``), which the kernel does several times faster than table lookups.
    """

    def __init__(self, n_texel: int, n_channel: int, variant: str, solver: PTMSolve, lut: np.ndarray | None,
                 coeffs: np.ndarray | None = None, albedo: np.ndarray | None = None, byte_scale: float = 1.0):
        self.variant, self.solver, self.lut = variant, solver, lut
        self.n_texel, self.n_channel = n_texel, n_channel
        k = 1 if variant == "lrgb" else n_channel
        self.coeffs = coeffs if coeffs is not None else np.empty((n_texel, k, N_TERMS), np.float32)
        self.albedo = albedo if albedo is not None else np.empty((n_texel, n_channel if variant == "lrgb" else 0),
                                                                 np.float32)
        self.sums = self.coeffs if variant == "rgb" else np.empty((n_texel, n_channel, N_TERMS), np.float32)
        self.lights_added = 0
        backend = self._backend = get_backend()
        weights = (solver.solve.T.astype(np.float64) * byte_scale).astype(np.float32)
        self._weights = backend.to_device(np.ascontiguousarray(weights))
        self._lut = backend.to_device(lut if lut is not None else np.zeros(1, np.float32))
        flags = backend.cl.mem_flags
        self._sums = backend.cl.Buffer(backend.context, flags.READ_WRITE | flags.USE_HOST_PTR, hostbuf=self.sums)

    def add(self, samples: np.ndarray, texel_offset: int = 0, *, wait: bool = True):
        """Add the next lights' ``samples [B, T, C]`` (uint8 or float32, C-contiguous); texels
        ``texel_offset .. texel_offset + n_texel`` of them are this projection's.

        With ``wait=False`` the kernel is only queued: ``samples`` must then stay untouched until the returned
        :meth:`done` callable has been called (launches run in order, so sums still add up in light order).
        """
        backend = self._backend
        options = (f"-DSAMPLE_T={'uchar' if samples.dtype == np.uint8 else 'float'}",) + (
            ("-DUSE_LUT",) if self.lut is not None else ())
        kernel = backend.kernel(KERNELS, "ptm_project", options)
        n_batch, n_sample_texel, n_channel = samples.shape
        n_element = self.n_texel * n_channel
        device_samples = backend.host_input(samples)
        kernel.set_args(device_samples, self._lut, self._weights, np.int32(n_batch), np.int32(self.lights_added),
                        np.int64(n_sample_texel * n_channel), np.int64(texel_offset * n_channel),
                        np.int64(n_element), np.int32(self.lights_added > 0), self._sums)
        event = backend.cl.enqueue_nd_range_kernel(backend.queue, kernel, (-(-n_element // 8),), None)
        self.lights_added += n_batch

        def done() -> None:
            event.wait()
            device_samples.release()
        if wait:
            done()
        return done

    def finish(self) -> tuple[np.ndarray, np.ndarray]:
        if self.lights_added != self.solver.solve.shape[1]:
            raise BtforgeInputError("ptm.fit", f"expected samples of {self.solver.solve.shape[1]} lights, "
                                    f"found {self.lights_added}", "a bug in the caller: add every light once")
        backend = self._backend
        if self.variant == "lrgb":
            gram = self.solver.gram()
            c_dev, a_dev = backend.host_output(self.coeffs), backend.host_output(self.albedo)
            backend.run(backend.kernel(KERNELS, "ptm_finish_lrgb"), (self.n_texel,), self._sums,
                        backend.to_device(gram.astype(np.float32)), np.int32(self.n_texel), np.int32(self.n_channel),
                        c_dev, a_dev)
            backend.finish_output(c_dev, self.coeffs)
            backend.finish_output(a_dev, self.albedo)
            self._sums = self.sums = None
        else:
            backend.finish_output(self._sums, self.sums)
        return self.coeffs, self.albedo


def _fit_texels(samples, variant, solver, lut, byte_scale, convert, engine, coeffs, albedo, budget_bytes) -> None:
    """Fit ``samples [L, N, C]`` into ``coeffs [N, K, 6]`` and ``albedo [N, C or 0]``."""
    n_light, n_texel, c = samples.shape
    if engine == "numpy":
        reference_lut = BYTE_LEVELS if byte_scale != 1.0 else lut  # the twin reads bytes through a table
        for texels in texel_chunks(n_texel, n_light * c * 8, budget_bytes):  # the reference works in float64
            band = samples[:, texels]
            coeffs[texels], albedo[texels] = fit_ptm_numpy(convert(band) if convert else band, reference_lut,
                                                           solver, variant)
    elif convert is None and variant == "rgb":
        projection = PTMProjection(n_texel, c, variant, solver, lut, coeffs, albedo, byte_scale)
        projection.add(samples)  # all texels in one launch, read in place
        projection.finish()
    else:  # bands of texels: a converted band is a copy, an lrgb band keeps 6 sums per channel until finished
        per_texel = n_light * c * 8 if convert else c * N_TERMS * 16
        for texels in texel_chunks(n_texel, per_texel, budget_bytes):
            projection = PTMProjection(texels.stop - texels.start, c, variant, solver, lut, coeffs[texels],
                                       albedo[texels], byte_scale)
            if convert:
                projection.add(np.ascontiguousarray(convert(samples[:, texels])))
            else:
                projection.add(samples, texel_offset=texels.start)
            projection.finish()


def ptm_space(stack: SampleStack, variant: str, space: str, *, rcond: float = DEFAULT_RCOND) -> str:
    """The space ``fit_ptm`` fits in: ``space``, or for ``auto`` the one whose fit predicts held-out lights of a
    grid of texels better (``btforge.fitspace.held_out_space``, scored by :func:`ptm_held_out_errors`)."""
    if space != "auto":
        return space
    if stack.encoding != "srgb8" or stack.n_light < AUTO_MIN_LIGHTS:
        return resolve_space(stack, "auto")  # linear capture, or too few lights to hold any out
    return ptm_held_out_errors(held_out_grid(stack), stack, variant, rcond)[0]


def ptm_held_out_errors(grid: np.ndarray, like: SampleStack, variant: str,
                        rcond: float = DEFAULT_RCOND) -> tuple[str, dict]:
    """``auto``'s choice of space on 8-bit samples ``grid [1, L, h, w, C]`` of a texel grid (``like``'s lights and
    channels), and each space's mean squared error of held-out display values: the scores of
    :func:`btforge.fitspace.best_held_out` for ``fit_ptm`` of each fold in each space (with its own ``ridge:
    auto``) evaluated at the lights it holds out, computed in float64 on the host without building models.

    An rgb fit is linear in its samples, so every fold's predictions of the lights it holds out are rows of one
    ``L x L`` matrix applied to the samples of all lights (a fold's row is zero at the lights it holds out), and
    each fold's ridge is scored on the fold's block of one Gram matrix of all lights
    (:func:`btforge.fitspace.leave_one_out_errors_of_gram`): a few products per space, not a fit per fold.
    """
    from btforge.backend import single_threaded_blas
    raw = np.asarray(grid[0])
    squared = {}
    with single_threaded_blas():  # small products: BLAS threads only spin against busy cores
        for space in ("srgb", "linear"):
            predicted = _held_out_predictions(_grid_values(grid, like.encoding, space), like.lights, variant, rcond)
            squared[space] = 0.0
            for start in range(0, len(raw), 8):  # a few lights at a time: small temporaries
                lights = slice(start, start + 8)
                display = np.clip(predicted[lights], 0.0, 1.0) if space == "srgb" else linear_to_srgb(predicted[lights])
                target = scored(raw[lights], like.encoding).reshape(len(display), -1)
                squared[space] += float(np.sum((display - target) ** 2))
    return best_of(squared, raw.size)


def _held_out_predictions(values: np.ndarray, lights: np.ndarray, variant: str, rcond: float) -> np.ndarray:
    """``[L, h * w * C]``: each light's samples as predicted by ``fit_ptm`` of its fold (the other lights, with
    ``ridge: auto``) from ``values [L, h, w, C]`` (float64, in the space fitted), before clipping."""
    n_light = len(values)
    flat = values.reshape(n_light, -1)
    step = auto_grid_step(*values.shape[1:3])  # the grid a fold's ridge is judged on (held_out_grid of the fold)
    ridge_values = flat if step == 1 else values[:, ::step, ::step].reshape(n_light, -1)
    gram = ridge_values @ ridge_values.T
    weights = np.zeros((n_light, n_light))    # rgb: prediction = weights @ samples
    predicted = None if variant == "rgb" else np.empty_like(flat)
    for held in held_out_folds(n_light):
        keep, out = np.flatnonzero(~held), np.flatnonzero(held)
        errors = leave_one_out_errors_of_gram(ptm_terms(lights[keep]), gram[np.ix_(keep, keep)],
                                              ridge_values.shape[1], rcond=rcond)
        solver = ptm_solver(lights[keep], rcond, best_ridge(errors)[0])
        held_terms = ptm_terms(lights[out])
        if variant == "rgb":
            weights[np.ix_(out, keep)] = held_terms @ solver.solve.astype(np.float64)
            continue
        samples = values[keep].reshape(len(keep), -1, values.shape[-1])
        coeffs, albedo = fit_ptm_numpy(samples, None, solver, variant)    # lrgb: colour x luminance polynomial
        poly = held_terms @ coeffs[:, 0, :].T.astype(np.float64)           # [L', N]
        predicted[out] = (poly[:, :, None] * albedo.astype(np.float64)[None]).reshape(len(out), -1)
    return weights @ flat if variant == "rgb" else predicted


def ptm_ridge(grid: np.ndarray, like: SampleStack, space: str, rcond: float = DEFAULT_RCOND) -> float:
    """``ridge: auto``: the weight of ``btforge.fitspace.RIDGE_WEIGHTS`` whose fits best predict each light left
    out of the samples ``grid [1, L, h, w, C]`` of a texel grid (``like``'s lights and encoding), in ``space``
    (closed-form leave-one-out, :func:`btforge.fitspace.ridge_by_leave_one_out`)."""
    values = _grid_values(grid, like.encoding, space)
    # Every term is penalised, the constant too: it is the value at the zenith, not the mean, and shrinking it
    # with the rest predicted held-out lights of the real captures measured better (docs, Benchmarks).
    return ridge_by_leave_one_out(ptm_terms(like.lights), values.reshape(like.n_light, -1), rcond=rcond)[0]


def _grid_values(grid: np.ndarray, encoding: str, space: str) -> np.ndarray:
    """Samples ``[V, L, ...]`` of a texel grid in the space fitted (float64)."""
    raw = np.asarray(grid[0])
    if encoding == "srgb8":
        return SRGB8_TO_LINEAR[raw].astype(np.float64) if space == "linear" else raw / 255.0
    return raw.astype(np.float64) if space == "linear" else linear_to_srgb(raw).astype(np.float64)


def ptm_settings(stack: SampleStack, variant: str, space: str, ridge, *,
                 rcond: float = DEFAULT_RCOND) -> tuple[str, float]:
    """The space and ridge weight ``fit_ptm`` uses: the given ones, or ``auto``'s choices on a grid of texels."""
    space = ptm_space(stack, variant, space, rcond=rcond)
    if ridge == "auto":
        ridge = ptm_ridge(held_out_grid(stack), stack, space, rcond)
    return space, float(ridge)


def check_ridge(ridge, owner: str = "ptm.fit") -> None:
    if ridge == "auto":
        return
    if isinstance(ridge, bool) or not isinstance(ridge, (int, float)) or not 0 <= ridge <= 1:
        raise BtforgeInputError(f"{owner} 'ridge'", f"expected 'auto' or a number in [0, 1], found {ridge!r}",
                                "use auto (chosen by leave-one-out on a grid of texels) or e.g. 0.001")


def fit_ptm(stack: SampleStack, variant: str = "rgb", space: str = "auto", *, engine: str = "opencl",
            rcond: float = DEFAULT_RCOND, ridge="auto", budget_bytes: int = 64 << 20,
            output_array=None) -> tuple[PTMModel, PTMSolve]:
    """Regularised least-squares PTM fit of a single-view stack (``ridge``: a weight, or ``auto``).

    The OpenCL path reads an 8-bit or linear capture in place and writes coefficients straight into the
    result, so memory stays near the stack plus its coefficients; other paths go band by band, and so does a
    stack read from a store (``stack.chunked``), one band of chunk rows at a time.  ``output_array(name, shape,
    dtype)`` gives the arrays the result is computed into (a stage passes ``ctx.output_array``); default new ones.
    """
    if stack.n_view != 1:
        raise BtforgeInputError(
            "ptm.fit 'stack'", f"expected a single-view stack (a PTM depends on the light only), found {stack.n_view} views",
            "pick one view with a stackio.select node before the fit, e.g. `pick: {stage: stackio.select, params: "
            "{views: [0]}, inputs: {stack: NODE.stack}}` (or a view by its angles, views: ['tv0_pv0']), or fit a "
            "view-dependent representation such as sh.fit or lafortune.fit")
    if stack.n_channel > MAX_CHANNELS:
        raise BtforgeInputError("ptm.fit 'stack'", f"expected at most {MAX_CHANNELS} channels, found {stack.n_channel}")
    check_ridge(ridge)
    space, ridge = ptm_settings(stack, variant, space, ridge, rcond=rcond)
    solver = ptm_solver(stack.lights, rcond, ridge)
    h, w, c = stack.height, stack.width, stack.n_channel
    k = 1 if variant == "lrgb" else c
    output_array = output_array or (lambda name, shape, dtype: np.empty(shape, dtype))
    coeffs = output_array("coeffs", (h * w, k, N_TERMS), np.float32)
    albedo = output_array("albedo", (h * w, c if variant == "lrgb" else 0), np.float32)
    lut, byte_scale, convert = _kernel_input(stack, space)
    if stack.chunked:  # a store: one band of chunk rows at a time, each fitted like a whole stack
        for rows in stack.row_bands(budget_bytes):
            texels = slice(rows.start * w, rows.stop * w)
            part = np.ascontiguousarray(stack.samples[0, :, rows]).reshape(stack.n_light, -1, c)
            _fit_texels(part, variant, solver, lut, byte_scale, convert, engine, coeffs[texels], albedo[texels],
                        budget_bytes)
    else:
        samples = stack.samples[0].reshape(stack.n_light, h * w, c)  # a view of the capture, read in place
        _fit_texels(samples, variant, solver, lut, byte_scale, convert, engine, coeffs, albedo, budget_bytes)
    model = PTMModel(coeffs.reshape(h, w, k, N_TERMS), albedo.reshape(h, w, albedo.shape[1]), variant, space,
                     stack.channels)
    return model, solver


def _capture_grid(reader) -> np.ndarray:
    """The texel grid ``[1, L, h, w, C]`` ``fit_ptm``'s ``auto`` choices judge on, read in a first pass over the
    images (one image held at a time), so both paths choose alike.  This pass decodes every image once more; an
    explicit ``space`` and ``ridge`` skip it."""
    h, w, c = reader.shape
    step = auto_grid_step(h, w)
    image = np.empty((1, h, w, c), reader.dtype)
    grid = np.empty((1, reader.n_light, len(range(0, h, step)), len(range(0, w, step)), c), reader.dtype)
    for light in range(reader.n_light):
        reader.read_into([(0, light)], image, threads=1)
        grid[0, light] = image[0, ::step, ::step]
    return grid


def _capture_settings(reader, probe: SampleStack, variant: str, space: str, ridge, rcond: float):
    """``fit_ptm_capture``'s space and ridge: the given ones, or ``auto``'s choices on :func:`_capture_grid`."""
    if space != "auto" and ridge != "auto":
        return space, float(ridge)
    grid = _capture_grid(reader)
    if space == "auto":
        if reader.encoding != "srgb8" or reader.n_light < AUTO_MIN_LIGHTS:
            space = resolve_space(probe, "auto")  # linear capture, or too few lights to hold any out
        else:
            space = ptm_held_out_errors(grid, probe, variant, rcond)[0]
    if ridge == "auto":
        ridge = ptm_ridge(grid, probe, space, rcond)
    return space, float(ridge)


def fit_ptm_capture(light_file, variant: str = "rgb", space: str = "auto", *, transfer: str = "auto",
                    rcond: float = DEFAULT_RCOND, ridge="auto", batch_bytes: int = 16 << 20,
                    threads: int = 2) -> tuple[PTMModel, PTMSolve]:
    """The PTM fit of a capture's light file, accumulated as its images decode: the capture is never held whole.

    Images are decoded ``threads`` at a time into one of two batches of about ``batch_bytes / 2`` while the
    kernel (``ptm_project``) projects the other onto the pseudo-inverse, each batch adding onto the sums of the
    lights before it, in light order.  The result is the one of ``fit_ptm(load_stack(light_file))``: the same regularised estimator and,
    for rgb, the same float operations in the same order.  Peak memory is the coefficients plus one batch.
    """
    from btforge.plugins.stackio.images import CaptureReader
    reader = CaptureReader(light_file, transfer=transfer)
    if reader.n_view != 1:
        raise BtforgeInputError(
            f"{light_file}", f"expected a single-view capture (a PTM depends on the light only), found {reader.n_view} "
            "views", "read it with stackio.read and pick one view with stackio.select before ptm.fit")
    h, w, c = reader.shape
    if c > MAX_CHANNELS:
        raise BtforgeInputError("ptm.fit 'stack'", f"expected at most {MAX_CHANNELS} channels, found {c}")
    probe = SampleStack(np.zeros((1, reader.n_light, 1, 1, c), reader.dtype), reader.lights, reader.views,
                        reader.channels, reader.encoding)
    check_ridge(ridge)
    space, ridge = _capture_settings(reader, probe, variant, space, ridge, rcond)
    solver = ptm_solver(reader.lights, rcond, ridge)
    lut, byte_scale, convert = _kernel_input(probe, space)
    # Two half-size batches: the images of one decode while the kernel sums the other.
    batch_size = max(1, min(reader.n_light, batch_bytes // 2 // max(1, h * w * c * reader.dtype.itemsize)))
    batches = [np.empty((batch_size, h * w, c), reader.dtype) for _ in range(2)]
    pending: list = [None, None]
    projection = PTMProjection(h * w, c, variant, solver, lut, byte_scale=byte_scale)
    for index, start in enumerate(range(0, reader.n_light, batch_size)):
        lights = range(start, min(reader.n_light, start + batch_size))
        slot = index % 2
        if pending[slot] is not None:
            pending[slot]()  # the kernel that read this batch has finished
        part = batches[slot][:len(lights)]
        reader.read_into([(0, light) for light in lights], part.reshape(len(lights), h, w, c), threads=threads)
        pending[slot] = projection.add(np.ascontiguousarray(convert(part)) if convert else part, wait=False)
    for done in pending:
        if done is not None:
            done()
    del batches, part
    coeffs, albedo = projection.finish()
    model = PTMModel(coeffs.reshape(h, w, coeffs.shape[1], N_TERMS), albedo.reshape(h, w, albedo.shape[1]),
                     variant, space, reader.channels)
    return model, solver
