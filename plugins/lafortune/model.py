"""Per-texel Lafortune lobes fitted by Levenberg-Marquardt, with OpenCL kernels (``lafortune.cl``) and NumPy twins.

The model (Lafortune et al. 1997, per texel as in McAllister et al. 2002 and Bosserhoff & Nicoll) is evaluated
in each texel's own frame - its normal ``n`` and the tangent ``t`` obtained by Gram-Schmidt of the surface x-axis
against ``n`` (the y-axis when ``n`` is nearly the x-axis), ``b = n x t``::

    f(u, v)     = rho_d + sum_i max(Cx_i ux vx + Cy_i uy vy + Cz_i uz vz, 0) ^ n_i
    radiance    = max(uz, 0) * f(u, v)                        (times colour_c for the ``lum`` variant)

with ``u``, ``v`` the light and view directions expressed in the texel frame.

Radiance convention
-------------------
``f`` is a BRDF: the predicted pixel value is ``f`` times the cosine foreshortening ``max(n . l, 0)`` (unit light
intensity).  An RTI capture is dominated by Lambertian shading; with the cosine outside ``f`` the constant
``rho_d`` reproduces it exactly, lights below a texel's horizon give black, and every lobe is free to model
gloss.  Fitting the pixel value directly with ``f`` would spend a whole lobe (n = 1, ``Cz``) on imitating the
cosine and leave a 1-lobe fit with nothing for the highlight.

Guards and bounds
-----------------
* a lobe is ``max(base, 0) ^ n``: a negative base is never raised to a non-integer power (the lobe and its
  derivatives are 0 there);
* exponents are fitted as ``p = ln n`` clamped to ``[0, ln 1000]``, so ``n`` stays in ``[1, 1000]``;
* each lobe's peak over *all* directions, ``max_j |C_j| ^ n`` (``|sum_j C_j u_j v_j| <= max_j |C_j|`` for unit
  ``u``, ``v``), is held below ``LOBE_CAP`` (10) times the texel's brightest sample for the first lobe and
  ``LATER_CAP`` (2) times for every later one: a fit can not invent a highlight between the measured lights that
  is brighter than that.  The tighter cap on later lobes is the regulariser that keeps extra lobes from
  fitting single samples with narrow spikes: on 128^2 glossy bumps (48 lights) it lifts the held-out PSNR of a
  2-lobe fit from 22.2 to 28.4 dB, and with unevenly sampled lights (half the dome 3x sparser) from 19.8 to
  27.9 dB.  Interpolating virtual images between neighbouring lights of the sparse half (as Bosserhoff &
  Nicoll suggest) helped only without it (+3.7 dB) and costs 0.1-0.5 dB with it, so it is not done;
* ``rho_d >= 0``; the ``lum`` colour is the non-negative least-squares scale of each channel (1 for a black
  texel).

Fit (per texel, and per channel for ``rgb``)
--------------------------------------------
Normals come first, from robust photometric stereo (:func:`estimate_normals`: a trimmed least-squares start,
then Tukey-reweighted least squares over every lit, unsaturated sample).  Each texel is then scaled to a
peak in (0.5, 1] and the result scaled back (:func:`fit_band`), so nothing below depends on the data's brightness.
Lobes are then added one at a time.  Stage 0 is the closed-form ``rho_d``.  Stage ``k`` keeps the ``k - 1`` lobes of the best fit so far and
scores a grid of start shapes for the new lobe against their residual - mirror ``(-1, -1, 1)``, retro
``(1, 1, 1)`` and normal ``(0, 0, 1)`` directions at 20 exponents 1, 1.5, 2, 3, ... 768 (powers of a base by
squaring alone, no exp or log; coarser grids leave LM stranded between them), each with its non-negative
amplitude and ``rho_d`` solved in closed form.  Each shape starts at most one lobe, so lobes start spread out.
The first lobe races two starts - the best shape and the best broader one (``N_STARTS`` = 2) - for
``RACE_ITER`` steps each and only the better is refined on; later lobes start from the best shape.
Levenberg-Marquardt refines all ``1 + 4k`` parameters:

* damped normal equations ``(J'J + lambda D) d = J'r`` with Marquardt's scaling ``D = diag(J'J)``, solved by
  Cholesky; each trial's pass over the samples also builds its normal equations, so an accepted step costs one
  pass (the host lays each texel's samples and geometry out contiguously);
* the step stays inside the box (``rho >= 0``, ``p`` in ``[0, ln 1000]``, ``alpha`` and ``|psi_j|`` under the
  cap): a parameter whose step would cross a bound lands on it and the others are solved again with that move
  fixed (an active-set step) - clipping by projection alone left LM trying ever shorter steps against the bound;
* ``lambda`` follows the gain ratio of actual to predicted reduction (Nielsen's trust-region rule: x max(1/3,
  1 - (2 rho - 1)^3) on an accepted step, x nu and nu x2 on a rejected one);
* converged: an exact fit (``ATOL``), a zero gradient, a Gauss-Newton step (damped by ``LAM_DEC`` only) that
  promises at most ``FTOL`` of the cost (the Newton decrement: not fooled by short steps in a curved valley),
  an accepted step that gains at most ``GTOL`` of the cost, or ``lambda > LAM_MAX`` (no descent left).  A
  converged texel's work-item stops there (retires early); the limit is ``iterations`` tried steps.

Only improving steps are taken, so a texel that does not converge keeps its best iterate (and is counted).
The better of the starts becomes the stage result, which replaces the previous one only if it lowers the final
error (the RGB error after the colour fit for ``lum``); otherwise the new lobe is switched off (``C = 0``).
So error never grows with the number of lobes, and a ``k``-lobe fit passes through exactly the ``k - 1``-lobe
fit.

During LM a lobe is held as ``(psi, alpha, p)`` with ``C = exp(alpha / n) psi`` and ``max_j |psi_j| = 1``: the
lobe is ``exp(alpha + n ln(psi . x))``, ``alpha`` its peak's log.  With ``C`` itself, a change of ``n`` also
changes the lobe's height whenever ``|C| != 1`` and LM crawls along that curved valley; this parameterisation
decouples height from width (it recovered 1-lobe data exactly where the plain one stalled on ~5 % of texels).

Known limits: two lobes that peak in the same place (top view: all lobes peak near the normal) are not always
separated - a few per cent of texels of exact 2-lobe data end in a local minimum; the lobe cap and the start
grid are heuristics.  The OpenCL kernel runs the algorithm in float32, the NumPy reference in float64: they
agree closely but a texel near a tie may take another branch and settle in another minimum.

Speed
-----
One work-item fits one texel (and channel), in work-groups of one (PoCL's CPU device keeps a work-group's
private arrays on one thread's stack).  Every pass over a texel's samples - the sums of the start grid, each
trial's cost and normal equations, the colour fit - works on ``VECTOR_WIDTH`` samples at once as OpenCL
vectors (the host lays each texel's samples and geometry out per quantity, zero-padded to whole blocks, which
add exactly 0 to every sum); the passes and the damped steps of the first and the last lobe stage are compiled
with the lobe count known.  The start grid needs two sums per exponent rung: ``sum g^2`` of a shape
``g = c b^n`` is the ``sum c^2 b^n`` two rungs up the ladder.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import ClassVar

import numpy as np

from btforge.backend import get_backend
from btforge.numerics import texel_chunks
from btforge.buffers import (ReflectanceModel, SampleStack, check_array, freeze_fields, scattered_lookup,
                             unit_directions)
from btforge.errors import BtforgeInputError

from .lm import (ATOL, B_MIN, CANDIDATE_DIRS, CANDIDATE_EXPONENTS, CAP_DROP, D_FLOOR, DEFAULT_ITERATIONS, ETOL,
                 EXPONENT_MAX, EXPONENT_MIN, FTOL, GTOL, LAM0, LAM_DEC, LAM_MAX, LAM_MIN, LOBE_CAP, N_STARTS, NU0,
                 P_MAX, RACE_ITER, T_CAP, W_FLOOR, _fit_signals_numpy, _model64)
from .normals import NORMAL_MIN_Z, _normals_band, _sample_directions

KERNELS = Path(__file__).with_name("lafortune.cl")

VARIANTS = ("lum", "rgb")
MAX_LOBES = 7            # luminance lobes
RGB_LOBES = 2            # lobes per channel of the rgb variant
MAX_CHANNELS = 4
VECTOR_WIDTH = 8         # samples per OpenCL vector in the fit kernel (measured at 128^2 x 48: 4 is 25 % slower,
                         # 16 no faster on AVX-512; 8 wastes less padding on odd sample counts)


def _cl_float(value: float) -> str:
    return f"{float(value)!r}f"


# lafortune.cl takes every constant above from these build options (it defines none itself), so the kernels and
# their NumPy twins cannot drift apart.
BUILD_OPTIONS = tuple(f"-D{name}={_cl_float(value)}" for name, value in (
    ("P_MAX", P_MAX), ("LOBE_CAP", LOBE_CAP), ("CAP_DROP", CAP_DROP), ("T_CAP", T_CAP), ("B_MIN", B_MIN),
    ("LAM0", LAM0), ("NU0", NU0), ("LAM_MIN", LAM_MIN), ("LAM_MAX", LAM_MAX), ("LAM_DEC", LAM_DEC), ("FTOL", FTOL),
    ("GTOL", GTOL), ("ETOL", ETOL), ("ATOL", ATOL), ("D_FLOOR", D_FLOOR), ("W_FLOOR", W_FLOOR))) + (
    f"-DMAXC={MAX_CHANNELS}", f"-DN_DIRS={len(CANDIDATE_DIRS)}", f"-DN_EXPS={len(CANDIDATE_EXPONENTS)}",
    f"-DRACE_ITER={RACE_ITER}")


# ----------------------------------------------------------------------------------------------- frames


def texel_frames(normals: np.ndarray) -> np.ndarray:
    """Per-texel frames ``[N, 3, 3]`` float32, rows ``(t, b, n)``: the tangent is the surface x-axis made
    orthogonal to ``n`` (Gram-Schmidt; the y-axis when ``n`` is within ~0.057 degree of x, where
    ``|t|^2 = 1 - nx^2 < 1e-6``), ``b = n x t``."""
    n = np.asarray(normals, np.float32).reshape(-1, 3)
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    tx, ty, tz = np.float32(1) - nx * nx, -nx * ny, -nx * nz
    len2 = tx * tx + ty * ty + tz * tz
    use_y = len2 < np.float32(1e-6)
    tx = np.where(use_y, -ny * nx, tx)
    ty = np.where(use_y, np.float32(1) - ny * ny, ty)
    tz = np.where(use_y, -ny * nz, tz)
    inv = np.float32(1) / np.sqrt(tx * tx + ty * ty + tz * tz)
    t = np.stack([tx * inv, ty * inv, tz * inv], axis=1)
    b = np.cross(n, t).astype(np.float32)
    return np.ascontiguousarray(np.stack([t, b, n], axis=1), dtype=np.float32)


def _local(frames: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """``dirs [D, 3]`` in each frame -> ``[N, D, 3]``, float32 with the kernels' order of operations."""
    return np.stack(_local_rows(frames, dirs), axis=2)


