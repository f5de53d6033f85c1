"""Reference warping and template-guided block copy (Liu, Yu & Shum 2001, sec. 6.1-6.3).

Warping.  The stack's images are in the texture frame (rectified, as measured BTFs are stored), so the paper's
back-projection onto the surface plane and re-projection into the target view are the identity and the warp is
the rotation about the normal by eq. 7's angle (and the mirror image when eq. 7 chose it), one bilinear
resampling about the image centres.  Where the rotated image has no data the validity mask is False.

Block copy.  The template is histogram-matched to the grey reference; its pixels are visited in order of Harris
corner response; at each uncovered pixel, every block size whose square would not overlap an earlier block is
matched against the reference (normalised SSD, i.e. SSD per compared pixel) and the best block is copied in
colour.  Remaining holes are filled with the smallest blocks, which may overlap: each hole pixel is matched
with the ``hole_size`` block centred on it (overlapping its neighbours) and takes that block's centre, so the
fill is one batched search and every pixel ends up covered.  Blocks are compared on a sub-sampled grid of at most ``BLOCK_SAMPLES`` x ``BLOCK_SAMPLES`` pixels,
and the search (:func:`.search.knn`) runs on their leading principal components, the ``RERANK`` nearest then
re-ranked by their full sub-sampled SSD.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from btforge.lazy import lazy_module

from .search import knn

ndimage = lazy_module("scipy.ndimage")

BLOCK_SAMPLES = 5      # a block is compared on at most 5 x 5 evenly spaced pixels
SEARCH_DIMS = 8        # principal components the k-d tree searches
RERANK = 8             # candidates re-ranked by the full block distance
MAX_POSITIONS = 30000  # reference block positions per size (a coarser position grid beyond)
BATCH = 2048           # Harris-ordered pixels of the first batch matched at once (one search per size)
HARRIS_K = 0.04
WARP_ORDER = 0         # nearest-neighbour resampling: every output pixel is a real reference pixel


def warp(image: np.ndarray, rotation: float, mirrored: bool, out_shape: tuple[int, int]):
    """``image [h, w, C]`` rotated by ``rotation`` (radians, counter-clockwise in the texture frame) and, when
    ``mirrored``, reflected top to bottom, resampled bilinearly onto ``out_shape`` about the centres.

    Returns ``(warped [H, W, C] float32, valid [H, W] bool)``.
    """
    h, w = image.shape[:2]
    H, W = out_shape
    rows, cols = np.meshgrid(np.arange(H, dtype=np.float64), np.arange(W, dtype=np.float64), indexing="ij")
    x, y = cols - (W - 1) / 2, (H - 1) / 2 - rows        # texture frame about the output centre
    if mirrored:
        y = -y
    c, s = math.cos(rotation), math.sin(rotation)
    xs, ys = c * x + s * y, -s * x + c * y                 # rotate back by -rotation into the source
    src_cols, src_rows = xs + (w - 1) / 2, (h - 1) / 2 - ys
    eps = 1e-6
    valid = (src_rows >= -eps) & (src_rows <= h - 1 + eps) & (src_cols >= -eps) & (src_cols <= w - 1 + eps)
    coords = np.stack([np.clip(src_rows, 0, h - 1), np.clip(src_cols, 0, w - 1)])
    out = np.stack([ndimage.map_coordinates(image[..., ch].astype(np.float64), coords, order=WARP_ORDER, mode="nearest")
                    for ch in range(image.shape[2])], axis=-1)
    return out.astype(np.float32), valid


def histogram_match(source: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``source`` with its values replaced by the ``reference`` values of the same rank (quantile mapping)."""
    order = np.argsort(source, axis=None, kind="stable")
    ref = np.sort(reference, axis=None)
    quantiles = (np.arange(source.size) + 0.5) / source.size
    matched = np.empty(source.size, np.float64)
    matched[order] = np.interp(quantiles, (np.arange(ref.size) + 0.5) / ref.size, ref)
    return matched.reshape(source.shape).astype(np.float32)


