"""Per-texel normals by robust photometric stereo: the frame every Lafortune lobe is fitted in.

A trimmed least-squares start (the darkest and brightest samples of each texel dropped) refined by
Tukey-reweighted least squares over the lit samples; pieces of texels run on one thread per core.
"""
from __future__ import annotations

import os

import numpy as np

from btforge.buffers import SampleStack



DARK_FRACTION = 0.3     # photometric stereo drops this fraction of each texel's darkest samples (shadows) ...
BRIGHT_FRACTION = 0.3   # ... and this fraction of its brightest (highlights)
NORMAL_MIN_Z = 0.05
PS_RIDGE = 1e-4         # tangential components of b are damped by this x trace(L'L): clustered lights -> up
PS_Z_RIDGE = 1e-12      # ... and the normal component by this x trace: L'L stays invertible for coplanar lights
PS_IRLS_STEPS = 4       # reweighted least-squares steps after the trimmed start
PS_HORIZON = 0.05       # a light with n . l at or below this is in attached shadow and left out
PS_TUKEY = 4.685        # Tukey's biweight (1 - (r / (PS_TUKEY s))^2)^2, s = 1.4826 x median |r| (95 % efficient)
PS_SCALE_FLOOR = 1e-3   # s >= this x the texel's brightest sample (exact data: s = 0 would weight by noise)


# The per-texel products below are small ([n, S] x [S, 9]): np.einsum's own loops run them on the calling thread,
# where `@` hands them to a multi-threaded BLAS whose threads cost more than the products (2-3x the whole
# normal estimate's CPU time on a busy machine).
_UPPER = np.array([0, 1, 2, 1, 3, 4, 2, 4, 5])   # 3 x 3 symmetric matrix from its 6 upper entries


def _solve_normals(weight, lum, ld):
    """Weighted least squares ``lum ~ b . l`` per texel with the tangential ridge -> ``b [n, 3]``."""
    rows, cols = np.triu_indices(3)
    a = np.einsum("ns,sk->nk", weight, ld[:, rows] * ld[:, cols])[:, _UPPER].reshape(-1, 3, 3)
    rhs = np.einsum("ns,sk->nk", weight * lum, ld)
    trace = np.maximum(np.trace(a, axis1=1, axis2=2), 1e-30)
    a[:, 0, 0] += PS_RIDGE * trace
    a[:, 1, 1] += PS_RIDGE * trace
    a[:, 2, 2] += PS_Z_RIDGE * trace
    return np.linalg.solve(a, rhs[..., None])[..., 0]


def _trimmed_weights(lum):
    """0/1 weights dropping each texel's darkest and brightest samples (by value, ties included)."""
    n_texel, s = lum.shape
    n_dark = int(DARK_FRACTION * s)
    n_bright = int(BRIGHT_FRACTION * s)
    if s - n_dark - n_bright < 3:
        n_dark = n_bright = 0
    # Trim by value, not by position: every sample tied with the last dropped one is dropped too, so clipped
    # (0 or saturated) runs go as a whole and the normal does not depend on the order of the lights.
    ordered = np.sort(lum, axis=1)
    low = ordered[:, n_dark - 1:n_dark] if n_dark else np.full((n_texel, 1), -np.inf)
    high = ordered[:, s - n_bright:s - n_bright + 1] if n_bright else np.full((n_texel, 1), np.inf)
    keep = (lum > low) & (lum < high)
    keep[keep.sum(axis=1) < 3] = True            # ties left too few samples: use them all
    return keep


def _tukey_weights(resid, scale):
    u = resid / (PS_TUKEY * scale)
    u *= u
    np.subtract(1.0, u, out=u)
    np.maximum(u, 0.0, out=u)
    return np.square(u, out=u)


