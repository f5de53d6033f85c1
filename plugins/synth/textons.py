"""Texton analysis: the exemplar's appearance vectors clustered by k-means, with a table of cluster distances.

Synthesizers that compare many candidate neighbourhoods (k-coherence, jump maps) quantise each texel to its
cluster (its *texton*) so that a texel distance is one lookup in a ``[T, T]`` table.  The features are scaled into
[-1, 1] first (:func:`normalise_features`); seeding is k-means++ on a sample, with a fixed iteration cap and seed,
and the assignment runs on OpenCL (``textons.cl``, ``kmeans_assign``) with a NumPy twin of the same float32
arithmetic (:func:`assign_numpy`).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from btforge.backend import get_backend
from btforge.errors import BtforgeInputError

from .device import launch

KERNELS = Path(__file__).with_name("textons.cl")
DEFAULT_TEXTONS = 256        #: cluster count of the texton analysis (capped by the texel count of a level)
KMEANS_ITERATIONS = 6        #: Lloyd iterations at most (stops earlier when no label changes)
KMEANS_SEED_SAMPLE = 4096    #: k-means++ seeding runs on a sample of at most this many texels (>= 2 x textons)
KMEANS_FIT_SAMPLE = 32       #: Lloyd iterations run on at most this many texels per texton (all are assigned at the end)
ANALYSIS_SEED = 0            #: the analysis does not depend on the synthesis seed (same exemplar, same textons)


@dataclasses.dataclass(frozen=True)
class Textons:
    """The texton map of one exemplar level.

    ``labels`` ``[H, W]`` int32 texton ids; ``centres`` ``[T, D]`` float32 appearance vectors (cluster means);
    ``table`` ``[T, T]`` float32 squared distances between the centres (>= 0, zero diagonal);
    ``iterations`` the Lloyd iterations run; ``error`` the mean squared quantisation error relative to the
    features' total variance (0 = exact).
    """

    labels: np.ndarray
    centres: np.ndarray
    table: np.ndarray
    iterations: int
    error: float

    @property
    def count(self) -> int:
        return int(self.centres.shape[0])


def normalise_features(features: np.ndarray) -> np.ndarray:
    """Features scaled by their largest magnitude into [-1, 1] (float32): huge values cannot overflow a distance."""
    f = np.asarray(features, dtype=np.float64)
    if f.size and not np.isfinite(f).all():
        raise BtforgeInputError("synthesis 'exemplar'", "expected finite appearance values, found NaN/Inf",
                                "repair the exemplar before synthesis")
    scale = float(np.abs(f).max()) if f.size else 0.0
    if scale > 0:
        f = f / scale
    return np.ascontiguousarray(f, dtype=np.float32)


def kmeans_pp_seeds(x: np.ndarray, n: int, rng: np.random.Generator, sample: int = KMEANS_SEED_SAMPLE) -> np.ndarray:
    """k-means++ seeding on a sample of the rows of ``x``: ``min(sample, 8 n)`` rows, at least ``2 n``.

    Stops early when every sampled point is already a centre (fewer distinct points than ``n``).
    """
    size = min(len(x), max(min(sample, 8 * n), 2 * n))
    pool = x if len(x) <= size else x[np.sort(rng.choice(len(x), size, replace=False))]
    pool = np.ascontiguousarray(pool, dtype=np.float32)
    chosen = [int(rng.integers(len(pool)))]
    d2 = ((pool - pool[chosen[0]]) ** 2).sum(axis=1, dtype=np.float64)
    while len(chosen) < n:
        cumulative = np.cumsum(d2)
        total = cumulative[-1]
        if not total > 0:
            break  # fewer distinct points than centres asked for
        pick = min(int(np.searchsorted(cumulative, rng.random() * total, side="right")), len(pool) - 1)
        if d2[pick] <= 0:  # rounding at the end of the cumulative sum; take the farthest point instead
            pick = int(np.argmax(d2))
        chosen.append(pick)
        np.minimum(d2, ((pool - pool[pick]) ** 2).sum(axis=1, dtype=np.float64), out=d2)
    return pool[chosen]




def assign_numpy(x: np.ndarray, centres: np.ndarray, chunk: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """Twin of ``kmeans_assign``: nearest centre (first on ties) and its squared distance, in float32."""
    n, d = x.shape
    labels = np.empty(n, np.int32)
    dist = np.empty(n, np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        for start in range(0, n, chunk):
            xs = x[start:start + chunk]
            acc = np.zeros((len(xs), len(centres)), np.float32)
            for j in range(d):
                t = xs[:, j, None] - centres[None, :, j]
                acc += t * t
            labels[start:start + chunk] = np.argmin(acc, axis=1)
            dist[start:start + chunk] = acc[np.arange(len(xs)), labels[start:start + chunk]]
    return labels, dist


def assign_opencl(x: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest centre of every row of ``x`` on OpenCL (``kmeans_assign``)."""
    backend = get_backend()
    n, d = x.shape
    kernel = backend.kernel(KERNELS, "kmeans_assign", (f"-DDIM={d}",))
    labels_dev = backend.empty(4 * n)
    dist_dev = backend.empty(4 * n)
    launch(backend, kernel, (n,), backend.to_device(np.ascontiguousarray(x, np.float32)),
                backend.to_device(np.ascontiguousarray(centres, np.float32)), np.int32(n),
                np.int32(len(centres)), labels_dev, dist_dev)
    return backend.from_device(labels_dev, (n,), np.int32), backend.from_device(dist_dev, (n,), np.float32)