def harris_response(image: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    gy = ndimage.sobel(image.astype(np.float64), axis=0)
    gx = ndimage.sobel(image.astype(np.float64), axis=1)
    sxx, syy, sxy = (ndimage.gaussian_filter(a, sigma) for a in (gx * gx, gy * gy, gx * gy))
    return sxx * syy - sxy * sxy - HARRIS_K * (sxx + syy) ** 2


def _offsets(size: int) -> np.ndarray:
    r = size // 2
    n = min(size, BLOCK_SAMPLES)
    return np.unique(np.round(np.linspace(-r, r, n)).astype(np.int64))


@dataclasses.dataclass
class _Index:
    """The reference blocks of one size: centres, sub-sampled grey vectors, their PCA projection."""

    size: int
    centres: np.ndarray    # [N, 2] row, col
    vectors: np.ndarray    # [N, D]
    mean: np.ndarray
    axes: np.ndarray       # [D, d]
    projected: np.ndarray  # [N, d]


def _block_index(grey: np.ndarray, valid: np.ndarray, size: int, rng) -> _Index | None:
    h, w = grey.shape
    r = size // 2
    if h < size or w < size:
        return None
    inside = ndimage.minimum_filter(valid.astype(np.uint8), size=size, mode="constant", cval=0).astype(bool)
    inside[:r], inside[h - r:], inside[:, :r], inside[:, w - r:] = False, False, False, False
    centres = np.argwhere(inside)
    if len(centres) == 0:
        return None
    if len(centres) > MAX_POSITIONS:
        centres = centres[np.sort(rng.choice(len(centres), MAX_POSITIONS, replace=False))]
    off = _offsets(size)
    dr, dc = np.meshgrid(off, off, indexing="ij")
    vectors = grey[centres[:, :1] + dr.ravel()[None], centres[:, 1:] + dc.ravel()[None]].astype(np.float32)
    mean = vectors.mean(0)
    centred = (vectors - mean).astype(np.float64)
    _, axes = np.linalg.eigh(centred.T @ centred)
    axes = axes[:, ::-1][:, :min(SEARCH_DIMS, vectors.shape[1])].astype(np.float32)
    return _Index(size, centres, vectors, mean, axes, (vectors - mean) @ axes)


def _template_vectors(padded: np.ndarray, pad: int, pixels: np.ndarray, size: int) -> np.ndarray:
    off = _offsets(size)
    dr, dc = np.meshgrid(off, off, indexing="ij")
    return padded[pixels[:, :1] + pad + dr.ravel()[None], pixels[:, 1:] + pad + dc.ravel()[None]].astype(np.float32)


def _match(index: _Index, queries: np.ndarray, engine: str) -> tuple[np.ndarray, np.ndarray]:
    """Best reference centre ``[M, 2]`` and normalised SSD ``[M]`` for template block vectors ``[M, D]``."""
    idx, _ = knn(index.projected, (queries - index.mean) @ index.axes, RERANK, engine=engine)
    full = ((index.vectors[idx] - queries[:, None]) ** 2).sum(-1)
    best = full.argmin(1)
    chosen = idx[np.arange(len(idx)), best]
    return index.centres[chosen], full[np.arange(len(idx)), best] / queries.shape[1]


@dataclasses.dataclass
class BlockCopy:
    image: np.ndarray      # [H, W, C] the synthesized image
    source: np.ndarray     # [H, W, 2] int32: reference pixel each output pixel was copied from
    blocks: int
    hole_pixels: int       # pixels filled by hole filling
    mean_ssd: float


def block_copy(template: np.ndarray, reference: np.ndarray, valid: np.ndarray, block_sizes=(3, 5, 9),
               hole_size: int = 3, seed: int = 0, engine: str = "fast") -> BlockCopy:
    """Synthesize an image shaped like ``template [H, W]`` from blocks of ``reference [h, w, C]`` (see module)."""
    rng = np.random.default_rng(seed)
    H, W = template.shape
    grey = reference.mean(axis=2)
    guide = histogram_match(template, grey[valid] if valid.any() else grey)
    sizes = sorted({int(s) | 1 for s in block_sizes}, reverse=True)
    indexes = [i for i in (_block_index(grey, valid, s, rng) for s in sizes) if i is not None]
    hole_index = _block_index(grey, valid, hole_size | 1, rng) or (indexes[-1] if indexes else None)
    if hole_index is None:
        from btforge.errors import BtforgeInputError
        raise BtforgeInputError("liu.synthesize 'references'", f"a warped reference has no valid "
                                f"{hole_size} x {hole_size} block", "give larger reference images")
    pad = max([i.size for i in indexes] + [hole_index.size]) // 2
    padded = np.pad(guide, pad, mode="reflect")
    response = harris_response(guide) + rng.uniform(0, 1e-12, (H, W))   # random tie-break
    order = np.argsort(-response, axis=None, kind="stable")
    pixels_in_order = np.column_stack(np.unravel_index(order, (H, W)))

    out = np.zeros((H, W, reference.shape[2]), np.float32)
    source = np.zeros((H, W, 2), np.int32)
    covered = np.zeros((H, W), bool)
    blocks, ssd_sum = 0, 0.0
    start, step = 0, BATCH
    while start < len(pixels_in_order):
        # batches grow geometrically: late pixels are mostly covered already, and every batch rebuilds the trees
        batch = pixels_in_order[start:start + step]
        start, step = start + step, step * 2
        # a size is matched only at pixels where its block still fits; pixels where none fits wait for hole filling
        fits = [~ndimage.maximum_filter(covered, size=ix.size, mode="constant", cval=False)[batch[:, 0], batch[:, 1]]
                for ix in indexes]
        keep = np.logical_or.reduce(fits)
        batch, fits = batch[keep], [f[keep] for f in fits]
        if len(batch) == 0:
            continue
        matches = []
        for ix, fit in zip(indexes, fits):
            centres = np.zeros((len(batch), 2), np.int64)
            cost = np.full(len(batch), np.inf)
            if fit.any():
                centres[fit], cost[fit] = _match(ix, _template_vectors(padded, pad, batch[fit], ix.size), engine)
            matches.append((centres, cost))
        for j, (r, c) in enumerate(batch):
            if covered[r, c]:
                continue
            best = None
            for ix, (centres, cost) in zip(indexes, matches):
                if not np.isfinite(cost[j]):
                    continue
                k = ix.size // 2
                r0, r1, c0, c1 = max(r - k, 0), min(r + k + 1, H), max(c - k, 0), min(c + k + 1, W)
                if covered[r0:r1, c0:c1].any():
                    continue
                if best is None or cost[j] < best[0]:
                    best = (cost[j], centres[j], (r0, r1, c0, c1))
            if best is None:
                continue
            cost, (sr, sc), (r0, r1, c0, c1) = best
            _paste(out, source, covered, reference, r, c, sr, sc, (r0, r1, c0, c1))
            blocks += 1
            ssd_sum += float(cost)
    hole_pixels = int((~covered).sum())
    if hole_pixels:
        pixels = np.argwhere(~covered)
        centres, _ = _match(hole_index, _template_vectors(padded, pad, pixels, hole_index.size), engine)
        out[pixels[:, 0], pixels[:, 1]] = reference[centres[:, 0], centres[:, 1]]
        source[pixels[:, 0], pixels[:, 1]] = centres
        covered[pixels[:, 0], pixels[:, 1]] = True
    return BlockCopy(out, source, blocks, hole_pixels, ssd_sum / max(blocks, 1))


def _paste(out, source, covered, reference, r, c, sr, sc, box):
    r0, r1, c0, c1 = box
    rows = slice(sr + r0 - r, sr + r1 - r)
    cols = slice(sc + c0 - c, sc + c1 - c)
    where = (slice(r0, r1), slice(c0, c1))
    out[where] = reference[rows, cols]
    source[where + (0,)] = np.arange(rows.start, rows.stop)[:, None]
    source[where + (1,)] = np.arange(cols.start, cols.stop)[None, :]
    covered[where] = True