def _masked_median(values, mask):
    """Per row, the median of ``values`` where ``mask`` -> ``[n, 1]`` (0 for a row with nothing masked in)."""
    ordered = np.sort(np.where(mask, values, np.inf), axis=1)
    count = mask.sum(axis=1)
    rows = np.arange(len(values))
    low = ordered[rows, np.maximum((count - 1) // 2, 0)]
    high = ordered[rows, np.maximum(count // 2, 0)]
    return np.where(count > 0, 0.5 * (low + high), 0.0)[:, None]


def _reweighted_normals(b, lum, ld, bright):
    """``PS_IRLS_STEPS`` reweighted least-squares steps from ``b [n, 3]`` -> ``(b, robust scale [n, 1])``."""
    scale = np.zeros((len(b), 1))
    # A run of samples tied at the texel's top value is saturated: the true value is unknown, not an outlier.
    top = lum >= bright[:, None]
    clipped = top & (top.sum(axis=1, keepdims=True) >= 2)
    for _ in range(PS_IRLS_STEPS):
        pred = np.einsum("nj,sj->ns", b, ld)
        lit = pred > PS_HORIZON * np.linalg.norm(b, axis=1, keepdims=True)
        resid = lum - pred
        scale = 1.4826 * _masked_median(np.abs(resid), lit)
        scale = np.maximum(scale, PS_SCALE_FLOOR * bright[:, None] + 1e-30)
        enough = lit.sum(axis=1) >= 3
        weight = np.where(enough[:, None], (lit & ~clipped) * _tukey_weights(resid, scale), 1.0)
        b = np.where(enough[:, None], _solve_normals(weight, lum, ld), b)
    return b, scale


PS_THREAD_TEXELS = 4096  # photometric stereo works on pieces of this many texels, one thread per core: each
                         # texel's normal is its own, NumPy releases the GIL in its array loops, and a piece's
                         # arrays stay in the cache (320^2 texels: 1.2 s CPU in one piece, 0.84 s in these)


def _normals_band(values: np.ndarray, sample_lights: np.ndarray) -> np.ndarray:
    """Robust photometric stereo of ``values [S, n, C]`` lit from ``sample_lights [S, 3]`` -> ``[n, 3]`` float32."""
    n = values.shape[1]
    pieces = [slice(start, min(start + PS_THREAD_TEXELS, n)) for start in range(0, n, PS_THREAD_TEXELS)]
    threads = min(os.cpu_count() or 1, len(pieces))
    if threads < 2:
        return _normals_part(values, sample_lights)
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(threads) as pool:
        return np.concatenate(list(pool.map(lambda piece: _normals_part(values[:, piece], sample_lights), pieces)))


def _normals_part(values: np.ndarray, sample_lights: np.ndarray) -> np.ndarray:
    lum = np.ascontiguousarray(values.mean(axis=2, dtype=np.float64).T)   # [n, S]
    keep = _trimmed_weights(lum)
    kept_lo = np.where(keep, lum, np.inf).min(axis=1)
    kept_hi = np.where(keep, lum, -np.inf).max(axis=1)
    spread = kept_hi > kept_lo                   # no spread (a constant texel) says nothing about the normal
    ld = sample_lights.astype(np.float64)
    bright = np.abs(lum).max(axis=1)
    # Reweighted least squares over every sample from the trimmed start: a light the current normal puts at or
    # below the horizon carries no linear information (attached shadow) and is left out; the others are weighted
    # by Tukey's biweight of their residual against a robust scale, so cast shadows and highlights lose their
    # pull (far ones entirely) while the clean samples the trim dropped count again - which matters most when
    # lights are few.  (Starting from plain least squares as well and keeping the lower robust loss was tried:
    # highlights inflate the scale and the loss then often picks the worse start.)
    b, _ = _reweighted_normals(_solve_normals(keep.astype(np.float64), lum, ld), lum, ld, bright)
    norm = np.linalg.norm(b, axis=1)
    good = (norm > 1e-12 * np.maximum(bright, 1e-30)) & (bright > 0) & np.isfinite(norm) & spread
    normals = np.where(good[:, None], b / np.where(good, norm, 1.0)[:, None], [0.0, 0.0, 1.0])
    normals[normals[:, 2] <= NORMAL_MIN_Z] = (0.0, 0.0, 1.0)
    return normals.astype(np.float32)


def _sample_directions(stack: SampleStack) -> tuple[np.ndarray, np.ndarray]:
    """World light and view of every sample ``s = view * L + light``: ``[S, 3]`` each."""
    lights = np.tile(stack.lights, (stack.n_view, 1))
    views = np.repeat(stack.views, stack.n_light, axis=0)
    return lights, views


def estimate_normals(stack: SampleStack, budget_bytes: int = 64 << 20) -> np.ndarray:
    """Per-texel normals ``[H, W, 3]`` float32 by robust photometric stereo on the luminance.

    Least squares ``I ~ b . l`` over every (view, light) sample of a texel, after dropping its darkest 30 % (cast
    and attached shadows) and brightest 30 % (highlights), together with every sample equal to the last one
    dropped (so ties - clipped or saturated runs - never depend on the order of the lights; all samples are used
    when fewer than 3 would remain); the tangential part of ``b`` is slightly damped so clustered lights give a
    near-vertical normal rather than noise.  ``n = b / |b|``, or ``(0, 0, 1)`` for a black or constant texel
    (kept samples without spread) or one whose ``n_z <= 0.05``.
    """
    sample_lights, _ = _sample_directions(stack)
    out = np.empty((stack.height, stack.width, 3), np.float32)
    for rows in stack.row_bands(budget_bytes):
        band = np.asarray(stack.linear(rows))
        values = band.reshape(stack.n_view * stack.n_light, -1, stack.n_channel)
        out[rows] = _normals_band(values, sample_lights).reshape(-1, stack.width, 3)
    return out