def _local_rows(frames: np.ndarray, dirs: np.ndarray) -> list[np.ndarray]:
    """The three components ``[N, D]`` of :func:`_local`."""
    d = dirs.astype(np.float32)
    rows = []
    for i in range(3):
        row = frames[:, i, 0, None] * d[:, 0]
        row += frames[:, i, 1, None] * d[:, 1]
        row += frames[:, i, 2, None] * d[:, 2]
        rows.append(row)
    return rows


def _local_each(frames: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Item i's direction ``dirs[i]`` in its own frame ``frames[i]`` -> ``[N, 3]``, as :func:`_local`."""
    d = np.asarray(dirs, np.float32)[:, None, :]
    return (frames[..., 0] * d[..., 0] + frames[..., 1] * d[..., 1]) + frames[..., 2] * d[..., 2]


# ----------------------------------------------------------------------------------------------- the model


@dataclasses.dataclass(frozen=True, eq=False)
class LafortuneModel(ReflectanceModel):
    """Per-texel Lafortune lobes in per-texel frames (see the module docstring for the formula).

    ``normals [H, W, 3]`` unit; ``diffuse [H, W, 1]`` (lum) or ``[H, W, C]`` (rgb); ``lobes [H, W, K, 3]`` the
    ``(Cx, Cy, Cz)`` of each lobe (for rgb ``K = 2 C``, channel-major: lobes ``2c, 2c+1`` belong to channel
    ``c``); ``exponents [H, W, K]`` in ``[1, 1000]``; ``colour [H, W, C]`` for lum, ``[H, W, 0]`` for rgb.
    A lobe with ``C = 0`` is switched off.
    """

    type_name: ClassVar[str] = "LafortuneModel"
    view_dependent: ClassVar[bool] = True
    texel_fields: ClassVar[tuple[str, ...]] = ("normals", "diffuse", "lobes", "exponents", "colour")
    blendable: ClassVar[bool] = False  # lobes are non-linear in their parameters: a mean of lobes is no mean lobe

    normals: np.ndarray
    diffuse: np.ndarray
    lobes: np.ndarray
    exponents: np.ndarray
    colour: np.ndarray
    variant: str = "lum"
    channel_names: tuple[str, ...] = ("R", "G", "B")

    def __post_init__(self):
        owner = "LafortuneModel"
        if self.variant not in VARIANTS:
            raise BtforgeInputError(f"{owner} 'variant'", f"must be one of {VARIANTS}, got {self.variant!r}")
        n_channel = len(self.channel_names)
        if not 1 <= n_channel <= MAX_CHANNELS:
            raise BtforgeInputError(f"{owner} 'channel_names'", f"must name 1 to {MAX_CHANNELS} channels, got {n_channel}")
        normals = check_array("normals", self.normals, ("H", "W", 3), np.float32, finite=True, owner=owner)
        h, w = normals.shape[:2]
        norms = np.linalg.norm(normals.astype(np.float64), axis=-1)
        if normals.size and np.abs(norms - 1.0).max() > 1e-3:
            raise BtforgeInputError(f"{owner} 'normals'", f"must be unit vectors, found lengths in [{norms.min():.4g}, {norms.max():.4g}]")
        lum = self.variant == "lum"
        check_array("diffuse", self.diffuse, (h, w, 1 if lum else n_channel), np.float32, finite=True, owner=owner)
        lobes = check_array("lobes", self.lobes, (h, w, "K", 3), np.float32, finite=True, owner=owner)
        k = lobes.shape[2]
        if lum and not 1 <= k <= MAX_LOBES:
            raise BtforgeInputError(f"{owner} 'lobes'", f"must hold 1 to {MAX_LOBES} lobes, got {k}")
        if not lum and k != RGB_LOBES * n_channel:
            raise BtforgeInputError(f"{owner} 'lobes'", f"must hold {RGB_LOBES} lobes per channel ({RGB_LOBES * n_channel}), got {k}")
        exponents = check_array("exponents", self.exponents, (h, w, k), np.float32, finite=True, owner=owner)
        if exponents.size and (exponents.min() < EXPONENT_MIN or exponents.max() > EXPONENT_MAX):
            raise BtforgeInputError(f"{owner} 'exponents'", f"must lie in [{EXPONENT_MIN:g}, {EXPONENT_MAX:g}], "
                                    f"found [{exponents.min():g}, {exponents.max():g}]")
        check_array("colour", self.colour, (h, w, n_channel if lum else 0), np.float32, finite=True, owner=owner)
        freeze_fields(self, *self.texel_fields, "channel_names")

    @property
    def channels(self) -> tuple[str, ...]:
        return self.channel_names

    @property
    def n_lobes(self) -> int:
        """Lobes per fitted signal: the luminance lobes (lum) or the lobes of each channel (rgb)."""
        return self.lobes.shape[2] if self.variant == "lum" else RGB_LOBES

    def flat(self) -> dict[str, np.ndarray]:
        """The per-texel arrays flattened to ``[N, ...]`` (``frames`` computed from the normals)."""
        n = self.height * self.width
        return {
            "frames": texel_frames(self.normals.reshape(n, 3)),
            "diffuse": self.diffuse.reshape(n, -1),
            "lobes": self.lobes.reshape(n, -1, 3),
            "exponents": self.exponents.reshape(n, -1),
            "colour": self.colour.reshape(n, self.colour.shape[2]),
        }

    def evaluate_texels(self, rows: np.ndarray, cols: np.ndarray, lights_local: np.ndarray,
                        views_local: np.ndarray | None = None, *, engine: str = "opencl") -> np.ndarray:
        """Linear radiance ``[N, C]`` float32 of texel ``(rows[i], cols[i])`` at its own light and view in the
        surface frame (for renderers).  The host turns each item's directions into its texel's frame; the lobes
        are summed by kernel ``lafortune_eval_scattered`` (``engine="numpy"``: its NumPy twin)."""
        rows, cols, lights_local, views_local = scattered_lookup(self, rows, cols, lights_local, views_local)
        frames = texel_frames(self.normals[rows, cols])
        u, w = _local_each(frames, lights_local), _local_each(frames, views_local)
        texels = (rows.astype(np.int64) * self.width + cols).astype(np.int32)
        n = self.height * self.width
        arrays = (self.diffuse.reshape(n, -1), self.lobes.reshape(n, -1, 3), self.exponents.reshape(n, -1),
                  self.colour.reshape(n, self.colour.shape[2]))
        if engine not in ("opencl", "numpy"):
            raise BtforgeInputError("Lafortune evaluation 'engine'", f"must be 'opencl' or 'numpy', got {engine!r}")
        run = evaluate_lafortune_scattered_numpy if engine == "numpy" else evaluate_lafortune_scattered_opencl
        return run(*arrays, texels, u, w, self.variant, len(self.channel_names))

    def evaluate(self, lights: np.ndarray, views: np.ndarray | None = None, *, engine: str = "opencl") -> np.ndarray:
        """Linear radiance ``[V, L, H, W, C]`` float32 at unit ``lights [L, 3]`` and ``views [V, 3]`` (top view
        ``(0, 0, 1)`` when None), both in the surface frame."""
        lights = unit_directions("lights", lights, owner="Lafortune evaluation")
        views = unit_directions("views", [[0.0, 0.0, 1.0]] if views is None else views, owner="Lafortune evaluation")
        if engine not in ("opencl", "numpy"):
            raise BtforgeInputError("Lafortune evaluation 'engine'", f"must be 'opencl' or 'numpy', got {engine!r}")
        a = self.flat()
        run = evaluate_lafortune_numpy if engine == "numpy" else evaluate_lafortune_opencl
        flat = run(a["frames"], a["diffuse"], a["lobes"], a["exponents"], a["colour"], lights, views,
                   self.variant, len(self.channel_names))
        return flat.reshape(len(views), len(lights), self.height, self.width, len(self.channel_names))


# ----------------------------------------------------------------------------------------------- evaluation


def evaluate_lafortune_numpy(frames, diffuse, lobes, exponents, colour, lights, views, variant, n_channel) -> np.ndarray:
    """Reference evaluation, float32 in the kernel's order of operations: ``-> [V, L, N, C]``."""
    lights = np.asarray(lights, np.float32)
    views = np.asarray(views, np.float32)
    n_texel = frames.shape[0]
    u = _local(frames, lights)                    # [N, L, 3]
    v = _local(frames, views)                     # [N, V, 3]
    out = np.empty((len(views), len(lights), n_texel, n_channel), np.float32)
    cos = np.maximum(u[..., 2], np.float32(0)).T  # [L, N]
    per_signal = exponents.shape[1] if variant == "lum" else RGB_LOBES
    n_signal = 1 if variant == "lum" else n_channel
    for iv in range(len(views)):
        x = u * v[:, iv:iv + 1, :]                # [N, L, 3]
        x = np.transpose(x, (1, 0, 2))            # [L, N, 3]
        for sig in range(n_signal):
            f = np.broadcast_to(diffuse[:, sig], (len(lights), n_texel)).astype(np.float32)
            for j in range(per_signal):
                k = sig * per_signal + j
                c = lobes[:, k]
                base = (c[:, 0] * x[..., 0] + c[:, 1] * x[..., 1]) + c[:, 2] * x[..., 2]
                f = f + _lobe32(base, exponents[:, k])
            value = cos * f
            if variant == "lum":
                out[iv] = colour[None] * value[..., None]
            else:
                out[iv, :, :, sig] = value
    return out


def _lobe32(base: np.ndarray, n: np.ndarray) -> np.ndarray:
    pos = base > np.float32(B_MIN)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = n * np.log(np.where(pos, base, np.float32(1)))
        return np.where(pos, np.exp(np.minimum(t, np.float32(T_CAP))), np.float32(0)).astype(np.float32)


def evaluate_lafortune_opencl(frames, diffuse, lobes, exponents, colour, lights, views, variant, n_channel,
                              budget_bytes: int = 256 << 20) -> np.ndarray:
    backend = get_backend()
    kernel = backend.kernel(KERNELS, "lafortune_eval", BUILD_OPTIONS)
    n_texel, k_total = exponents.shape
    n_light, n_view = len(lights), len(views)
    out = np.empty((n_view, n_light, n_texel, n_channel), np.float32)
    if n_texel == 0 or n_light == 0:
        return out
    lights_dev = backend.to_device(np.ascontiguousarray(lights, np.float32))
    views_dev = backend.to_device(np.ascontiguousarray(views, np.float32))
    colour_src = colour if colour.shape[1] else np.zeros((n_texel, 1), np.float32)
    per_texel = 4 * (9 + diffuse.shape[1] + 4 * k_total + colour_src.shape[1] + n_view * n_light * n_channel)
    for chunk in texel_chunks(n_texel, per_texel, budget_bytes):
        n = chunk.stop - chunk.start
        args = [backend.to_device(np.ascontiguousarray(a[chunk], np.float32))
                for a in (frames, diffuse, lobes, exponents, colour_src)]
        o_dev = backend.empty(n_view * n_light * n * n_channel * 4)
        backend.run(kernel, (n, n_light, n_view), *args, lights_dev, views_dev, np.int32(n_light), np.int32(n_view),
                    np.int32(n), np.int32(n_channel), np.int32(k_total), np.int32(variant == "lum"), o_dev)
        out[:, :, chunk] = backend.from_device(o_dev, (n_view, n_light, n, n_channel), np.float32)
    return out


def evaluate_lafortune_scattered_numpy(diffuse, lobes, exponents, colour, texels, lights, views, variant,
                                      n_channel) -> np.ndarray:
    """Reference scattered evaluation: texel ``texels[i]`` of the flat arrays at ``lights[i]`` and ``views[i]``,
    both already in that texel's frame -> ``[N, C]`` float32, in the kernel's order of operations."""
    x = lights * views
    cos = np.maximum(lights[:, 2], np.float32(0))
    n_signal = 1 if variant == "lum" else n_channel
    per_signal = exponents.shape[1] // n_signal
    lob, ex = lobes[texels], exponents[texels]
    out = np.empty((len(texels), n_channel), np.float32)
    for sig in range(n_signal):
        f = diffuse[texels, sig].astype(np.float32)
        for k in range(sig * per_signal, (sig + 1) * per_signal):
            c = lob[:, k]
            f = f + _lobe32((c[:, 0] * x[:, 0] + c[:, 1] * x[:, 1]) + c[:, 2] * x[:, 2], ex[:, k])
        if variant == "lum":
            out[:] = colour[texels] * (cos * f)[:, None]
        else:
            out[:, sig] = cos * f
    return out


def evaluate_lafortune_scattered_opencl(diffuse, lobes, exponents, colour, texels, lights, views, variant,
                                       n_channel) -> np.ndarray:
    """Scattered evaluation on OpenCL (kernel ``lafortune_eval_scattered``); the model is read in place."""
    backend = get_backend()
    kernel = backend.kernel(KERNELS, "lafortune_eval_scattered", BUILD_OPTIONS)
    n = len(texels)
    out = np.empty((n, n_channel), np.float32)
    if n == 0:
        return out
    colour_src = colour if colour.shape[1] else np.zeros((1, 1), np.float32)
    o_dev = backend.host_output(out)
    backend.run(kernel, (n,), *(backend.host_input(a) for a in (diffuse, lobes, exponents, colour_src)),
                *(backend.to_device(a) for a in (np.ascontiguousarray(texels, np.int32), lights, views)),
                np.int32(n), np.int32(n_channel), np.int32(exponents.shape[1]), np.int32(variant == "lum"), o_dev)
    backend.finish_output(o_dev, out)
    return out


def _external(z: np.ndarray, k: int):
    """State -> ``(rho [M], C [M, k, 3], n [M, k])`` with ``C = exp(alpha / n) psi``."""
    lob = z[:, 1:].reshape(len(z), k, 5)
    n = np.exp(lob[..., 4])
    return z[:, 0], np.exp(lob[..., 3] / n)[..., None] * lob[..., :3], n


def _geometry64(frames: np.ndarray, sample_lights: np.ndarray, sample_views: np.ndarray):
    geom = fit_geometry(frames, sample_lights, sample_views).astype(np.float64)   # float32 ops, then widened
    return np.ascontiguousarray(np.transpose(geom[:, :3], (0, 2, 1))), geom[:, 3]


def _colour_fit(f: np.ndarray, values: np.ndarray):
    """Non-negative least-squares colour ``[M, C]`` of model ``f [M, S]`` against ``values [M, S, C]``, and the SSE."""
    ff = (f * f).sum(axis=1)
    fy = np.einsum("ms,msc->mc", f, values)
    colour = np.where(ff[:, None] > 1e-30, np.maximum(fy / np.where(ff > 1e-30, ff, 1.0)[:, None], 0.0), 1.0)
    sse = ((colour[:, None, :] * f[..., None] - values) ** 2).sum(axis=(1, 2))
    return colour, sse


def fit_band_numpy(values, frames, sample_lights, sample_views, per_fit, variant, iterations):
    """Reference fit of one band ``values [S, n, C]`` (float32) in ``frames [n, 3, 3]``, ``per_fit`` lobes per
    fitted signal (the luminance, or each channel for rgb).

    Returns ``(diffuse [n, G], lobes [n, G * per_fit, 3], exponents [n, G * per_fit], colour, sse [n, G],
    not_converged [n, G], iterations [n, G])`` for the ``G`` fitted signals.
    """
    s, n, n_channel = values.shape
    vals = np.transpose(values.astype(np.float64), (1, 0, 2))      # [n, S, C]
    x, c = _geometry64(frames, sample_lights, sample_views)
    if variant == "lum":
        y = vals.mean(axis=2)
        z, crit, flag, its = _fit_signals_numpy(y, x, c, lambda f: _colour_fit(f, vals)[1], per_fit, iterations)
        colour, _ = _colour_fit(_model64(z, per_fit, x, c), vals)
        rho, C, n_exp = _external(z, per_fit)
        return (rho[:, None].astype(np.float32), C.astype(np.float32), n_exp.astype(np.float32),
                colour.astype(np.float32), crit[:, None], flag[:, None], its[:, None])
    # rgb: one independent fit per (texel, channel)
    y = np.transpose(vals, (0, 2, 1)).reshape(n * n_channel, s)
    xr = np.repeat(x, n_channel, axis=0)
    cr = np.repeat(c, n_channel, axis=0)
    z, crit, flag, its = _fit_signals_numpy(y, xr, cr, lambda f: ((y - f) ** 2).sum(axis=1), per_fit, iterations)
    rho, C, n_exp = _external(z, per_fit)
    return (rho.reshape(n, n_channel).astype(np.float32), C.reshape(n, n_channel * per_fit, 3).astype(np.float32),
            n_exp.reshape(n, n_channel * per_fit).astype(np.float32), np.zeros((n, 0), np.float32),
            crit.reshape(n, n_channel), flag.reshape(n, n_channel), its.reshape(n, n_channel))


# ----------------------------------------------------------------------------------------------- OpenCL fit


def fit_geometry(frames: np.ndarray, sample_lights: np.ndarray, sample_views: np.ndarray,
                 padded: int | None = None) -> np.ndarray:
    """``[n, 4, S]`` float32: per texel ``x = (ux vx, uy vy, uz vz)`` and ``c = max(uz, 0)`` of every sample, with
    the light ``u`` and view ``v`` in the texel's frame (the float32 operations the NumPy fit widens); with
    ``padded``, zeros after the ``S`` samples up to ``padded``."""
    u = _local_rows(frames, sample_lights)
    views, which = np.unique(sample_views, axis=0, return_inverse=True)   # a view serves all its lights
    v = [row[:, which.ravel()] if len(views) > 1 else row for row in _local_rows(frames, views)]
    n, s = u[0].shape
    out = np.zeros((n, 4, padded or s), np.float32)
    for i in range(3):
        np.multiply(u[i], v[i], out=out[:, i, :s])
    np.maximum(u[2], np.float32(0), out=out[:, 3, :s])
    return out


def fit_band_opencl(values, frames, sample_lights, sample_views, per_fit, variant, iterations):
    """OpenCL fit of one band; same results as :func:`fit_band_numpy` (float32 arithmetic)."""
    backend = get_backend()
    s, n, n_channel = values.shape
    n_signal = 1 if variant == "lum" else n_channel
    kernel = backend.kernel(KERNELS, "lafortune_fit", (f"-DNLOBE={per_fit}", f"-DVW={VECTOR_WIDTH}") + BUILD_OPTIONS)
    dirs_dev = backend.to_device(CANDIDATE_DIRS.astype(np.float32).ravel())
    exps_dev = backend.to_device(CANDIDATE_EXPONENTS.astype(np.float32))
    k_total = per_fit * n_signal
    n_block = -(-s // VECTOR_WIDTH)              # the kernel reads VECTOR_WIDTH samples at once; zeros pad the last
    blocked = np.zeros((n, n_channel, n_block * VECTOR_WIDTH), np.float32)
    blocked[:, :, :s] = np.transpose(values, (1, 2, 0))
    s_dev = backend.to_device(blocked)
    g_dev = backend.to_device(fit_geometry(frames, sample_lights, sample_views, n_block * VECTOR_WIDTH))
    d_dev = backend.empty(n * n_signal * 4)
    c_dev = backend.empty(n * k_total * 3 * 4)
    e_dev = backend.empty(n * k_total * 4)
    col_dev = backend.empty(n * n_channel * 4)
    sse_dev = backend.empty(n * n_signal * 4)
    it_dev = backend.empty(n * n_signal * 4)
    fl_dev = backend.empty(n * n_signal * 4)
    backend.run(kernel, (n, n_signal), s_dev, g_dev, dirs_dev, exps_dev, np.int32(n_block), np.int32(n),
                np.int32(n_channel),
                np.int32(variant == "lum"), np.int32(iterations), np.int32(N_STARTS),
                d_dev, c_dev, e_dev, col_dev, sse_dev, it_dev, fl_dev, local_size=(1, 1))
    diffuse = backend.from_device(d_dev, (n, n_signal), np.float32)
    lobes = backend.from_device(c_dev, (n, k_total, 3), np.float32)
    exponents = backend.from_device(e_dev, (n, k_total), np.float32)
    colour = backend.from_device(col_dev, (n, n_channel), np.float32) if variant == "lum" else np.zeros((n, 0), np.float32)
    sse = backend.from_device(sse_dev, (n, n_signal), np.float32).astype(np.float64)
    its = backend.from_device(it_dev, (n, n_signal), np.int32)
    flag = backend.from_device(fl_dev, (n, n_signal), np.int32).astype(bool)
    return diffuse, lobes, exponents, colour, sse, flag, its


# ----------------------------------------------------------------------------------------------- driver


def _signal_scale(values: np.ndarray, variant: str) -> np.ndarray:
    """Each texel's scale, repeated for its ``G`` fitted signals ``[n, G]`` float64: the power of two at or above
    its largest sample magnitude (all channels), 0 for a black texel.  A power of two divides the samples
    exactly, so the scaled fit sees the very same digits (texels already peaking in (0.5, 1] are not touched);
    one scale per texel keeps the rgb channels' relative brightness, as the lum colour does."""
    peak = np.maximum(values.max(axis=0), -values.min(axis=0)).max(axis=1).astype(np.float64)[:, None]  # [n, 1]
    mantissa, exponent = np.frexp(peak)                                     # peak = mantissa 2^exponent, in [0.5, 1)
    scale = np.where(peak > 0, np.ldexp(1.0, exponent - (mantissa == 0.5)), 0.0)
    return np.repeat(scale, 1 if variant == "lum" else values.shape[2], axis=1)


def fit_band(values, frames, sample_lights, sample_views, per_fit, variant, iterations, engine):
    """Fit one band on either engine, each texel scaled to a peak in (0.5, 1] first and the result scaled back.

    LM's damping floor (``D_FLOOR`` x the largest diagonal entry) and the tolerances are relative, but the
    rho column of ``J'J`` does not scale with the data while the lobe columns go as ``y^2``: without this, dark
    texels were over-damped (1-lobe data x1e-6 recovered to 5e-3 only) and bright ones met ``T_CAP``.  Scaling a
    texel by ``m`` scales ``rho`` by ``m`` and each lobe's ``C`` by ``m^(1/n)`` (``alpha`` by ``ln m``); the
    lum colour is unchanged.  Black texels (``m = 0``) are fitted as they are and stay black.

    Returns ``(diffuse, lobes, exponents, colour, sse [n], not_converged [n], iterations [n])`` with the rgb
    lobes padded to ``RGB_LOBES`` per channel (unused ones switched off).
    """
    n = values.shape[1]
    scale = _signal_scale(values, variant)
    scale = np.where(scale > 0, scale, 1.0)
    normed = np.ldexp(values, -np.frexp(scale)[1][None] + 1).astype(np.float32, copy=False)   # exact: x / scale
    if engine == "numpy":
        res = fit_band_numpy(normed, frames, sample_lights, sample_views, per_fit, variant, iterations)
    else:
        res = fit_band_opencl(normed, frames, sample_lights, sample_views, per_fit, variant, iterations)
    diffuse, lob, expo, colour, sse, flag, its = res
    n_signal = diffuse.shape[1]
    stored = per_fit if variant == "lum" else RGB_LOBES
    if stored > per_fit:                     # rgb with 1 lobe per channel: the second is switched off
        lob = np.concatenate([lob.reshape(n, n_signal, per_fit, 3),
                              np.zeros((n, n_signal, stored - per_fit, 3), np.float32)], axis=2).reshape(n, -1, 3)
        expo = np.concatenate([expo.reshape(n, n_signal, per_fit),
                               np.full((n, n_signal, stored - per_fit), EXPONENT_MIN, np.float32)], axis=2).reshape(n, -1)
    expo = np.clip(expo, EXPONENT_MIN, EXPONENT_MAX)   # exp(ln n) may round a hair outside the bounds
    lobe_scale = np.exp(np.log(np.repeat(scale, stored, axis=1)) / expo.astype(np.float64))
    lob = (lob.astype(np.float64) * lobe_scale[..., None]).astype(np.float32)
    diffuse = (diffuse.astype(np.float64) * scale).astype(np.float32)
    sse = (np.asarray(sse, np.float64) * scale * scale).sum(axis=1)
    return diffuse, lob, expo.astype(np.float32), colour, sse, np.asarray(flag).any(axis=1), np.asarray(its).sum(axis=1)


def _check_fit_args(stack, lobes, variant, engine, iterations, normals):
    where = "lafortune.fit"
    if not isinstance(stack, SampleStack):
        raise BtforgeInputError(f"{where} 'stack'", f"expected a SampleStack, found {type(stack).__name__}")
    if variant not in VARIANTS:
        raise BtforgeInputError(f"{where} 'variant'", f"expected one of {', '.join(VARIANTS)}, found {variant!r}")
    if isinstance(lobes, bool) or not isinstance(lobes, (int, np.integer)) or not 1 <= lobes <= MAX_LOBES:
        raise BtforgeInputError(f"{where} 'lobes'", f"expected an int in [1, {MAX_LOBES}], found {lobes!r}")
    if variant == "rgb" and lobes > RGB_LOBES:
        raise BtforgeInputError(f"{where} 'lobes'", f"the rgb variant fits 1 or {RGB_LOBES} lobes per channel, "
                                f"found lobes={lobes}", "use variant 'lum' for more lobes (up to 7 on the luminance)")
    if engine not in ("opencl", "numpy"):
        raise BtforgeInputError(f"{where} 'engine'", f"expected 'opencl' or 'numpy', found {engine!r}")
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)) or iterations < 1:
        raise BtforgeInputError(f"{where} 'iterations'", f"expected an int >= 1, found {iterations!r}")
    if stack.n_channel > MAX_CHANNELS:
        raise BtforgeInputError(f"{where} 'stack'", f"expected at most {MAX_CHANNELS} channels, found {stack.n_channel}")
    per_fit = int(lobes)
    unknowns = 1 + 4 * per_fit
    samples = stack.n_view * stack.n_light
    if samples < unknowns:
        what = f"{per_fit} lobe(s)" + (" per channel" if variant == "rgb" else "")
        raise BtforgeInputError(
            f"{where} 'stack'", f"expected at least {unknowns} samples per texel for {what} ({unknowns} unknowns), "
            f"found {samples} ({stack.n_view} view(s) x {stack.n_light} light(s))",
            "capture more lights, or fit lobes=1 (5 unknowns, in either variant)" if per_fit > 1 else
            "capture more lights or views: a diffuse term and one lobe have 5 unknowns in either variant")
    if normals is not None:
        normals = check_array("normals", np.asarray(normals, np.float32), (stack.height, stack.width, 3), np.float32,
                              finite=True, owner=where)
        norms = np.linalg.norm(normals, axis=-1)
        if normals.size and norms.min() < 1e-6:
            row, col = np.argwhere(norms < 1e-6)[0]
            raise BtforgeInputError(f"{where} 'normals'", f"expected non-zero normals, found length {norms[row, col]:.3g} "
                                    f"at row {row}, column {col}", "give a unit normal for every texel, or leave "
                                    "'normals' unset to estimate them from the stack")
        normals = (normals / norms[..., None]).astype(np.float32)
        down = normals[..., 2] <= NORMAL_MIN_Z
        if down.any():
            # A normal at or below the surface plane puts every light and view (upper hemisphere) behind or
            # nearly behind the texel: the fit would return a black or meaningless texel.
            row, col = np.argwhere(down)[0]
            raise BtforgeInputError(
                f"{where} 'normals'", f"expected normals pointing up (n_z > {NORMAL_MIN_Z:g}, i.e. within "
                f"{math.degrees(math.acos(NORMAL_MIN_Z)):.1f} degrees of the surface normal), found "
                f"({', '.join(f'{v:.3g}' for v in normals[row, col])}) at row {row}, column {col} "
                f"({int(down.sum())} texel(s) in all)",
                "negate normals given in the opposite convention, or leave 'normals' unset to estimate them")
    return per_fit, normals


