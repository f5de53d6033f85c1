"""Double spherical harmonics (view x light) fitted by constrained least squares, optionally 8-bit quantized.

Following Leung et al. ("Tileable BTF", after Lam, Leung & Wong 2006), each texel's reflectance per channel is

    f(l, v) = sum_{a < k_v} sum_{b < k_l} c[a, b] Y_a(v) Y_b(l)

with ``Y`` the orthonormal real spherical harmonics of :func:`real_sh`.  **Order** ``N`` means bands
``0 .. N-1``, i.e. ``N^2`` functions: ``k_l = light_order^2``, ``k_v = view_order^2``.  A single-view stack
(``view_order`` 1) has ``k_v = 1`` and ``Y_0(v) = 1 / sqrt(4 pi)``, so ``f(l) = sum_b (c[0, b] / sqrt(4 pi)) Y_b(l)``:
single SH over the light, with coefficients scaled by ``sqrt(4 pi)``.

**Constrained least squares.**  Samples cover the upper hemisphere only, so plain least squares is free to
make the function large below the horizon (and, at high orders, to blow up fitting noise).  We minimise
``||A c - y||^2 + lambda ||c||^2`` and pick per texel and channel the smallest ``lambda >= 0`` whose solution's
energy ``||c||^2`` (its L2 norm over the whole sphere, or sphere x sphere, as the basis is orthonormal) obeys the
**energy bound**::

    ||c||^2  <=  energy_factor * (4 pi)^2 * mean(y^2)

``2 pi * mean(y^2)`` estimates the energy over a sampled hemisphere (exact when samples are uniform in solid
angle).  The bound allows twice that per sampled hemisphere - the energy of the function's mirror image about
the horizon, i.e. as much below the horizon as above and no more - and a view-independent model (``k_v = 1``) is
constant over the whole view sphere (4 pi).  Both cases give ``(4 pi)^2 mean(y^2)``; ``energy_factor`` scales
it (default :data:`DEFAULT_ENERGY_FACTOR` = 1, the mirror rule; ``inf`` gives plain minimum-norm least squares).
A constant function meets the bound with equality, so the bound carries a relative slack of ``ENERGY_SLACK``
(1e-4) to keep rounding from regularising it.  By Cauchy-Schwarz and the addition theorem
(``sum_b Y_b(l)^2 = k_l / 4 pi``) the bound caps the function everywhere on the sphere(s):
``|f(l, v)| <= ||c|| sqrt(k_l k_v) / (4 pi) = sqrt(energy_factor k_l k_v mean(y^2))``.

``A`` is the same for every texel (``kron(Y_view, Y_light)``), and so is its SVD, the Kronecker product of the two
small SVDs computed once on the host.  With ``p = U^T y`` the solution for any ``lambda`` is
``c = V diag(s / (s^2 + lambda)) p`` and its energy ``sum (s_i p_i / (s_i^2 + lambda))^2`` decreases with
``lambda``, so the per-texel bisection (OpenCL kernel ``sh_lambda``, NumPy twin :func:`cls_weights_numpy`) is
cheap.  Singular values ``s_v[i] s_l[j]`` of the product below ``RCOND`` x the largest are treated as exact zeros
(their weights are 0: the minimum-norm solution ignores those directions).  Applying the cut to each factor alone
would keep products down to ``RCOND^2`` of the largest, which with clustered lights and views lets plain least
squares blow float32 rounding up into huge coefficients.

**Quantization** (optional) stores each coefficient as ``uint8``: per coefficient index ``(a, b)`` over all
texels and channels, ``bias`` is the minimum and ``scale`` the range / 255, values are rounded, so dequantized
coefficients ``q * scale + bias`` are within half a step of the fitted ones.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import ClassVar

import numpy as np

from btforge.backend import get_backend, single_threaded_blas
from btforge.numerics import fibonacci_directions, real_sh, texel_chunks
from btforge.buffers import (SRGB8_TO_LINEAR, ReflectanceModel, SampleStack, check_array, frozen, linear_to_srgb,
                             scattered_lookup, srgb_to_linear, unit_directions)
from btforge.errors import BtforgeInputError
from btforge.fitspace import AUTO_HOLD_EVERY, AUTO_MIN_LIGHTS, best_held_out, held_out_grid, resolve_space
from btforge.spill import finite_range, release, spilled_empty

KERNELS = Path(__file__).with_name("sh.cl")
MAX_ORDER = 10
DEFAULT_ENERGY_FACTOR = 1.0
ENERGY_SLACK = 1e-4   # relative slack on the bound: a constant texel meets it exactly and must not be clamped by rounding
RCOND = 1e-6          # singular values of the design matrix below this x its largest count as zero
LAMBDA_SPAN = 40.0    # bisection over log2(lambda) in [log2(hi) - SPAN, log2(hi)]
LAMBDA_ITERS = 32
# sh.cl defines none of these itself: every build of it gets them from here, so the kernel and its twin agree.
BUILD_OPTIONS = (f"-DLAMBDA_SPAN={LAMBDA_SPAN!r}f", f"-DLAMBDA_ITERS={LAMBDA_ITERS}")
FOUR_PI = 4.0 * math.pi
SPACES = ("linear", "srgb")
AUTO_ORDERS = (2, 3, 4, 5, 6)  # the light orders ``light_order="auto"`` chooses among
# Held-out errors within this fraction of the lowest count as a tie, won by the higher order: the whole stack has
# a quarter more lights than each fold fits, and more lights carry higher orders (measured on the shared real
# captures: the accuracy figures in the docs).
AUTO_ORDER_TIE = 0.05
AUTO_SMOOTHNESS = (0.003, 0.01, 0.03)  # the smoothness weights ``smoothness="auto"`` tries (0 is tried too)


# ----------------------------------------------------------------------------------------------- basis


def compression_rate(k_l: int, k_v: int, n_light: int, n_view: int) -> float:
    """Coefficients per texel and channel over raw samples per texel and channel, at the same bit depth.

    ``compression_rate(25, 25, 81, 81) == 625 / 6561`` (9.53 %, Table II of Leung et al.).
    """
    return (k_l * k_v) / (n_light * n_view)


# ----------------------------------------------------------------------------------------------- model


GRAM_QUADRATURE = 4096  # hemisphere directions of the Gram-matrix quadrature


def hemisphere_gram_root(order: int, n: int = GRAM_QUADRATURE) -> np.ndarray:
    """``S`` with ``S S^T = int_H Y_i Y_j`` over the upper hemisphere, for SH bands ``0 .. order-1``.

    The Gram matrix is summed over ``n`` equal-area Fibonacci points (weight ``2 pi / n`` each); ``S`` is its
    symmetric square root with negative rounding clipped.
    """
    y = real_sh(order, fibonacci_directions(n, 0.0, rising=True))
    values, vectors = np.linalg.eigh((y.T @ y) * (2 * np.pi / n))
    return vectors * np.sqrt(np.clip(values, 0.0, None))


@dataclasses.dataclass(frozen=True, eq=False)
class SHModel(ReflectanceModel):
    """Per-texel double spherical harmonics ``f(l, v) = sum_ab c[a, b] Y_a(v) Y_b(l)`` (see the module docs).

    ``coeffs`` is ``[H, W, C, k_v, k_l]``: float32, or uint8 when ``quantized`` (then the coefficient is
    ``q * scale[a, b] + bias[a, b]``).  ``scale`` / ``bias`` are ``[k_v, k_l]`` float32 (ones / zeros when not
    quantized).  ``k_l = light_order^2``, ``k_v = view_order^2``.
    """

    type_name: ClassVar[str] = "SHModel"
    texel_fields: ClassVar[tuple[str, ...]] = ("coeffs",)

    coeffs: np.ndarray
    scale: np.ndarray
    bias: np.ndarray
    light_order: int = 4
    view_order: int = 1
    quantized: bool = False
    channel_names: tuple[str, ...] = ("R", "G", "B")
    space: str = "linear"

    def __post_init__(self):
        owner = "SHModel"
        for name in ("light_order", "view_order"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= MAX_ORDER:
                raise BtforgeInputError(f"{owner} '{name}'", f"must be an int in [1, {MAX_ORDER}], got {value!r}")
        if self.space not in SPACES:
            raise BtforgeInputError(f"{owner} 'space'", f"must be one of {SPACES}, got {self.space!r}")
        if not isinstance(self.quantized, (bool, np.bool_)):
            raise BtforgeInputError(f"{owner} 'quantized'", f"must be a bool, got {self.quantized!r}")
        k_l, k_v = int(self.light_order) ** 2, int(self.view_order) ** 2
        n_channel = len(self.channel_names)
        if n_channel < 1:
            raise BtforgeInputError(f"{owner} 'channel_names'", "must name at least one channel")
        dtype = np.uint8 if self.quantized else np.float32
        check_array("coeffs", self.coeffs, ("H", "W", n_channel, k_v, k_l), dtype, finite=True, owner=owner)
        check_array("scale", self.scale, (k_v, k_l), np.float32, finite=True, owner=owner)
        check_array("bias", self.bias, (k_v, k_l), np.float32, finite=True, owner=owner)
        if (self.scale < 0).any():
            raise BtforgeInputError(f"{owner} 'scale'", "must be >= 0 (a quantization step)")
        object.__setattr__(self, "light_order", int(self.light_order))
        object.__setattr__(self, "view_order", int(self.view_order))
        object.__setattr__(self, "quantized", bool(self.quantized))
        object.__setattr__(self, "coeffs", frozen(self.coeffs))
        object.__setattr__(self, "scale", frozen(self.scale))
        object.__setattr__(self, "bias", frozen(self.bias))
        object.__setattr__(self, "channel_names", tuple(self.channel_names))

    @property
    def channels(self) -> tuple[str, ...]:
        return self.channel_names

    @property
    def view_dependent(self) -> bool:  # type: ignore[override]
        return self.view_order > 1

    @property
    def blendable(self) -> bool:
        # srgb coefficients describe display values, decoded per direction after evaluation: they do not mix
        # like radiance.
        return self.space == "linear"

    @property
    def mixes_records(self) -> bool:
        return True  # linear in the evaluated values, before an srgb model's clip and decode

    def _radiance(self, values: np.ndarray) -> np.ndarray:
        """Evaluated values -> linear radiance: as they are (linear), or display values clipped to [0, 1] and
        decoded by the sRGB curve."""
        return values if self.space == "linear" else srgb_to_linear(np.minimum(values, 1.0)).astype(np.float32)

    @property
    def k_l(self) -> int:
        return self.light_order ** 2

    @property
    def k_v(self) -> int:
        return self.view_order ** 2

    def dequantized(self) -> np.ndarray:
        """The coefficients as float32 ``[H, W, C, k_v, k_l]`` (the stored ones when not quantized)."""
        if not self.quantized:
            return self.coeffs
        return (self.coeffs.astype(np.float32) * self.scale + self.bias).astype(np.float32)

    def appearance_features(self) -> np.ndarray:
        """``[H, W, C * k_v * k_l]`` float32: the coefficients in a frame orthonormal over the upper hemisphere of
        lights and of views, so Euclidean distance is the L2 distance of the fitted functions where they were
        measured (the full-sphere basis's own orthonormality would also count the unmeasured lower half)."""
        weighted = np.einsum("hwcab,ai,bj->hwcij", self.dequantized().astype(np.float64),
                             hemisphere_gram_root(self.view_order), hemisphere_gram_root(self.light_order))
        return np.ascontiguousarray(weighted.reshape(self.height, self.width, -1), np.float32)

    def evaluate_texels(self, rows: np.ndarray, cols: np.ndarray, lights_local: np.ndarray,
                        views_local: np.ndarray | None = None, *, engine: str = "opencl") -> np.ndarray:
        """Linear radiance ``[N, C]`` float32 of texel ``(rows[i], cols[i])`` at its own light and view (for
        renderers): the host evaluates the SH basis per item, kernel ``sh_eval_scattered`` (``engine="numpy"``:
        its NumPy twin) contracts it with the texel's coefficients."""
        rows, cols, lights_local, views_local = scattered_lookup(self, rows, cols, lights_local, views_local)
        texels = (rows.astype(np.int64) * self.width + cols).astype(np.int32)
        yl = real_sh(self.light_order, lights_local).astype(np.float32)              # [N, k_l]
        yv = real_sh(self.view_order, views_local).astype(np.float32)                # [N, k_v]
        flat = self.coeffs.reshape(self.height * self.width, len(self.channel_names), self.k_v, self.k_l)
        self._check_engine(engine)
        run = evaluate_sh_scattered_numpy if engine == "numpy" else evaluate_sh_scattered_opencl
        return self._radiance(run(flat, self.scale, self.bias, self.quantized, texels, yv, yl))

    @staticmethod
    def _check_engine(engine: str) -> None:
        if engine not in ("opencl", "numpy"):
            raise BtforgeInputError("SH evaluation 'engine'", f"must be 'opencl' or 'numpy', got {engine!r}")

    def evaluate(self, lights: np.ndarray, views: np.ndarray | None = None, *, engine: str = "opencl") -> np.ndarray:
        """Linear radiance ``[V, L, H, W, C]`` float32 at unit ``lights [L, 3]`` and ``views [V, 3]``, clipped at 0.

        ``views`` defaults to the top view ``(0, 0, 1)``.  Directions below the horizon are allowed (the model
        is defined on the whole sphere), though nothing was measured there.
        """
        lights = unit_directions("lights", lights, owner="SH evaluation")
        views = unit_directions("views", [[0.0, 0.0, 1.0]] if views is None else views, owner="SH evaluation")
        yl = real_sh(self.light_order, lights).astype(np.float32)
        yv = real_sh(self.view_order, views).astype(np.float32)
        n_texel = self.height * self.width
        flat = self.coeffs.reshape(n_texel, len(self.channel_names), self.k_v, self.k_l)
        self._check_engine(engine)
        run = evaluate_sh_numpy if engine == "numpy" else evaluate_sh_opencl
        out = self._radiance(run(flat, self.scale, self.bias, self.quantized, yv, yl))
        return out.reshape(len(views), len(lights), self.height, self.width, len(self.channel_names))


# ----------------------------------------------------------------------------------------------- evaluation


def evaluate_sh_numpy(coeffs: np.ndarray, scale: np.ndarray, bias: np.ndarray, quantized: bool,
                      yv: np.ndarray, yl: np.ndarray) -> np.ndarray:
    """Reference evaluation: ``coeffs [N, C, k_v, k_l]`` at basis rows ``yv [V, k_v]``, ``yl [L, k_l]`` -> ``[V, L, N, C]``."""
    c = coeffs.astype(np.float32) * scale + bias if quantized else coeffs
    q = np.matmul(c, yl.T.astype(np.float32))                     # [N, C, k_v, L]
    out = np.einsum("va,ncal->vlnc", yv.astype(np.float32), q)
    return np.maximum(out, 0.0).astype(np.float32)


def evaluate_sh_opencl(coeffs: np.ndarray, scale: np.ndarray, bias: np.ndarray, quantized: bool,
                       yv: np.ndarray, yl: np.ndarray, budget_bytes: int = 256 << 20) -> np.ndarray:
    backend = get_backend()
    n_texel, n_channel, k_v, k_l = coeffs.shape
    n_view, n_light = yv.shape[0], yl.shape[0]
    options = (f"-DMAX_KV={k_v}",) + (("-DQUANTIZED",) if quantized else ()) + BUILD_OPTIONS
    kernel = backend.kernel(KERNELS, "sh_eval", options)
    out = np.empty((n_view, n_light, n_texel, n_channel), dtype=np.float32)
    scale_dev = backend.to_device(np.ascontiguousarray(scale, np.float32))
    bias_dev = backend.to_device(np.ascontiguousarray(bias, np.float32))
    yv_dev = backend.to_device(np.ascontiguousarray(yv, np.float32))
    yl_dev = backend.to_device(np.ascontiguousarray(yl, np.float32))
    per_texel = n_channel * (k_v * k_l * coeffs.itemsize + n_view * n_light * 4)
    for chunk in texel_chunks(n_texel, per_texel, budget_bytes):
        n = chunk.stop - chunk.start
        c_dev = backend.to_device(np.ascontiguousarray(coeffs[chunk]))
        o_dev = backend.empty(n_view * n_light * n * n_channel * 4)
        backend.run(kernel, (n, n_light), c_dev, scale_dev, bias_dev, yv_dev, yl_dev, np.int32(k_v), np.int32(k_l),
                    np.int32(n_view), np.int32(n_light), np.int32(n), np.int32(n_channel), o_dev)
        out[:, :, chunk] = backend.from_device(o_dev, (n_view, n_light, n, n_channel), np.float32)
    return out


def evaluate_sh_scattered_numpy(coeffs: np.ndarray, scale: np.ndarray, bias: np.ndarray, quantized: bool,
                                texels: np.ndarray, yv: np.ndarray, yl: np.ndarray) -> np.ndarray:
    """Reference scattered evaluation: texel ``texels[i]`` of ``coeffs [T, C, k_v, k_l]`` with item i's basis
    values ``yv [N, k_v]`` and ``yl [N, k_l]`` -> ``[N, C]`` float32, clipped at 0."""
    c = coeffs[texels]
    c = c.astype(np.float32) * scale + bias if quantized else c
    q = np.einsum("ncab,nb->nca", c, yl, dtype=np.float32)
    return np.maximum(np.einsum("nca,na->nc", q, yv, dtype=np.float32), 0.0).astype(np.float32)


def evaluate_sh_scattered_opencl(coeffs: np.ndarray, scale: np.ndarray, bias: np.ndarray, quantized: bool,
                                 texels: np.ndarray, yv: np.ndarray, yl: np.ndarray) -> np.ndarray:
    """Scattered evaluation on OpenCL (kernel ``sh_eval_scattered``); the coefficients are read in place."""
    backend = get_backend()
    n_channel, k_v, k_l = coeffs.shape[1:]
    options = (f"-DMAX_KV={k_v}",) + (("-DQUANTIZED",) if quantized else ()) + BUILD_OPTIONS
    kernel = backend.kernel(KERNELS, "sh_eval_scattered", options)
    n = len(texels)
    out = np.empty((n, n_channel), np.float32)
    if n == 0:
        return out
    o_dev = backend.host_output(out)
    backend.run(kernel, (n,), backend.host_input(coeffs),
                *(backend.to_device(np.ascontiguousarray(a, np.float32)) for a in (scale, bias)),
                backend.to_device(np.ascontiguousarray(texels, np.int32)),
                *(backend.to_device(np.ascontiguousarray(a, np.float32)) for a in (yv, yl)),
                np.int32(k_v), np.int32(k_l), np.int32(n), np.int32(n_channel), o_dev)
    backend.finish_output(o_dev, out)
    return out


# ----------------------------------------------------------------------------------------------- fitting


@dataclasses.dataclass(frozen=True)
class SHSolver:
    """The shared SVD of the design matrix ``kron(Y_view, Y_light)``, kept as its two factors.

    ``u_*`` ``[n, r]``, ``s_*`` ``[r]``, ``v_*`` ``[k, r]`` for view and light; ``s`` is the flattened Kronecker
    product ``s_v[i] * s_l[j]`` at index ``i * r_l + j``, with 0 where it is below ``RCOND`` x the largest (a
    direction both solvers leave out).
    """

    u_v: np.ndarray
    s_v: np.ndarray
    v_v: np.ndarray
    u_l: np.ndarray
    s_l: np.ndarray
    v_l: np.ndarray

    @property
    def s(self) -> np.ndarray:
        s = np.outer(self.s_v, self.s_l).ravel()
        return np.where(s > RCOND * s.max(), s, 0.0) if s.size else s

    @property
    def rank(self) -> int:
        return int(np.count_nonzero(self.s))

    def project(self, y: np.ndarray) -> np.ndarray:
        """``U^T y`` for samples ``y [V, L, N]`` -> ``[N, r_v * r_l]`` float32 (BLAS on the host)."""
        n_view, n_light, n = y.shape
        # Two plain matrix products (one over the views, then one per view coefficient over the lights) on
        # C-ordered factors: a batched product with a transposed factor runs 5-10x slower in NumPy.
        t = np.ascontiguousarray(self.u_v.T, np.float32) @ y.reshape(n_view, -1)      # [r_v, L * N]
        # (rows of u_l past the lights belong to penalty rows, whose samples are zero)
        p = np.matmul(np.ascontiguousarray(self.u_l[:n_light].T, np.float32), t.reshape(len(self.s_v), n_light, n))
        return np.ascontiguousarray(p.transpose(2, 0, 1)).reshape(n, -1)             # [N, r_v * r_l]


def _factor_svd(basis: np.ndarray):
    # A factor's singular value below RCOND x its largest gives products below RCOND x the largest product
    # (those are cut in SHSolver.s anyway): dropping it here only saves work.
    u, s, vt = np.linalg.svd(basis, full_matrices=False)
    keep = s > s[0] * RCOND if s.size and s[0] > 0 else np.zeros(s.shape, bool)
    return u[:, keep], s[keep], vt[keep].T


def smoothness_rows(light_order: int, n_light: int, smoothness: float) -> np.ndarray:
    """Rows appended to the light design matrix (with zero samples) whose squared residual is the smoothness
    penalty ``smoothness (n_light / 4 pi) sum_lm l (l + 1) c_lm^2``: the squared gradient of the function over
    the sphere, in units of the data term (``n_light / 4 pi`` is ``A^T A`` for lights spread evenly over it)."""
    bands = np.repeat(np.arange(light_order), 2 * np.arange(light_order) + 1)
    return np.diag(np.sqrt(smoothness * n_light / FOUR_PI * bands * (bands + 1.0)))


def sh_solver(lights: np.ndarray, views: np.ndarray, light_order: int, view_order: int,
              smoothness: float = 0.0) -> SHSolver:
    """SVD of the light and view SH design matrices (the design matrix's Kronecker factors); with
    ``smoothness`` the light factor carries the rows of :func:`smoothness_rows` below the lights."""
    design = real_sh(light_order, lights)
    if smoothness > 0:
        design = np.vstack([design, smoothness_rows(light_order, len(lights), smoothness)])
    u_l, s_l, v_l = _factor_svd(design)
    u_v, s_v, v_v = _factor_svd(real_sh(view_order, views))
    return SHSolver(u_v, s_v, v_v, u_l, s_l, v_l)


def energy_root(y: np.ndarray, energy_factor: float) -> np.ndarray:
    """``sqrt`` of the energy bound per texel-channel for samples ``y [V, L, N]``: ``factor (4 pi)^2 mean(y^2)``
    (times ``1 + ENERGY_SLACK``, so that functions meeting the bound exactly, like a constant, stay unregularised)."""
    mean_sq = np.einsum("vln,vln->n", y, y, dtype=np.float64) / (y.shape[0] * y.shape[1])
    if math.isinf(energy_factor):
        return np.where(mean_sq > 0, np.inf, 0.0).astype(np.float32)
    return (FOUR_PI * np.sqrt(energy_factor * (1.0 + ENERGY_SLACK) * mean_sq)).astype(np.float32)


def cls_weights_numpy(proj: np.ndarray, s: np.ndarray, root_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Twin of kernel ``sh_lambda``: per row of ``proj [N, r]`` the smallest lambda whose solution's energy is
    within ``root_target^2``, by bisection over ``log2(lambda)``.  Returns ``(lambda [N], weights [N, r])``."""
    p = proj.astype(np.float64)
    s = s.astype(np.float64)
    kept = s > 0                                  # s = 0: a direction below RCOND, weight 0 (kernel: the same)
    p = np.where(kept, p, 0.0)
    s_safe = np.where(kept, s, 1.0)
    root = root_target.astype(np.float64)
    n = p.shape[0]
    live = root > np.finfo(np.float32).tiny
    inv_root = np.where(live, 1.0 / np.where(live, root, 1.0), 0.0)
    q = p * inv_root[:, None]

    def energy(rows, lam):
        w = s * q[rows] / (s_safe * s_safe + lam[:, None])
        return (w * w).sum(axis=1)

    lam = np.zeros(n)
    idx = np.flatnonzero(live)
    idx = idx[energy(idx, np.zeros(len(idx))) > 1.0]
    if len(idx):
        hi = 0.5 * np.log2(((s * q[idx]) ** 2).sum(axis=1))
        lo = hi - LAMBDA_SPAN
        floor = lo.copy()
        tiny = energy(idx, np.exp2(floor)) <= 1.0     # below 2^-40 of the bracket: as good as zero
        for _ in range(LAMBDA_ITERS):
            mid = 0.5 * (lo + hi)
            ok = energy(idx, np.exp2(mid)) <= 1.0
            hi = np.where(ok, mid, hi)
            lo = np.where(ok, lo, mid)
        hi = np.where(tiny, floor, hi)
        lam[idx] = np.exp2(hi)
    weights = np.where(kept, s * p / (s_safe * s_safe + lam[:, None]), 0.0)
    weights[~live] = 0.0
    return lam.astype(np.float32), weights


def cls_coeffs_numpy(proj: np.ndarray, root_target: np.ndarray, solver: SHSolver) -> tuple[np.ndarray, np.ndarray]:
    """Reference constrained solve: ``proj [N, r]`` -> ``(coeffs [N, k_v, k_l] float32, lambda [N])``."""
    lam, w = cls_weights_numpy(proj, solver.s, root_target)
    w = w.reshape(-1, len(solver.s_v), len(solver.s_l))
    coeffs = np.einsum("ai,nij,bj->nab", solver.v_v, w, solver.v_l, optimize=True)
    return coeffs.astype(np.float32), lam


def cls_coeffs_opencl(proj: np.ndarray, root_target: np.ndarray, solver: SHSolver) -> tuple[np.ndarray, np.ndarray]:
    backend = get_backend()
    n, r = proj.shape
    r_v, r_l = len(solver.s_v), len(solver.s_l)
    k_v, k_l = solver.v_v.shape[0], solver.v_l.shape[0]
    lambda_kernel = backend.kernel(KERNELS, "sh_lambda", BUILD_OPTIONS)
    solve_kernel = backend.kernel(KERNELS, "sh_solve", (f"-DMAX_RV={max(r_v, 1)}",) + BUILD_OPTIONS)
    p_dev = backend.to_device(np.ascontiguousarray(proj, np.float32))
    s_dev = backend.to_device(solver.s.astype(np.float32))
    root_dev = backend.to_device(np.ascontiguousarray(root_target, np.float32))
    lam_dev = backend.empty(n * 4)
    w_dev = backend.cl.Buffer(backend.context, backend.cl.mem_flags.READ_WRITE, size=max(n * r * 4, 1))
    backend.run(lambda_kernel, (n,), p_dev, s_dev, root_dev, np.int32(r), np.int32(n), lam_dev, w_dev)
    vv_dev = backend.to_device(solver.v_v.astype(np.float32))
    vl_dev = backend.to_device(solver.v_l.astype(np.float32))
    c_dev = backend.empty(n * k_v * k_l * 4)
    backend.run(solve_kernel, (n, k_l), w_dev, vv_dev, vl_dev, np.int32(r_v), np.int32(r_l), np.int32(k_v),
                np.int32(k_l), np.int32(n), c_dev)
    coeffs = backend.from_device(c_dev, (n, k_v, k_l), np.float32)
    return coeffs, backend.from_device(lam_dev, (n,), np.float32)


def quantize_coeffs(coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Uniform 8-bit quantization per coefficient index over all texels and channels.

    ``coeffs [..., k_v, k_l]`` float32 -> ``(q uint8, scale [k_v, k_l], bias [k_v, k_l])`` with
    ``bias = min``, ``scale = (max - min) / 255`` (1 where the range is empty) and ``q = round((c - bias) / scale)``.
    """
    flat = coeffs.reshape(-1, *coeffs.shape[-2:]).astype(np.float64)
    if flat.shape[0] == 0:
        ones = np.ones(coeffs.shape[-2:], np.float32)
        return coeffs.astype(np.uint8), ones, np.zeros_like(ones)
    lo, hi = flat.min(axis=0), flat.max(axis=0)
    bias = lo.astype(np.float32)
    scale = ((hi - lo) / 255.0).astype(np.float32)
    scale = np.where(scale > 0, scale, np.float32(1.0)).astype(np.float32)
    q = np.rint((coeffs.astype(np.float64) - bias.astype(np.float64)) / scale.astype(np.float64))
    return np.clip(q, 0, 255).astype(np.uint8), scale, bias


def _fitted_values(stack: SampleStack, rows: slice, cols: slice, space: str) -> np.ndarray:
    """The block's values in the space fitted: linear radiance, or display values (an 8-bit capture's bytes / 255,
    a linear one's radiance clipped to [0, 1] and sRGB-encoded)."""
    raw = np.asarray(stack.samples[:, :, rows, cols])
    if stack.encoding == "srgb8":
        if space == "linear":
            return SRGB8_TO_LINEAR[raw]
        return np.divide(raw, np.float32(255.0), dtype=np.float32)  # one float array, not two
    return raw if space == "linear" else linear_to_srgb(raw).astype(np.float32)


def _fit_blocks(stack: SampleStack, solver: SHSolver, solve, space: str, energy_factor: float, budget_bytes: int,
                coeffs: np.ndarray, lam: np.ndarray) -> None:
    """Fit ``coeffs [H, W, C, k_v, k_l]`` and ``lam [H, W, C]`` block of texels by block of texels."""
    for rows, cols in stack.texel_blocks(max(1, budget_bytes)):
        y = _fitted_values(stack, rows, cols, space)
        block = y.shape[2:4]
        y = np.ascontiguousarray(y).reshape(stack.n_view, stack.n_light, -1)
        proj = solver.project(y)
        root = energy_root(y, energy_factor)
        del y
        part, part_lam = solve(proj, root, solver)
        coeffs[rows, cols] = part.reshape(*block, *coeffs.shape[2:])
        lam[rows, cols] = part_lam.reshape(*block, lam.shape[2])
        release(coeffs[rows, cols])


def auto_orders(n_light: int) -> tuple[int, ...]:
    """The light orders ``auto`` tries on ``n_light`` lights: those of :data:`AUTO_ORDERS` with no more
    coefficients than the lights each held-out fold fits (more would be fitted by the energy bound alone)."""
    n_fit = n_light - math.ceil(n_light / AUTO_HOLD_EVERY)
    return tuple(order for order in AUTO_ORDERS if order * order <= n_fit) or AUTO_ORDERS[:1]


def few_lights_order(n_light: int) -> int:
    """``auto``'s light order when there are too few lights to hold any out: the largest order up to 4 with at
    least two lights per light coefficient (at least 1)."""
    return max([order for order in range(1, 5) if 2 * order * order <= n_light] or [1])


def resolve_choices(stack: SampleStack, light_order, view_order: int, space: str, smoothness, engine: str,
                    energy_factor: float) -> tuple[int, str, float, dict]:
    """The light order, space and smoothness to fit, and the held-out error of each setting ``auto`` compared
    (keyed ``"order space smoothness"``).

    ``light_order="auto"`` fits every order of :func:`auto_orders` (in each space ``space`` allows) to a grid of
    texels with every light held out once (:func:`btforge.fitspace.best_held_out`) and keeps the pair whose fits
    predict the held-out lights best (the highest order among near ties, :func:`highest_near_best`).
    ``smoothness="auto"`` then tries that order and the higher ones, in that space, at each smoothness of
    :data:`AUTO_SMOOTHNESS`, and keeps the best setting, unsmoothed included.  With fewer than
    ``AUTO_MIN_LIGHTS`` lights nothing is held out: :func:`few_lights_order`, no smoothing, and the space
    ``auto`` takes without a test.
    """
    def predict(fit, candidate, lights, views):
        order, sp, smooth = candidate
        return fit_sh(fit, order, view_order, engine=engine, energy_factor=energy_factor, space=sp,
                      smoothness=smooth)[0].evaluate(lights, views)

    orders = auto_orders(stack.n_light) if light_order == "auto" else (light_order,)
    spaces = (space,) if space != "auto" else ("srgb", "linear") if stack.encoding == "srgb8" else ("linear",)
    smooth = 0.0 if smoothness == "auto" else float(smoothness)
    if stack.n_light < AUTO_MIN_LIGHTS:
        order = few_lights_order(stack.n_light) if light_order == "auto" else light_order
        return order, resolve_space(stack, space), smooth, {}
    if len(orders) == 1 and len(spaces) == 1 and smoothness != "auto":
        return orders[0], spaces[0], smooth, {}
    grid = held_out_grid(stack)
    _, errors = best_held_out(grid, stack, [(o, sp, smooth) for o in orders for sp in spaces], predict)
    order, sp = highest_near_best({(o, sp): e for (o, sp, _), e in errors.items()})
    best = (order, sp, smooth)
    if smoothness == "auto":
        smoothed = [(o, sp, value) for o in orders if o >= order for value in AUTO_SMOOTHNESS]
        errors.update(best_held_out(grid, stack, smoothed, predict)[1])
        best = min([best] + smoothed, key=errors.get)
    return (*best, {f"{o} {sp} {value:g}": e for (o, sp, value), e in errors.items()})


def highest_near_best(errors: dict) -> tuple[int, str]:
    """Of ``{(order, space): held-out error}``, the highest order within :data:`AUTO_ORDER_TIE` of the lowest
    error, in its better space."""
    lowest = min(errors.values())
    near = [(order, -error, sp) for (order, sp), error in errors.items() if error <= lowest * (1 + AUTO_ORDER_TIE)]
    order, _, sp = max(near)
    return order, sp


def fit_sh(stack: SampleStack, light_order: int | str = 4, view_order: int = 1, quantize: bool = False, *,
           engine: str = "opencl", budget_bytes: int = 64 << 20,
           energy_factor: float = DEFAULT_ENERGY_FACTOR, space: str = "auto",
           smoothness: float | str = 0.0) -> tuple[SHModel, dict]:
    """Constrained least-squares double-SH fit of a stack, streamed over bands of rows.

    ``view_order`` is forced to 1 for a single-view stack.  Returns the model and a dict of statistics:
    ``lambda`` (``[H, W, C]`` float32), ``lambda_median``, ``lambda_max``, ``clamped`` (texel-channels whose
    constraint was active, ``lambda > 0``), ``clamped_fraction``, ``compression_rate_percent``,
    ``n_coefficients``, ``n_samples``, ``rank``, ``underdetermined``, ``view_order``, ``energy_factor``.
    ``energy_factor=inf`` (plain least squares) refuses fewer lights than ``light_order^2`` or fewer views than
    ``view_order^2``: nothing would then choose among the exact fits.
    """
    for name, value in (("light_order", light_order), ("view_order", view_order)):
        if name == "light_order" and value == "auto":
            continue
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= MAX_ORDER:
            allowed = "'auto' or " * (name == "light_order")
            raise BtforgeInputError(f"sh.fit '{name}'", f"expected {allowed}an int in [1, {MAX_ORDER}], found {value!r}")
    if smoothness != "auto" and (isinstance(smoothness, bool) or not isinstance(smoothness, (int, float))
                                 or not 0 <= smoothness < math.inf):
        raise BtforgeInputError("sh.fit 'smoothness'", f"expected 'auto' or a number >= 0, found {smoothness!r}")
    if not energy_factor > 0:
        raise BtforgeInputError("sh.fit 'energy_factor'", f"expected a positive number, found {energy_factor!r}")
    if engine not in ("opencl", "numpy"):
        raise BtforgeInputError("sh.fit 'engine'", f"expected 'opencl' or 'numpy', found {engine!r}")
    if space not in SPACES + ("auto",):
        raise BtforgeInputError("sh.fit 'space'", f"expected one of auto, linear, srgb, found {space!r}")
    if stack.n_view == 1:
        view_order = 1
    light_order, space, smoothness, held_out_errors = resolve_choices(stack, light_order, view_order, space,
                                                                      smoothness, engine, energy_factor)
    k_l, k_v = light_order ** 2, view_order ** 2
    if math.isinf(energy_factor) and (stack.n_light < k_l or stack.n_view < k_v):
        # Without the energy bound nothing picks among the exact fits: the minimum-norm one is arbitrary.
        raise BtforgeInputError(
            "sh.fit 'energy_factor'", f"plain least squares (energy_factor=inf) needs at least as many lights as "
            f"light coefficients and views as view coefficients, found light_order {light_order} ({k_l} "
            f"coefficients) for {stack.n_light} light(s) and view_order {view_order} ({k_v}) for {stack.n_view} "
            f"view(s): {stack.n_light * stack.n_view} samples for {k_l * k_v} coefficients",
            "lower the orders, or keep the energy constraint (a finite energy_factor, default 1)")
    solver = sh_solver(stack.lights, stack.views, light_order, view_order, smoothness)
    solve = cls_coeffs_numpy if engine == "numpy" else cls_coeffs_opencl
    h, w, c = stack.height, stack.width, stack.n_channel
    n_samples = stack.n_view * stack.n_light
    # A store's fit goes to a file whose pages are handed back as they are written: memory stays flat as the
    # BTF grows (a 256^2 double SH 25 x 25 is 491 MB of coefficients).
    coeffs = (spilled_empty if stack.chunked else np.empty)((h, w, c, k_v, k_l), np.float32)
    lam = np.empty((h, w, c), np.float32)
    # Working set per texel: the samples plus projections, weights and coefficients.
    scale = n_samples / (n_samples + 2 * solver.rank + k_v * k_l)
    with single_threaded_blas():
        _fit_blocks(stack, solver, solve, space, energy_factor, int(budget_bytes * scale), coeffs, lam)
    if coeffs.size and not finite_range(coeffs):  # cannot happen; guard anyway
        raise BtforgeInputError("sh.fit", "the solve produced non-finite coefficients",
                                "lower the orders or use a finite energy_factor")
    lam = lam.reshape(-1)
    if quantize:
        q, qscale, qbias = quantize_coeffs(coeffs)
        model = SHModel(q, qscale, qbias, light_order, view_order, True, stack.channels, space)
    else:
        model = SHModel(coeffs, np.ones((k_v, k_l), np.float32), np.zeros((k_v, k_l), np.float32),
                        light_order, view_order, False, stack.channels, space)
    clamped = int((lam > 0).sum())
    stats = {
        "lambda": lam.reshape(h, w, c),
        "lambda_median": float(np.median(lam)) if lam.size else 0.0,
        "lambda_max": float(lam.max()) if lam.size else 0.0,
        "clamped": clamped,
        "clamped_fraction": clamped / max(lam.size, 1),
        "compression_rate_percent": 100.0 * compression_rate(k_l, k_v, stack.n_light, stack.n_view),
        "n_coefficients": k_l * k_v,
        "n_samples": n_samples,
        "rank": solver.rank,
        "underdetermined": solver.rank < k_l * k_v,
        "view_order": view_order,
        "energy_factor": energy_factor,
        "space": space,
        "light_order": light_order,
        "smoothness": smoothness,
        "held_out_errors": held_out_errors,
        "sigma_max_sq": float(solver.s.max() ** 2) if solver.rank else 0.0,
    }
    return model, stats