def kmeans(x: np.ndarray, n: int, seed: int = ANALYSIS_SEED, iterations: int = KMEANS_ITERATIONS,
           engine: str = "opencl") -> tuple[np.ndarray, np.ndarray, int]:
    """Lloyd's k-means on the rows of ``x`` ``[N, D]`` float32: ``(labels [N], centres [T, D], iterations)``.

    k-means++ seeding (fewer than ``n`` centres when there are fewer distinct points), at most ``iterations``
    rounds (on a sample of :data:`KMEANS_FIT_SAMPLE` rows per centre when ``x`` has more than twice that), an
    emptied cluster keeps its centre.  Deterministic for a given ``seed``.
    """
    assign = assign_opencl if engine == "opencl" else assign_numpy
    rng = np.random.default_rng(seed)
    centres = kmeans_pp_seeds(x, max(1, min(n, len(x))), rng)
    # the centres settle on a sample; every texel is labelled once at the end (a 192^2 level: 6x less work)
    fit_rows = KMEANS_FIT_SAMPLE * len(centres)
    if len(x) > 2 * fit_rows:
        sample = x[np.sort(rng.choice(len(x), fit_rows, replace=False))]
        _, centres, done = _lloyd(sample, centres, iterations, assign)
        return assign(x, centres)[0], centres, done
    return _lloyd(x, centres, iterations, assign)


def _lloyd(x, centres, iterations, assign):
    labels, _ = assign(x, centres)
    done = 0
    for done in range(1, iterations + 1):
        counts = np.bincount(labels, minlength=len(centres))
        sums = np.stack([np.bincount(labels, weights=x[:, j].astype(np.float64), minlength=len(centres))
                         for j in range(x.shape[1])], axis=1)
        filled = counts > 0
        centres = centres.copy()
        centres[filled] = (sums[filled] / counts[filled, None]).astype(np.float32)
        new_labels, _ = assign(x, centres)
        changed = bool((new_labels != labels).any())
        labels = new_labels
        if not changed:
            break
    return labels, centres, done


def texton_table(centres: np.ndarray, chunk: int = 64) -> np.ndarray:
    """Squared distances between every two centres ``[T, T]`` float32 (zero diagonal, symmetric, >= 0).

    Summed directly from the differences (no BLAS), so the table does not depend on threading or blocking.
    """
    c = centres.astype(np.float64)
    table = np.empty((len(c), len(c)), np.float32)
    for start in range(0, len(c), chunk):
        table[start:start + chunk] = ((c[start:start + chunk, None, :] - c[None, :, :]) ** 2).sum(axis=2)
    table = np.minimum(table, table.T)  # exactly symmetric
    np.fill_diagonal(table, 0.0)
    return table


def texton_analysis(features: np.ndarray, n_textons: int = DEFAULT_TEXTONS, *, seed: int = ANALYSIS_SEED,
                    engine: str = "opencl") -> Textons:
    """Cluster ``[H, W, D]`` float32 features into at most ``n_textons`` textons (see the module docstring)."""
    h, w, d = features.shape
    x = np.ascontiguousarray(features.reshape(-1, d), dtype=np.float32)
    few = _at_most_distinct(x, n_textons)
    if few is not None:
        # no more distinct vectors than textons (small or flat levels): every vector is its own texton, exactly
        distinct, inverse = few
        labels, centres, iterations = inverse.reshape(-1).astype(np.int32), np.ascontiguousarray(distinct), 0
    else:
        labels, centres, iterations = kmeans(x, n_textons, seed, engine=engine)
    residual = x.astype(np.float64) - centres[labels].astype(np.float64)
    variance = float(((x - x.mean(axis=0)) ** 2).sum())
    error = float((residual ** 2).sum() / variance) if variance > 0 else 0.0
    return Textons(labels.reshape(h, w).astype(np.int32), centres, texton_table(centres), iterations, error)


def _at_most_distinct(x: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``np.unique(x, axis=0, return_inverse=True)`` when ``x`` has at most ``n`` distinct rows, else None.

    Equal rows have equal hashes, so more than ``n`` distinct hashes prove more than ``n`` distinct rows without
    the (several times dearer) exact row sort; only a few distinct hashes lead to the exact count."""
    bits = np.ascontiguousarray(x + np.float32(0)).view(np.uint32).astype(np.uint64)  # -0.0 hashes as 0.0
    weights = (np.arange(1, x.shape[1] + 1, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15))
    if len(np.unique((bits * weights).sum(axis=1))) > n:
        return None
    distinct, inverse = np.unique(x, axis=0, return_inverse=True)
    return (distinct, inverse) if len(distinct) <= n else None