def fit_lafortune(stack: SampleStack, lobes: int | None = None, variant: str = "lum", *, engine: str = "opencl",
                  iterations: int = DEFAULT_ITERATIONS, budget_bytes: int = 64 << 20,
                  normals: np.ndarray | None = None) -> tuple[LafortuneModel, dict]:
    """Fit per-texel Lafortune lobes to a stack (single- or multi-view), streamed over bands of rows.

    Parameters
    ----------
    stack
        Any :class:`SampleStack`; 8-bit stacks are fitted in linear radiance.
    lobes
        Lobes per fitted signal: on the luminance (1-7) for ``lum``, on each channel (1 or 2) for ``rgb``; the
        rgb model always stores 2 per channel, the second switched off (``C = 0``) for 1.  None: the variant's
        usual count, 1 for ``lum`` and 2 per channel for ``rgb`` (McAllister's RGB model).
    variant
        ``lum``: lobes on the channel mean times a per-texel colour; ``rgb``: each channel its own lobes.
    engine
        ``opencl`` (one work-item per texel runs the whole fit) or ``numpy`` (the vectorised reference).
    iterations
        Levenberg-Marquardt iterations (tried steps) allowed per lobe stage.
    budget_bytes
        Linear samples held per band of rows.
    normals
        ``[H, W, 3]`` texel normals to use instead of the photometric-stereo estimate; each must point up
        (``n_z > NORMAL_MIN_Z`` once normalised).

    Returns
    -------
    model, info
        ``info``: ``not_converged`` (texels whose kept fit ran out of iterations), ``iterations`` (mean tried
        steps per texel, all stages and channels), ``iteration_limit``, ``rms`` (linear radiance over every
        sample and channel), ``texels``.
    """
    if lobes is None:
        lobes = RGB_LOBES if variant == "rgb" else 1
    per_fit, normals = _check_fit_args(stack, lobes, variant, engine, iterations, normals)
    h, w, n_channel = stack.height, stack.width, stack.n_channel
    n_signal = 1 if variant == "lum" else n_channel
    k_total = (per_fit if variant == "lum" else RGB_LOBES) * n_signal
    n_texel = h * w
    sample_lights, sample_views = _sample_directions(stack)
    out_n = np.empty((n_texel, 3), np.float32)
    out_d = np.empty((n_texel, n_signal), np.float32)
    out_c = np.empty((n_texel, k_total, 3), np.float32)
    out_e = np.empty((n_texel, k_total), np.float32)
    out_col = np.empty((n_texel, n_channel if variant == "lum" else 0), np.float32)
    sse_total, not_converged, its_total = 0.0, 0, 0
    for rows in stack.row_bands(budget_bytes):
        band = np.asarray(stack.linear(rows), np.float32)
        values = np.ascontiguousarray(band.reshape(stack.n_view * stack.n_light, -1, n_channel))
        texels = slice(rows.start * w, rows.stop * w)
        band_normals = (normals[rows].reshape(-1, 3) if normals is not None
                        else _normals_band(values, sample_lights))
        frames = texel_frames(band_normals)
        diffuse, lob, expo, colour, sse, flag, its = fit_band(values, frames, sample_lights, sample_views, per_fit,
                                                              variant, iterations, engine)
        out_n[texels] = frames[:, 2]
        out_d[texels], out_c[texels], out_e[texels], out_col[texels] = diffuse, lob, expo, colour
        sse_total += float(np.sum(sse))
        not_converged += int(np.count_nonzero(flag))
        its_total += int(np.sum(its))
    model = LafortuneModel(out_n.reshape(h, w, 3), out_d.reshape(h, w, n_signal), out_c.reshape(h, w, k_total, 3),
                           out_e.reshape(h, w, k_total), out_col.reshape(h, w, out_col.shape[1]), variant, stack.channels)
    count = n_texel * stack.n_view * stack.n_light * n_channel
    info = {
        "not_converged": not_converged,
        "iterations": its_total / max(n_texel, 1),
        "iteration_limit": int(iterations),
        "rms": math.sqrt(sse_total / max(count, 1)),
        "texels": n_texel,
    }
    return model, info
