"""The lower layer of the shared neighbourhood search: windows, principal projections and packed neighbour
lists, used by the search (:mod:`.search`) and its self-join (:mod:`.selfjoin`) alike."""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from btforge.backend import single_threaded_blas
from btforge.errors import BtforgeInputError

FAST_ENERGY = 0.98          #: share of the exemplar's variance the fast engine's reduced vectors keep
FAST_MAX_DIMS = 24
FAST_MIN_DIMS = 8
SUBSPACE_EXTRA = 8          #: extra columns of the subspace iteration beyond the axes that can be kept
SUBSPACE_ITERATIONS = 24


def cores() -> int:
    """The CPUs this process may run on (what a parallel k-d tree query or decode should use)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


# ============================================================================================ windows


def square_window(size: int) -> np.ndarray:
    """Offsets ``[size^2, 2]`` (dy, dx) of an odd ``size x size`` window around its centre, row-major."""
    if size < 1 or size % 2 == 0:
        raise BtforgeInputError("neighbourhood window", f"expected an odd size >= 1, found {size}", "use 3, 5, 7 ...")
    r = size // 2
    dy, dx = np.mgrid[-r:r + 1, -r:r + 1]
    return np.column_stack([dy.ravel(), dx.ravel()]).astype(np.int32)


def causal_window(size: int) -> np.ndarray:
    """The offsets of the ``size x size`` window that come before its centre in scanline order (L-shaped)."""
    offs = square_window(size)
    return offs[(offs[:, 0] < 0) | ((offs[:, 0] == 0) & (offs[:, 1] < 0))]


def band_window(block: int, top: int = 0, bottom: int = 0, left: int = 0, right: int = 0) -> np.ndarray:
    """Texels ``[n, 2]`` (row, column) of a ``block x block`` block within the given widths of its edges,
    row-major: the overlap a quilting block shares with its synthesized neighbours."""
    yy, xx = np.indices((block, block))
    inside = (yy < top) | (yy >= block - bottom) | (xx < left) | (xx >= block - right)
    return np.column_stack([yy[inside], xx[inside]]).astype(np.int32)


def l_shaped_window(block: int, overlap: int) -> np.ndarray:
    """The top and left overlap strips of a block (scanline quilting's overlap), row-major."""
    return band_window(block, top=overlap, left=overlap)


# ============================================================================================ principal projections


@dataclasses.dataclass(frozen=True)
class Projection:
    """An orthogonal projection onto the leading principal axes of a set of vectors."""

    mean: np.ndarray    # [D] float32
    axes: np.ndarray    # [D, d] float32, orthonormal columns
    energy: float       # share of the variance kept

    def apply(self, x: np.ndarray) -> np.ndarray:
        with single_threaded_blas():  # x @ axes - mean @ axes: no centred copy of x (236 MB at 512 x 512)
            return np.ascontiguousarray(x @ self.axes - self.mean @ self.axes, dtype=np.float32)


def principal_projection(x: np.ndarray, *, energy: float | None = None, max_dims: int | None = None,
                         min_dims: int | None = None, sample: int = 4096, seed: int = 0) -> Projection:
    """The fewest leading principal axes of ``x`` ``[N, D]`` that keep ``energy`` of its variance (clipped to
    ``[min_dims, max_dims]`` and to D), fitted on at most ``sample`` rows.  Defaults: the ``FAST_*`` settings."""
    energy = FAST_ENERGY if energy is None else energy
    max_dims = FAST_MAX_DIMS if max_dims is None else max_dims
    min_dims = FAST_MIN_DIMS if min_dims is None else min_dims
    rng = np.random.default_rng(seed)
    pick = x if len(x) <= sample else x[np.sort(rng.choice(len(x), sample, replace=False))]
    mean = pick.mean(axis=0, dtype=np.float64)
    centred = (pick - mean).astype(np.float32)  # the axes only steer the search: float32 products suffice
    with single_threaded_blas():
        covariance = (centred.T @ centred).astype(np.float64)
        values, axes = leading_eigenpairs(covariance, max_dims + SUBSPACE_EXTRA, seed=seed)
    total = float(np.trace(covariance))
    kept = np.cumsum(values) / total if total > 0 else np.ones(len(values))
    dims = int(np.clip(np.searchsorted(kept, energy - 1e-12) + 1, min(min_dims, x.shape[1]), min(max_dims, x.shape[1])))
    return Projection(mean.astype(np.float32), np.ascontiguousarray(axes[:, :dims], np.float32), float(kept[dims - 1]))


def leading_eigenpairs(matrix: np.ndarray, count: int, *, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` largest eigenvalues (descending, >= 0) and eigenvectors of a symmetric PSD matrix.

    Large matrices go by subspace iteration with a Rayleigh-Ritz step: a few products with a thin block, never
    a full eigendecomposition (an 800 x 800 one costs more than the whole iteration).  The axes only steer the
    search (candidates are re-ranked at full dimension), so the iteration need not converge to the last digit.
    BLAS runs on one thread here (:func:`btforge.backend.single_threaded_blas`).
    """
    d = len(matrix)
    with single_threaded_blas():
        if d <= 2 * count:
            values, vectors = np.linalg.eigh(matrix)
            return np.clip(values[::-1][:count], 0, None), vectors[:, ::-1][:, :count]
        block = np.linalg.qr(np.random.default_rng(seed).standard_normal((d, count)))[0]
        for _ in range(SUBSPACE_ITERATIONS):
            block = np.linalg.qr(matrix @ block)[0]
        values, vectors = np.linalg.eigh(block.T @ (matrix @ block))
        return np.clip(values[::-1], 0, None), block @ vectors[:, ::-1]


# ============================================================================================ neighbour lists


def empty_lists(m: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """``m`` lists of ``k`` missing neighbours: rows -1, distances inf."""
    return np.full((m, k), -1, np.int32), np.full((m, k), np.inf, np.float32)


NONE_KEY = np.iinfo(np.int64).max   # the packed key of a missing entry: after every real one


def packed(dist: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(squared distance, row) pairs as one int64 key each, ordered as the pairs are: a non-negative float32's
    bits grow with its value, so ``bits << 32 | row`` sorts by distance, then row; -1 rows become :data:`NONE_KEY`."""
    key = np.ascontiguousarray(dist, np.float32).view(np.int32).astype(np.int64)
    key <<= 32
    key |= np.maximum(rows, 0)
    key[rows < 0] = NONE_KEY
    return key


def smallest(keys: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` smallest :func:`packed` keys of each row, unpacked: ``(rows [M, k] int64, dist [M, k] float32)``,
    -1 and inf where there are fewer than ``k``."""
    if keys.shape[1] < k:
        keys = np.concatenate([keys, np.full((len(keys), k - keys.shape[1]), NONE_KEY, np.int64)], axis=1)
    elif keys.shape[1] > k:
        keys = np.partition(keys, k - 1, axis=1)[:, :k]
    keys = np.sort(keys, axis=1)
    missing = keys == NONE_KEY
    rows = np.where(missing, -1, keys & 0xFFFFFFFF)
    dist = np.where(missing, np.int32(0x7F800000), (keys >> 32).astype(np.int32)).view(np.float32)
    return rows, dist
