"""The quilting search: the overlap distances of every candidate block, brute force or by exact rejection.

The search is the costly part.  ``brute`` computes every candidate's overlap distance on OpenCL.  ``rejection``
(Hel-Or & Hel-Or 2002) projects every candidate's unfolded overlap vector, once per overlap shape, onto an
orthonormal basis: the 2D Haar functions of the overlap's rectangles, one feature dimension at a time (piecewise
constant like Walsh-Hadamard kernels, so each projection of every candidate costs a few summed-area-table reads),
ordered by their energy over the candidates.  For a query, the sum of squared projected differences over the first
k functions is a lower bound on the full distance, so a candidate whose bound exceeds ``(1 + tolerance)`` x the
best full distance known can never be eligible and is dropped; the survivors get full distances computed exactly as
the brute-force kernel computes them, so both searches see bit-identical distances, the same eligible set and the
same random pick.  Safety margins on the threshold cover every rounding error involved (see
:meth:`QuiltSearch._reject`).

Candidates are all block positions lying wholly inside the exemplar (the exemplar is not treated as periodic).
Every kernel (``quilting.cl``) has a NumPy twin here.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np

from .search_base import band_window

KERNELS = Path(__file__).with_name("quilting.cl")

N_PROJECTIONS = 1024    # most projections kept per overlap shape (a projection costs O(1) per candidate)
PROJECTION_BUDGET = 128 << 20  # bytes of stored projections over all shapes (wrapping needs more shapes)
MIN_PROJECTIONS = 32
SEED_PROJECTIONS = 64   # projections whose lower bound nominates the candidates that set the threshold
SEED_CANDIDATES = 8     # how many of the lowest bounds get a full distance for the threshold
BASIS_SAMPLE = 512      # candidates sampled to rank the basis functions by energy
BASIS_SEED = 12345      # the basis affects speed only, never the result, so it does not follow the user's seed
LAUNCH_MULTIPLE = 64    # global sizes are padded to this, so the device can pick wide work-groups
PROJECT_RUN = 64        # functions per work-item in quilt_project (as in quilting.cl)
_U32 = 2.0 ** -24       # unit roundoff of float32 and float64
_U64 = 2.0 ** -53
_FLOAT32_MAX = float(np.finfo(np.float32).max)

SEARCHES = ("rejection", "brute")


# ----------------------------------------------------------------------------------------------- projection basis


def haar_1d(n: int) -> list[tuple[int, list[tuple[int, int, float]]]]:
    """An orthonormal Haar basis of length ``n`` (any n, halves split unevenly when odd), coarse to fine.

    Each function is ``(level, pieces)`` with pieces ``(start, stop, value)``: the constant ``1 / sqrt(n)`` at level
    0, then for every interval of the dyadic splitting a +/- step that sums to zero and has unit norm.
    """
    funcs = [(0, [(0, n, 1.0 / math.sqrt(n))])]
    queue = [(0, n, 1)]
    while queue:
        a, b, level = queue.pop(0)
        if b - a < 2:
            continue
        m = a + (b - a) // 2
        n1, n2 = m - a, b - m
        scale = math.sqrt(n1 * n2 / (b - a))
        funcs.append((level, [(a, m, scale / n1), (m, b, -scale / n2)]))
        queue += [(a, m, level + 1), (m, b, level + 1)]
    return funcs


def shape_rectangles(block: int, key: tuple[int, int, int, int]) -> list[tuple[int, int, int, int]]:
    """Disjoint rectangles ``(y0, x0, h, w)`` covering an overlap: full-width top and bottom strips, then the left
    and right strips between them."""
    t, b, l, r = key
    rects = [(0, 0, t, block), (block - b, 0, b, block), (t, 0, block - t - b, l), (t, block - r, block - t - b, r)]
    return [rc for rc in rects if rc[2] > 0 and rc[3] > 0]


@dataclasses.dataclass(frozen=True)
class HaarSet:
    """Orthonormal basis functions of an overlap: 2D Haar functions of its rectangles, one feature dimension each.

    Function j lives on feature dimension ``dims[j]`` and is ``coefs[j, b]`` on box ``boxes[j, b] = (y0, x0, y1, x1)``
    (block coordinates, half-open; unused boxes have coefficient 0).  Functions of different rectangles or
    dimensions have disjoint supports, so the whole set is orthonormal.
    """

    dims: np.ndarray     # [K] int32
    boxes: np.ndarray    # [K, 4, 4] int32
    coefs: np.ndarray    # [K, 4] float64

    def __len__(self) -> int:
        return len(self.dims)

    def take(self, order) -> "HaarSet":
        return HaarSet(self.dims[order], self.boxes[order], self.coefs[order])

    def padded(self, multiple: int = 8) -> "HaarSet":
        """The same functions followed by zero functions up to a multiple of ``multiple`` (their projections are 0,
        so they change no bound; the rejection kernel consumes projections 8 at a time)."""
        extra = -len(self) % multiple
        if not extra:
            return self
        return HaarSet(np.concatenate([self.dims, np.zeros(extra, np.int32)]),
                       np.concatenate([self.boxes, np.zeros((extra, 4, 4), np.int32)]),
                       np.concatenate([self.coefs, np.zeros((extra, 4))]))

    @property
    def coef_abs(self) -> np.ndarray:
        return np.abs(self.coefs).sum(axis=1)

    def dense(self, dy: np.ndarray, dx: np.ndarray, n_dims: int) -> np.ndarray:
        """The functions unfolded like the overlap vectors: ``[len(dy) * n_dims, K]`` float64."""
        out = np.zeros((len(dy) * n_dims, len(self)))
        rows = np.arange(len(dy)) * n_dims
        for j in range(len(self)):
            for (y0, x0, y1, x1), w in zip(self.boxes[j], self.coefs[j]):
                if w:
                    inside = (dy >= y0) & (dy < y1) & (dx >= x0) & (dx < x1)
                    out[rows[inside] + self.dims[j], j] = w
        return out


def haar_functions(block: int, key: tuple[int, int, int, int], n_dims: int, limit: int = 4096) -> HaarSet:
    """The Haar basis of an overlap shape for every feature dimension, coarsest first, at most ``limit`` functions."""
    entries = []
    for ri, (y0, x0, h, w) in enumerate(shape_rectangles(block, key)):
        for ly, fy in haar_1d(h):
            for lx, fx in haar_1d(w):
                boxes = [(y0 + a, x0 + c, y0 + b, x0 + d, u * v) for a, b, u in fy for c, d, v in fx]
                entries.append((ly + lx, ri, boxes))
    entries.sort(key=lambda e: (e[0], e[1]))
    k = min(limit, len(entries) * n_dims)
    dims = np.empty(k, np.int32)
    boxes = np.zeros((k, 4, 4), np.int32)
    coefs = np.zeros((k, 4))
    j = 0
    for _, _, fboxes in entries:
        for d in range(n_dims):
            if j == k:
                break
            dims[j] = d
            for b, (y0, x0, y1, x1, w) in enumerate(fboxes):
                boxes[j, b] = (y0, x0, y1, x1)
                coefs[j, b] = w
            j += 1
    return HaarSet(dims, boxes, coefs)


def summed_area(values: np.ndarray) -> np.ndarray:
    """Summed-area tables ``[D, H + 1, W + 1]`` float64 of ``values [H, W, D]``: entry (y, x) sums rows < y and
    columns < x."""
    h, w, d = values.shape
    sat = np.zeros((d, h + 1, w + 1))
    sat[:, 1:, 1:] = np.moveaxis(values, 2, 0).astype(np.float64).cumsum(axis=1).cumsum(axis=2)
    return sat


# ----------------------------------------------------------------------------------------------- kernels + twins


def ssd_numpy(feats: np.ndarray, bases: np.ndarray, offsets: np.ndarray, query: np.ndarray,
              budget: int = 1 << 24) -> np.ndarray:
    """Reference of ``quilt_ssd``: overlap distances ``[n_cand]`` float32 (computed in float64).

    ``feats`` is ``[H, W, D]`` (or ``[H * W, D]``), ``bases`` / ``offsets`` flat texel indices (see quilting.cl),
    ``query`` ``[n_pix, D]``.
    """
    d = feats.shape[-1]
    flat = feats.reshape(-1, d)
    q = np.asarray(query, np.float64).reshape(len(offsets), d)
    out = np.empty(len(bases), np.float32)
    step = max(1, budget // max(1, len(offsets) * d))
    for start in range(0, len(bases), step):
        block = flat[bases[start:start + step, None] + offsets[None, :]].astype(np.float64)
        out[start:start + step] = ((block - q) ** 2).sum(axis=(1, 2))
    return out


def project_numpy(sat: np.ndarray, rows: np.ndarray, cols: np.ndarray, funcs: HaarSet) -> np.ndarray:
    """Reference of ``quilt_project``: ``[K, n_cand]`` float32 projections of the candidates at (rows, cols)."""
    out = np.empty((len(funcs), len(rows)), np.float32)
    for j in range(len(funcs)):
        s = sat[funcs.dims[j]]
        acc = np.zeros(len(rows))
        for (y0, x0, y1, x1), w in zip(funcs.boxes[j], funcs.coefs[j]):
            if w:
                acc += w * (((s[rows + y1, cols + x1] - s[rows + y0, cols + x1]) - s[rows + y1, cols + x0])
                            + s[rows + y0, cols + x0])
        out[j] = acc
    return out


def project_dense(feats: np.ndarray, bases: np.ndarray, offsets: np.ndarray, basis: np.ndarray,
                  mean: np.ndarray) -> np.ndarray:
    """The definition the projections implement: ``(overlap vector - mean) . basis`` ``[K, n_cand]`` float64."""
    d = feats.shape[-1]
    x = feats.reshape(-1, d)[bases[:, None] + offsets[None, :]].astype(np.float64) - mean
    return (x.reshape(len(bases), -1) @ basis).T


def reject_numpy(proj: np.ndarray, qproj: np.ndarray, limit: np.ndarray, feats: np.ndarray, bases: np.ndarray,
                 offsets: np.ndarray, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference of ``quilt_reject`` (``proj [K, n_cand]``, K a multiple of 8): ``used [n_cand]`` int32 - the same
    float32 operations in the same order as the kernel, so identical - and ``dist [n_cand]`` float32 (survivors:
    the overlap distance as :func:`ssd_numpy` computes it; dropped: the lower bound that dropped them)."""
    k, n = proj.shape
    q = np.asarray(qproj, np.float32)
    lim = np.asarray(limit, np.float32)
    used = np.full(n, k + 1, np.int32)
    lb = np.zeros(n, np.float32)
    alive = np.arange(n)
    for b in range(k // 8):
        if not len(alive):
            break
        sq = [(proj[8 * b + i, alive] - q[8 * b + i]) ** 2 for i in range(8)]
        before = lb[alive]
        after = before + (((sq[0] + sq[1]) + (sq[2] + sq[3])) + ((sq[4] + sq[5]) + (sq[6] + sq[7])))
        lb[alive] = after
        dropped = after > lim[8 * b + 7]
        at = np.full(len(alive), 8 * b + 8, np.int32)
        run = before.copy()
        pending = dropped.copy()
        for i in range(8):
            run = run + sq[i]
            first = pending & (run > lim[8 * b + i])
            at[first] = 8 * b + i + 1
            pending &= ~first
        used[alive[dropped]] = at[dropped]
        alive = alive[~dropped]
    dist = lb.copy()
    dist[alive] = ssd_numpy(feats, bases[alive], offsets, query)
    return used, dist


class QuiltDevice:
    """The exemplar's appearance vectors (and summed-area tables) on the OpenCL device, with the quilting kernels.

    ``bases`` are the candidates' flat texel indices (all block positions in the exemplar by default).
    """

    def __init__(self, feats: np.ndarray, bases: np.ndarray | None = None, backend=None):
        from btforge.backend import get_backend
        self.backend = backend or get_backend()
        self.height, self.width, self.dims = feats.shape
        self.feats_dev = self.buffer(np.ascontiguousarray(feats.reshape(-1, self.dims), np.float32))
        self.bases_dev = self.buffer(bases.astype(np.int32)) if bases is not None else None
        self._sat_dev = None
        self._kernels: dict[str, object] = {}

    @staticmethod
    def padded(n: int) -> int:
        return max(LAUNCH_MULTIPLE, -(-n // LAUNCH_MULTIPLE) * LAUNCH_MULTIPLE)

    def buffer(self, array: np.ndarray):
        return self.backend.to_device(np.ascontiguousarray(array))

    def _kernel(self, name: str):
        kernel = self._kernels.get(name)
        if kernel is None:
            kernel = self._kernels[name] = self.backend.kernel(KERNELS, name, (f"-DD={self.dims}",))
        return kernel

    def ssd(self, bases, offsets, query: np.ndarray, n_cand: int | None = None) -> np.ndarray:
        """``quilt_ssd``; ``bases`` / ``offsets`` are arrays or device buffers (then ``n_cand`` is required)."""
        n = len(bases) if n_cand is None else n_cand
        if n == 0:
            return np.zeros(0, np.float32)
        bases_dev = bases if n_cand is not None else self.buffer(np.asarray(bases, np.int32))
        offsets_dev = self.buffer(offsets.astype(np.int32)) if isinstance(offsets, np.ndarray) else offsets
        out = self.backend.empty(4 * n)
        self.backend.run(self._kernel("quilt_ssd"), (self.padded(n),), self.feats_dev, bases_dev, offsets_dev,
                         self.buffer(np.asarray(query, np.float32)), np.int32(n), np.int32(query.size // self.dims),
                         out)
        return self.backend.from_device(out, (n,), np.float32)

    def set_tables(self, sat: np.ndarray) -> None:
        """Upload the summed-area tables ``[D, H + 1, W + 1]`` that :meth:`project` reads."""
        self._sat_dev = self.buffer(sat.astype(np.float64))
        self._plane = sat.shape[1] * sat.shape[2]
        self._sat_width = sat.shape[2]

    def project(self, rows: np.ndarray, cols: np.ndarray, funcs: HaarSet, read: bool = True):
        """``quilt_project`` for the candidates at (rows, cols): the device buffer (chunk-major
        ``[K / 8, n, 8]``, zero functions padding K to a multiple of 8) that :meth:`reject` reads, and (if ``read``)
        the projections on the host as ``[K, n]`` float32."""
        n, k = len(rows), len(funcs)
        funcs = funcs.padded(8)
        kp = len(funcs)
        sw = self._sat_width
        y0, x0, y1, x1 = (funcs.boxes[..., i].astype(np.int64) for i in range(4))
        corners = np.stack([y1 * sw + x1, y0 * sw + x1, y1 * sw + x0, y0 * sw + x0], axis=-1).astype(np.int32)
        out = self.backend.empty(4 * n * kp)
        self.backend.run(self._kernel("quilt_project"), (self.padded(n), -(-kp // PROJECT_RUN)), self._sat_dev,
                         np.int32(self._plane), self.buffer((rows * sw + cols).astype(np.int32)), self.buffer(corners),
                         self.buffer(funcs.coefs), self.buffer(funcs.dims.astype(np.int32)), np.int32(n), np.int32(kp),
                         out)
        if not read:
            self.backend.queue.finish()
            return out, None
        chunked = self.backend.from_device(out, (kp // 8, n, 8), np.float32)
        return out, np.ascontiguousarray(chunked.transpose(0, 2, 1).reshape(kp, n)[:k])

    def chunked_buffer(self, proj: np.ndarray):
        """The device layout ``[K / 8, n, 8]`` of host projections ``[K, n]`` (K a multiple of 8)."""
        k, n = proj.shape
        return self.buffer(proj.astype(np.float32).reshape(k // 8, 8, n).transpose(0, 2, 1))

    def reject(self, proj_dev, n: int, qproj: np.ndarray, limit: np.ndarray, offsets, query: np.ndarray):
        """``quilt_reject`` over all ``n`` candidates (needs ``bases``): ``(used, dist)``."""
        k = len(qproj)
        out = self.backend.empty(8 * n)
        offsets_dev = self.buffer(offsets.astype(np.int32)) if isinstance(offsets, np.ndarray) else offsets
        self.backend.run(self._kernel("quilt_reject"), (self.padded(n),), proj_dev,
                         self.buffer(np.concatenate([qproj, limit]).astype(np.float32)), np.int32(n), np.int32(k),
                         self.feats_dev, self.bases_dev, offsets_dev, self.buffer(np.asarray(query, np.float32)),
                         np.int32(query.size // self.dims), out)
        packed = self.backend.from_device(out, (2, n), np.int32)
        return packed[0], packed[1].view(np.float32)


# One-off helpers running a single kernel on the default device (tests; the synthesis keeps its buffers).

def ssd_opencl(feats, bases, offsets, query) -> np.ndarray:
    return QuiltDevice(feats).ssd(np.asarray(bases, np.int32), np.asarray(offsets, np.int32), query)


def project_opencl(feats, sat, rows, cols, funcs: HaarSet) -> np.ndarray:
    dev = QuiltDevice(feats)
    dev.set_tables(sat)
    return dev.project(np.asarray(rows), np.asarray(cols), funcs)[1]


def reject_opencl(proj, qproj, limit, feats, bases, offsets, query) -> tuple[np.ndarray, np.ndarray]:
    dev = QuiltDevice(feats, np.asarray(bases))
    return dev.reject(dev.chunked_buffer(proj), proj.shape[1], qproj, limit,
                      np.asarray(offsets), query)


# ----------------------------------------------------------------------------------------------- search


def _round_up32(values: np.ndarray) -> np.ndarray:
    """float32 values no smaller than ``values`` (so a float32 comparison never tightens a bound)."""
    out = np.asarray(values, np.float64).astype(np.float32)
    return np.where(out.astype(np.float64) < values, np.nextafter(out, np.float32(np.inf)), out)


@dataclasses.dataclass
class OverlapShape:
    """The texels of a block compared with the synthesized neighbours: top/bottom rows, left/right columns."""

    key: tuple[int, int, int, int]   # (top, bottom, left, right) overlap widths
    dy: np.ndarray                   # overlap texels' rows and columns inside the block, unfolding order
    dx: np.ndarray
    offsets: np.ndarray              # the same as flat exemplar offsets (int32)
    offsets_dev: object = None
    funcs: HaarSet | None = None     # projection basis, ordered by decreasing energy over the candidates
    proj: np.ndarray | None = None   # [K, n_cand] float32 projections of every candidate
    proj_dev: object = None          # the same on the device, chunk-major [K / 8, n_cand, 8]
    head: np.ndarray | None = None   # [k0, n_cand] the first SEED_PROJECTIONS projections, on the host
    seed_norm: np.ndarray | None = None  # [n_cand] their squared norm
    err_proj: np.ndarray | None = None   # [K] bound on each stored projection's rounding error
    corner_index: np.ndarray | None = None    # [K, 16] flat indices into a query's summed-area table
    corner_weights: np.ndarray | None = None  # [K, 16] their weights (box coefficient x corner sign)

    @property
    def n_pix(self) -> int:
        return len(self.offsets)


def shape_texels(block: int, key: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of an overlap's texels inside the block, row-major (the shared band window)."""
    texels = band_window(block, *key)
    return texels[:, 0].copy(), texels[:, 1].copy()


class QuiltSearch:
    """Finds the eligible exemplar blocks for a query overlap and picks one (brute force or exact rejection).

    Candidates are all block positions lying wholly inside the exemplar, indexed row-major.
    """

    def __init__(self, feats: np.ndarray, block: int, *, method: str = "rejection", tolerance: float = 0.1,
                 engine: str = "opencl", projections: int | None = None):
        self.feats = np.ascontiguousarray(feats, np.float32)
        self.height, self.width, self.dims = self.feats.shape
        self.block, self.method, self.tolerance, self.engine = block, method, float(tolerance), engine
        self.projections = projections or N_PROJECTIONS
        self.rows, self.cols = self.height - block + 1, self.width - block + 1
        self.n_cand = self.rows * self.cols
        self.cand_rows, self.cand_cols = np.divmod(np.arange(self.n_cand), self.cols)
        self.bases = (self.cand_rows * self.width + self.cand_cols).astype(np.int32)
        self.device = QuiltDevice(self.feats, self.bases) if engine == "opencl" else None
        self.shapes: dict[tuple[int, int, int, int], OverlapShape] = {}
        self.rejecting = method == "rejection" and self.n_cand > 2 * SEED_CANDIDATES
        if self.rejecting:
            self.flat64 = self.feats.reshape(-1, self.dims).astype(np.float64)
            self.mean = self.flat64.mean(axis=0)
            centered = self.feats.astype(np.float64) - self.mean
            self.sat = summed_area(centered)
            self.abs_sum = np.abs(centered).sum(axis=(0, 1))
            self.max_dev = np.abs(centered).max(axis=(0, 1))
            if self.device:
                self.device.set_tables(self.sat)
        # statistics
        self.queries = 0
        self.full_distances = 0       # candidates whose full distance was computed on the device
        self.host_distances = 0       # full distances computed on the host to set the threshold
        self.rejected_sum = np.zeros(0)  # per projection: sum over queries of the fraction rejected so far
        self.projected = 0            # queries that went through the rejection
        self.precompute_s = 0.0
        self.search_s = 0.0

    # -- shapes ---------------------------------------------------------------------------------------------
    def shape(self, key: tuple[int, int, int, int], projections: int | None = None) -> OverlapShape:
        """The overlap shape ``key``, prepared on first use with at most ``projections`` basis functions."""
        shape = self.shapes.get(key)
        if shape is None:
            start = time.perf_counter()
            dy, dx = shape_texels(self.block, key)
            shape = OverlapShape(key, dy, dx, (dy * self.width + dx).astype(np.int32))
            if self.device:
                shape.offsets_dev = self.device.buffer(shape.offsets)
            if self.rejecting:
                with np.errstate(over="ignore", invalid="ignore"):  # huge values: inf only loosens bounds
                    self._precompute(shape, projections or self.projections)
            self.shapes[key] = shape
            self.precompute_s += time.perf_counter() - start
        return shape

    def budget(self, uses: dict) -> dict:
        """Projections per overlap shape, given how many blocks search with each: the stored projections share
        ``PROJECTION_BUDGET``, in proportion to use, and a shape that serves a few blocks gets few (precomputing a
        thousand projections to search two blocks would cost more than it saves)."""
        total = PROJECTION_BUDGET // (4 * self.n_cand)
        count = sum(uses.values()) or 1
        return {key: int(np.clip(min(16 * n, total * n // count), MIN_PROJECTIONS, self.projections))
                for key, n in uses.items()}

    def _precompute(self, shape: OverlapShape, k: int) -> None:
        """Choose the shape's projection basis and project every candidate onto it.

        The Haar functions of the overlap's rectangles (per feature dimension) are ranked by their variance over a
        sample of candidates - their expected contribution to a candidate's distance - and the ``k`` most energetic
        are kept, in that order (padded with zero functions to a multiple of 8).  The ranked pool is the ``4 k``
        coarsest functions: fine ones carry little energy.
        """
        funcs = haar_functions(self.block, shape.key, self.dims, limit=max(4 * k, 512))
        if self.n_cand > BASIS_SAMPLE:
            sample = np.sort(np.random.default_rng(BASIS_SEED).choice(self.n_cand, BASIS_SAMPLE, replace=False))
        else:
            sample = np.arange(self.n_cand)
        rows, cols = self.cand_rows[sample], self.cand_cols[sample]
        if self.device:
            energy = self.device.project(rows, cols, funcs)[1].astype(np.float64).var(axis=1)
        else:
            energy = project_numpy(self.sat, rows, cols, funcs).astype(np.float64).var(axis=1)
        funcs = funcs.take(np.argsort(-energy, kind="stable")[:k]).padded(8)
        shape.funcs = funcs
        k0 = min(len(funcs), SEED_PROJECTIONS)
        if self.device:
            shape.proj_dev = self.device.project(self.cand_rows, self.cand_cols, funcs, read=False)[0]
            head = self.device.project(self.cand_rows, self.cand_cols, funcs.take(np.arange(k0)))[1]
        else:
            shape.proj = project_numpy(self.sat, self.cand_rows, self.cand_cols, funcs)
            head = shape.proj[:k0]
        shape.head = head
        shape.seed_norm = np.einsum("ij,ij->j", head, head)
        # Rounding of a projection: each summed-area entry is a sum of at most H + W partial sums of values whose
        # magnitudes total abs_sum, a box combines four, a projection at most four boxes; then float32 storage of a
        # value at most sum |coef| x box area x the largest deviation from the mean.
        table = (4 * (self.height + self.width + 2) + 40) * _U64 * self.abs_sum[funcs.dims] * funcs.coef_abs
        y0, x0, y1, x1 = (funcs.boxes[..., i] for i in range(4))
        largest = (np.abs(funcs.coefs) * (y1 - y0) * (x1 - x0)).sum(axis=1) * self.max_dev[funcs.dims]
        shape.err_proj = table + _U32 * (1 + 2 * _U32) * (largest * (1 + 1e-6))
        # The query's projections as one gather from its summed-area table [B + 1, B + 1, D] and a weighted sum.
        side, d = self.block + 1, funcs.dims[:, None]
        corner = [(y1, x1, 1.0), (y0, x1, -1.0), (y1, x0, -1.0), (y0, x0, 1.0)]
        shape.corner_index = np.concatenate([(yy * side + xx) * self.dims + d for yy, xx, _ in corner], axis=1)
        shape.corner_weights = np.concatenate([sign * funcs.coefs for _, _, sign in corner], axis=1)

    # -- distances ------------------------------------------------------------------------------------------
    def distances(self, shape: OverlapShape, query: np.ndarray) -> np.ndarray:
        """Every candidate's full overlap distance (float32), the brute-force way."""
        self.full_distances += self.n_cand
        if self.device is None:
            return ssd_numpy(self.feats, self.bases, shape.offsets, query)
        return self.device.ssd(self.device.bases_dev, shape.offsets_dev, query, n_cand=self.n_cand)

    def _host_distances(self, shape: OverlapShape, cands: np.ndarray, q64: np.ndarray) -> np.ndarray:
        """Full overlap distances of a few candidates, in float64 on the host (to set the rejection threshold)."""
        self.host_distances += len(cands)
        diff = self.flat64[self.bases[cands][:, None] + shape.offsets[None, :]] - q64
        return np.einsum("cij,cij->c", diff, diff)

    def _query_projections(self, shape: OverlapShape, block_feats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The query's projections (float64, from its own summed-area table) and a bound on their rounding."""
        centered = block_feats.astype(np.float64) - self.mean
        sat = np.zeros((self.block + 1, self.block + 1, self.dims))
        sat[1:, 1:] = centered.cumsum(axis=0).cumsum(axis=1)
        qp = np.einsum("jk,jk->j", shape.corner_weights, sat.reshape(-1)[shape.corner_index])
        abs_sum = np.abs(centered).sum(axis=(0, 1))
        # Each table entry sums at most 2B + 2 partial sums of values totalling abs_sum; a projection combines 16.
        err = (4 * (2 * self.block + 2) + 80) * _U64 * abs_sum[shape.funcs.dims] * shape.funcs.coef_abs
        return qp, err

    def _reject(self, shape: OverlapShape, block_feats: np.ndarray, query: np.ndarray,
                hints: tuple[int, ...] = (), allowed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The candidates the projections cannot rule out (sorted) with their full distances; with ``allowed``
        the threshold comes from allowed candidates, so every allowed one within tolerance of the best allowed one
        survives.

        Exactness.  Let d be a candidate's distance as the device computes it (float32 over m = n_pix * D terms,
        relative error below (m + 2) u32) and d* its exact value; eligible means d <= (1 + tol) min d.  The
        threshold comes from d64, the float64 distance of a candidate c (the best of a few nominees), and
        min d <= d(c) <= d64 (1 + (m + 2) u32) + underflow, so with thr = ((1 + tol) d64 + m 2^-100)(1 + 4 (m + 2) u32)
        every eligible candidate has LB*_k <= d* <= thr for the exact lower bound LB*_k of its first k projections
        (the basis is orthonormal).  The bound the kernel computes differs from LB*_k through the rounding e_j of
        the projections (candidate tables and float32 storage, query table and float32) - so that
        sqrt(LB_k) <= sqrt(LB*_k) + E_k with E_k = sqrt(sum_{j<k} (2 e_j)^2) - and through float32 accumulation
        (relative 2 (k + 4) u32).  Dropping a candidate only when its bound exceeds
        (sqrt(thr) + E_k)^2 (1 + 2 (K + 4) u32), rounded up to float32, therefore never drops an eligible one.
        """
        n = self.n_cand
        qp, err_query = self._query_projections(shape, block_feats)
        k = len(qp)
        q64 = query.astype(np.float64)
        m = query.size
        tol = 1 + self.tolerance
        qp32 = qp.astype(np.float32)  # the kernels work in float32: rounding the query is one more error
        err_query = err_query + _U32 * np.abs(qp)
        slack = np.sqrt(np.cumsum((2 * (shape.err_proj + err_query)) ** 2))
        thr = (tol * self._threshold_seed(shape, qp32, q64, hints, allowed) + m * 2.0 ** -100) * (1 + 4 * (m + 2) * _U32)
        if thr > 0.25 * _FLOAT32_MAX:  # device distances may overflow to inf: no safe bound, compute them all
            return np.arange(n), self.distances(shape, query)
        limit = _round_up32((math.sqrt(thr) + slack) ** 2 * (1 + 2 * (k + 4) * _U32))
        if self.device:
            used, dist = self.device.reject(shape.proj_dev, n, qp32, limit, shape.offsets_dev, query)
        else:
            used, dist = reject_numpy(shape.proj, qp32, limit, self.feats, self.bases, shape.offsets, query)
        rejected = np.cumsum(np.bincount(used, minlength=k + 2)[1:k + 1]) / n
        if len(self.rejected_sum) < k:  # earlier queries, with fewer projections, stopped rejecting at their end
            last = self.rejected_sum[-1] if len(self.rejected_sum) else 0.0
            self.rejected_sum = np.concatenate([self.rejected_sum, np.full(k - len(self.rejected_sum), last)])
        self.rejected_sum[:k] += rejected
        self.rejected_sum[k:] += rejected[-1]
        self.projected += 1
        idx = np.flatnonzero(used > k)
        self.full_distances += len(idx)
        return idx, dist[idx]

    def _threshold_seed(self, shape: OverlapShape, qp32: np.ndarray, q64: np.ndarray, hints,
                        allowed: np.ndarray | None = None) -> float:
        """The smallest float64 full distance among a few promising (``allowed``) candidates: those with the
        lowest bound from the first projections, and the ``hints`` (blocks continuing the neighbours' exemplar
        positions)."""
        k0 = min(len(qp32), SEED_PROJECTIONS)
        head = qp32[:k0]
        # + |head|^2, the same for all: ranking only.  einsum, not a BLAS call: a threaded BLAS would fight the
        # OpenCL runtime's threads for the cores.
        lb = shape.seed_norm - 2 * np.einsum("j,jn->n", head, shape.head)
        if allowed is not None:
            lb = np.where(allowed, lb, np.inf)
        nominees = set(np.argpartition(lb, SEED_CANDIDATES)[:SEED_CANDIDATES].tolist())
        nominees.update(h for h in hints if 0 <= h < self.n_cand)
        if allowed is not None:
            nominees = {n for n in nominees if allowed[n]}
        return float(self._host_distances(shape, np.fromiter(nominees, np.int64), q64).min())

    def pick(self, shape: OverlapShape, block_feats: np.ndarray, rng: np.random.Generator,
             hints: tuple[int, ...] = (), usage: np.ndarray | None = None,
             allowed: np.ndarray | None = None) -> int:
        """One candidate drawn uniformly from those within (1 + tolerance) x the best overlap distance.

        ``block_feats`` is the synthesized ``[B, B, D]`` block region; only its overlap texels are compared.
        ``hints`` may name candidates likely to match well (they only speed up the rejection).  With ``usage``
        (per candidate: how much of its exemplar area the output already copies), the draw is among the
        eligible candidates used least.  With ``allowed`` (a mask over the candidates, at least one true) only
        allowed candidates are eligible, within tolerance of the best allowed one.
        """
        start = time.perf_counter()
        self.queries += 1
        query = np.ascontiguousarray(block_feats[shape.dy, shape.dx])
        if self.rejecting:
            with np.errstate(over="ignore", invalid="ignore"):  # huge values: float32 infinities only loosen bounds
                idx, d = self._reject(shape, block_feats, query, hints, allowed)
        else:
            idx, d = np.arange(self.n_cand), self.distances(shape, query)
        if allowed is not None:
            keep = allowed[idx]
            idx, d = idx[keep], d[keep]
        d = d.astype(np.float64)
        eligible = idx[d <= (1 + self.tolerance) * d.min()]  # ascending candidate order: ties resolve by the seed
        if usage is not None:
            use = usage[eligible]
            eligible = eligible[use <= use.min() + 1e-9]
        self.search_s += time.perf_counter() - start
        return int(eligible[rng.integers(len(eligible))])

    def candidate(self, row: int, col: int) -> int:
        """The index of the candidate block at exemplar (row, col), or -1 if it does not fit."""
        return row * self.cols + col if 0 <= row < self.rows and 0 <= col < self.cols else -1

    def rejected_fractions(self) -> list[float]:
        """Mean fraction of all candidates rejected after each projection (cumulative), without the flat tail."""
        if not self.projected:
            return []
        values = [round(float(v) / self.projected, 4) for v in self.rejected_sum]
        while len(values) > 1 and values[-1] == values[-2]:
            values.pop()
        return values
