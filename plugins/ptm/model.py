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
    for chunk in _chunks(n_texel, per_texel, budget_bytes):
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


def _chunks(n: int, bytes_per_item: int, budget: int):
    step = max(1, min(n, budget // max(bytes_per_item, 1)))
    for start in range(0, n, step):
        yield slice(start, min(n, start + step))


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


def ptm_solver(lights: np.ndarray, rcond: float = DEFAULT_RCOND) -> PTMSolve:
    """Pseudo-inverse of the PTM design matrix, dropping singular values below ``rcond`` x the largest.

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
    design = ptm_terms(lights)
    u, s, vt = np.linalg.svd(design, full_matrices=False)
    floor = s[0] * rcond
    condition = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    clamped = int((s < floor).sum())
    inverse = np.where(s >= floor, 1.0 / np.where(s > 0, s, 1.0), 0.0)
    solve = (vt.T * inverse) @ u.T
    return PTMSolve(solve.astype(np.float32), design.astype(np.float32), condition, clamped)


def resolve_space(stack: SampleStack, space: str) -> str:
    if space == "auto":
        return "srgb" if stack.encoding == "srgb8" else "linear"
    return space


def _kernel_input(stack: SampleStack, space: str):
    """The samples as ``[L, H*W, C]`` (a view of the stack), the byte-decoding table, and a converter if needed.

    Bytes are decoded by a 256-entry table inside the kernel (identity/255 for display space, the sRGB curve
    for linear space), so an 8-bit capture is fitted in place.  Only a linear stack fitted in display space
    needs its values converted, band by band.
    """
    samples = stack.samples[0].reshape(stack.n_light, stack.height * stack.width, stack.n_channel)
    if stack.encoding == "srgb8":
        lut = (np.arange(256, dtype=np.float32) / 255.0) if space == "srgb" else SRGB8_TO_LINEAR
        return samples, np.ascontiguousarray(lut, np.float32), None
    if space == "linear":
        return samples, None, None
    return samples, None, lambda band: linear_to_srgb(band).astype(np.float32)


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
    pp = (poly * poly).sum(axis=0)                                    # [N]
    cross = np.einsum("ln,lnc->nc", poly, values)
    scale = np.where(pp[:, None] > 1e-20, np.maximum(cross / np.where(pp > 1e-20, pp, 1.0)[:, None], 0.0), 1.0)
    norm = np.maximum(scale.max(axis=1), 1.0)
    albedo = scale / norm[:, None]
    coeffs = (coeffs * norm[None]).T[:, None, :]
    return coeffs.astype(np.float32), albedo.astype(np.float32)


def fit_ptm_opencl(samples: np.ndarray, lut: np.ndarray | None, solver: PTMSolve, variant: str,
                   coeffs: np.ndarray, albedo: np.ndarray) -> None:
    """Fit ``samples [L, N, C]`` into the preallocated ``coeffs [N, K, 6]`` and ``albedo [N, C or 0]``.

    Inputs and outputs are handed to the device without copies where it shares host memory (PoCL on a CPU).
    """
    backend = get_backend()
    sample_type = "uchar" if samples.dtype == np.uint8 else "float"
    options = (f"-DSAMPLE_T={sample_type}",) + (("-DUSE_LUT",) if lut is not None else ())
    kernel = backend.kernel(KERNELS, "ptm_fit", options)
    n_light, n_texel, n_channel = samples.shape
    albedo_target = albedo if albedo.size else np.zeros(1, np.float32)
    s_dev = backend.host_input(samples)
    c_dev = backend.host_output(coeffs)
    a_dev = backend.host_output(albedo_target)
    backend.run(kernel, (n_texel,), s_dev, backend.to_device(lut if lut is not None else np.zeros(1, np.float32)),
                backend.to_device(solver.solve), backend.to_device(solver.design), np.int32(n_light),
                np.int32(n_texel), np.int32(0), np.int32(n_texel), np.int32(n_channel), np.int32(variant == "lrgb"),
                c_dev, a_dev)
    backend.finish_output(c_dev, coeffs)
    backend.finish_output(a_dev, albedo_target)


def fit_ptm(stack: SampleStack, variant: str = "rgb", space: str = "auto", *, engine: str = "opencl",
            rcond: float = DEFAULT_RCOND, budget_bytes: int = 64 << 20) -> tuple[PTMModel, PTMSolve]:
    """Least-squares PTM fit of a single-view stack.

    The OpenCL path reads an 8-bit or linear capture in place and writes coefficients straight into the
    result, so memory stays near the stack plus its coefficients; other paths go band by band.
    """
    if stack.n_view != 1:
        raise BtforgeInputError(
            "ptm.fit 'stack'", f"expected a single-view stack (a PTM depends on the light only), found {stack.n_view} views",
            "pick one view with a stack.select node before the fit, e.g. `pick: {stage: stack.select, params: "
            "{views: [0]}, inputs: {stack: NODE.stack}}` (or a view by its angles, views: ['tv0_pv0']), or fit a "
            "view-dependent representation such as sh.fit or lafortune.fit")
    if stack.n_channel > MAX_CHANNELS:
        raise BtforgeInputError("ptm.fit 'stack'", f"expected at most {MAX_CHANNELS} channels, found {stack.n_channel}")
    space = resolve_space(stack, space)
    solver = ptm_solver(stack.lights, rcond)
    h, w, c = stack.height, stack.width, stack.n_channel
    k = 1 if variant == "lrgb" else c
    coeffs = np.empty((h * w, k, N_TERMS), np.float32)
    albedo = np.empty((h * w, c if variant == "lrgb" else 0), np.float32)
    samples, lut, convert = _kernel_input(stack, space)
    if engine == "opencl" and convert is None:
        fit_ptm_opencl(samples, lut, solver, variant, coeffs, albedo)
    else:
        per_texel = stack.n_light * c * 8  # the reference works in float64
        for texels in _chunks(h * w, per_texel, budget_bytes):
            band = samples[:, texels]
            band = convert(band) if convert else band
            if engine == "numpy":
                coeffs[texels], albedo[texels] = fit_ptm_numpy(band, lut, solver, variant)
            else:
                fit_ptm_opencl(np.ascontiguousarray(band), lut, solver, variant, coeffs[texels], albedo[texels])
    model = PTMModel(coeffs.reshape(h, w, k, N_TERMS), albedo.reshape(h, w, albedo.shape[1]), variant, space,
                     stack.channels)
    return model, solver
