"""Reference warping and template-guided block copy (Liu, Yu & Shum 2001, sec. 6.1-6.3).

Warping.  The stack's images are in the texture frame (rectified, as measured BTFs are stored), so the paper's
back-projection onto the surface plane and re-projection into the target view are the identity and the warp is
the rotation about the normal by eq. 7's angle (and the mirror image when eq. 7 chose it), one bilinear
resampling about the image centres.  Where the rotated image has no data the validity mask is False.

Block copy.  The template is histogram-matched to the grey reference; its pixels are visited in order of Harris
corner response; at each uncovered pixel, every block size whose square would not overlap an earlier block is
matched against the reference and the best block is copied in colour.  Liu et al. match on the grey template
alone (normalised SSD, i.e. SSD per compared pixel), which cannot see colour: neighbouring blocks of the same
grey level but different hue make colour islands and visible block edges.  So each block is chosen among
``CANDIDATES`` nearest blocks by the template and the continuations of the blocks already copied around it, by
the template SSD plus ``colour`` times the colour disagreement between the candidate's continuation just outside
the block and the pixels already copied there (:func:`_choose`; ``colour`` 0: the template alone).  The
template keeps guiding the geometry (shadows, occlusion); the colour term only decides among blocks that fit
it.  That greedy pass runs in rounds (:func:`place_blocks`), each round's pixels searched in one batch per
size.  Remaining holes are filled from their rims inwards with the smallest blocks, which may overlap: each hole
pixel is matched with the ``hole_size`` block centred on it, among candidates chosen the same way, and takes
that block's centre (:func:`_fill_holes`), so every pixel ends up covered.  Blocks are compared on a sub-sampled
grid of at most ``BLOCK_SAMPLES`` x ``BLOCK_SAMPLES`` pixels; the search (:class:`.search.BlockIndex`) runs on
all their values when there are at most ``FULL_DIMS``, else on their leading principal components.
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import math

import numpy as np

from btforge.lazy import lazy_module

from .search import BlockIndex

ndimage = lazy_module("scipy.ndimage")

BLOCK_SAMPLES = 5      # a block is compared on at most 5 x 5 evenly spaced pixels
SEARCH_DIMS = 8        # principal components the k-d tree searches for blocks of more than FULL_DIMS values
FULL_DIMS = 9          # blocks of at most this many compared values are searched without projection
PCA_ROWS = 4096        # blocks the principal axes are estimated from
MAX_POSITIONS = 30000  # reference block positions per size (a coarser position grid beyond)
LARGE_POSITIONS = 15000  # ... for blocks larger than 3 x 3: neighbouring positions overlap by most of a block,
# and on the 256^2 bench image halving them kept the mean block SSD (0.000424 against 0.000426) at 16 % less time
HARRIS_K = 0.04
WARP_ORDER = 0         # nearest-neighbour resampling: every output pixel is a real reference pixel
GUIDE_SPREAD = 0.5     # feathering follows the template within this share of its spread (feather_seams)
FEATHER = 2            # texels on each side of a block boundary blended with the other block's continuation
RELAX = 2              # sweeps of seam relaxation over the block copy's source map (relax_block_seams)
CANDIDATES = 16        # template matches per block among which the colour agreement with its surroundings chooses
RING = 2               # rings of pixels around a block whose colours its continuation is compared with
COLOUR = 1.0           # weight of that colour agreement against the template SSD (0: the template alone)
HOLE_CHUNK = 4096      # hole pixels costed at once: bounds the candidates' working memory (about 20 MB per 1000)


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


@functools.lru_cache(maxsize=64)
def _offsets(size: int) -> np.ndarray:
    r = size // 2
    n = min(size, BLOCK_SAMPLES)
    return _frozen(np.unique(np.round(np.linspace(-r, r, n)).astype(np.int64)))


def _frozen(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)   # memoised arrays are shared
    return array


@dataclasses.dataclass
class _Index:
    """The reference blocks of one size: centres and the search over their sub-sampled grey vectors' PCA
    projection."""

    size: int
    centres: np.ndarray    # [N, 2] row, col
    mean: np.ndarray
    axes: np.ndarray       # [D, d]
    search: BlockIndex     # over the projected vectors [N, d]
    inside: np.ndarray     # [h, w] bool: centres whose whole block lies on valid reference pixels


def _block_index(grey: np.ndarray, valid: np.ndarray, size: int, rng, engine: str) -> _Index | None:
    h, w = grey.shape
    r = size // 2
    if h < size or w < size:
        return None
    inside = ndimage.minimum_filter(valid.astype(np.uint8), size=size, mode="constant", cval=0).astype(bool)
    inside[:r], inside[h - r:], inside[:, :r], inside[:, w - r:] = False, False, False, False
    centres = np.argwhere(inside)
    if len(centres) == 0:
        return None
    cap = MAX_POSITIONS if size <= 3 else LARGE_POSITIONS
    if len(centres) > cap:
        centres = centres[np.sort(rng.choice(len(centres), cap, replace=False))]
    vectors = _gather(np.ascontiguousarray(grey, np.float32), 0, centres, size)
    mean = vectors.mean(0)
    if vectors.shape[1] <= FULL_DIMS:     # small blocks: the tree searches the blocks themselves, exactly
        axes = np.eye(vectors.shape[1], dtype=np.float32)
        projected = vectors - mean
    else:
        sample = (vectors[::max(1, len(vectors) // PCA_ROWS)] - mean).astype(np.float64)
        _, axes = np.linalg.eigh(sample.T @ sample)
        axes = np.ascontiguousarray(axes[:, ::-1][:, :SEARCH_DIMS], np.float32)
        projected = (vectors - mean) @ axes
    return _Index(size, centres, mean, axes, BlockIndex(projected, engine), inside)


@functools.lru_cache(maxsize=64)
def _sample_offsets(size: int, stride: int) -> np.ndarray:
    """Flat offsets of the compared pixels of a ``size`` block (see :func:`_offsets`) in rows of ``stride``."""
    off = _offsets(size)
    return _frozen((off[:, None] * stride + off[None]).ravel())


def _gather(image: np.ndarray, pad: int, pixels: np.ndarray, size: int) -> np.ndarray:
    """The compared values ``[n, D]`` of the ``size`` blocks centred at ``pixels [n, 2]`` of an image that was
    padded by ``pad`` on every side."""
    flat = (pixels[:, 0] + pad) * image.shape[1] + pixels[:, 1] + pad
    return image.reshape(-1)[flat[:, None] + _sample_offsets(size, image.shape[1])[None]]


@dataclasses.dataclass
class BlockCopy:
    image: np.ndarray      # [H, W, C] the synthesized image
    source: np.ndarray     # [H, W, 2] int32: reference pixel each output pixel was copied from
    blocks: int
    hole_pixels: int       # pixels filled by hole filling
    mean_cost: float       # the greedy pass's mean block cost (see _choose)
    queries: int = 0       # block searches made (one per fitting size per block centre, plus one per hole pixel)
    rounds: int = 0


class _Frame:
    """A ``[H, W]`` grid embedded with a ``margin`` of cells on every side (and its right and bottom edges padded
    to multiples of ``tile``), so that the cells of any block near the grid are flat indices of one array, with
    no clipping."""

    def __init__(self, shape, margin: int, tile: int = 1):
        H, W = self.shape = shape
        self.margin = m = margin
        self.padded = (-(-H // tile) * tile + 2 * m, -(-W // tile) * tile + 2 * m)

    def flat(self, pixels: np.ndarray) -> np.ndarray:
        """Flat padded indices of ``pixels [n, 2]`` (row, col)."""
        return (pixels[:, 0] + self.margin) * self.padded[1] + pixels[:, 1] + self.margin

    def block(self, flat: np.ndarray, size: int) -> np.ndarray:
        """Flat padded indices ``[n, size * size]`` of the ``size x size`` blocks centred at ``flat [n]``."""
        return flat[:, None] + _square(size, self.padded[1])[None]


@functools.lru_cache(maxsize=64)
def _square(size: int, stride: int) -> np.ndarray:
    """Flat offsets of a ``size x size`` square about its centre in an array of row length ``stride``."""
    r = np.arange(-(size // 2), size // 2 + 1)
    return _frozen((r[:, None] * stride + r[None]).ravel())


class _Pending:
    """The pixels not yet done, and which of them are ready: ranked above every other pending pixel within
    ``reach`` (Chebyshev), so nothing processed before them in rank order can still change what fits at them,
    and no two of them can touch.

    Tested on tiles of side ``t = ceil(reach / 2)``: a tile's best pending pixel is ready when it beats the best
    of the 5 x 5 tiles around, a window (at least ``reach`` every way) a little larger than needed, which costs
    a few rounds and saves a full-resolution maximum filter per round.  Ranks must be distinct.  The ranks live
    in ``frame`` (-1 = done or outside the grid), so blocks of pixels are marked done by flat index.
    """

    def __init__(self, rank: np.ndarray, reach: int, margin: int):
        H, W = rank.shape
        self.t = t = max(1, -(-reach // 2))
        self.frame = _Frame((H, W), margin, t)
        flat_rank = rank.reshape(-1)
        if _is_dense(flat_rank):      # ranks 1 .. H W already: the order is the inverse permutation, no sort
            order = np.empty(H * W, np.int64)
            order[flat_rank - 1] = np.arange(H * W)
            dense = flat_rank
        else:
            order = np.argsort(flat_rank, kind="stable")
            dense = np.empty(H * W, np.int64)
            dense[order] = np.arange(1, H * W + 1)
        self.position = np.concatenate([[-1], order])           # dense rank (1 = lowest) -> flat pixel
        self.rank = np.full(self.frame.padded, -1, np.int32)   # int32: half the memory traffic of every round
        self.rank[margin:margin + H, margin:margin + W] = dense.reshape(H, W)
        self.core = self.rank[margin:self.rank.shape[0] - margin, margin:self.rank.shape[1] - margin]
        self.flat = self.rank.reshape(-1)

    def done(self, flat: np.ndarray) -> None:
        self.flat[flat] = -1

    def ready(self) -> np.ndarray:
        t = self.t   # maxima of strided slices: ~30x faster than a reduction over a tiled 4-D view
        columns = functools.reduce(np.maximum, (self.core[:, i::t] for i in range(t)))
        tile_max = functools.reduce(np.maximum, (columns[i::t] for i in range(t)))
        around = ndimage.maximum_filter(tile_max, size=5, mode="constant", cval=-1)
        flat = self.position[tile_max[(tile_max > 0) & (tile_max == around)]]
        return np.column_stack(np.divmod(flat, self.frame.shape[1]))


def _is_dense(rank: np.ndarray) -> bool:
    """Whether the flat ``rank`` is a permutation of 1 .. its length."""
    n = rank.size
    if n == 0 or rank.min() != 1 or rank.max() != n:
        return False
    return bool((np.bincount(rank, minlength=n + 1)[1:] == 1).all())


@dataclasses.dataclass
class Placement:
    """The non-overlapping blocks of the greedy pass, in processing order."""

    pixels: np.ndarray      # [n, 2] block centres in the output
    size_index: np.ndarray  # [n] index into the sizes
    centres: np.ndarray     # [n, 2] the matched reference centres
    costs: np.ndarray       # [n]
    queries: int
    rounds: int


def place_blocks(rank: np.ndarray, sizes, cost, context: int = 0, on_round=None) -> Placement:
    """The sequential greedy pass over ``rank [H, W]`` (highest first): each pixel that is still uncovered takes,
    of the ``sizes`` (descending) whose block (clipped at the edge) overlaps no earlier block, the one of lowest
    ``cost(size_index, pixels [n, 2]) -> (costs [n], centres [n, 2])``.

    The cost may depend on the earlier blocks within ``context`` cells around the block: ``on_round(size_index
    [n], pixels [n, 2], centres [n, 2])`` receives each round's new blocks before the next round is costed.
    Computed in rounds: a pixel is processed once every higher-ranked pixel near enough to interact with it is
    done, so one round's pixels are costed in one batch per size, and only pixels still uncovered at their turn
    are costed at all.  The result is that of visiting the pixels one by one in rank order.
    """
    H, W = rank.shape
    reach = 2 * (max(sizes) // 2) + context if len(sizes) else 0
    grow = sizes[-1] // 2 if len(sizes) else 0    # a pixel this near a block cannot take even the smallest block
    pending = _Pending(rank, reach, (max(sizes) // 2 if len(sizes) else 0) + grow)
    frame = pending.frame
    # covered cells, in the frame; the margin is cleared after every round, so blocks clipped at the edge fit
    covered = np.zeros(frame.padded, bool)
    covered_flat, m = covered.reshape(-1), frame.margin
    parts, queries, rounds = [], 0, 0
    while len(sizes):
        pixels = pending.ready()
        if len(pixels) == 0:
            break
        rounds += 1
        flat = frame.flat(pixels)
        costs = np.full((len(sizes), len(pixels)), np.inf)
        centres = np.zeros((len(sizes), len(pixels), 2), np.int64)
        for s, size in enumerate(sizes):
            here = ~covered_flat[frame.block(flat, size)].any(1)
            if here.any():
                costs[s, here], centres[s, here] = cost(s, pixels[here])
                queries += int(here.sum())
        best = costs.argmin(0)
        placed = np.isfinite(costs.min(0))
        for s, size in enumerate(sizes):
            chosen = flat[placed & (best == s)]
            covered_flat[frame.block(chosen, size)] = True
            # covered only grows: where not even the smallest block fits now, none ever will
            pending.done(frame.block(chosen, size + 2 * grow))
        covered[:m], covered[H + m:], covered[:, :m], covered[:, W + m:] = False, False, False, False
        pending.done(flat)
        picked = np.flatnonzero(placed)
        parts.append((pixels[picked], best[picked], centres[best[picked], picked], costs[best[picked], picked]))
        if on_round is not None:
            on_round(best[picked], pixels[picked], centres[best[picked], picked])
    if not parts:
        return Placement(np.zeros((0, 2), np.int64), np.zeros(0, np.int64), np.zeros((0, 2), np.int64),
                         np.zeros(0), queries, rounds)
    return Placement(*(np.concatenate(column) for column in zip(*parts)), queries, rounds)


def block_copy(template: np.ndarray, reference: np.ndarray, valid: np.ndarray, block_sizes=(3, 5, 9),
               hole_size: int = 3, seed: int = 0, engine: str = "fast", threads: int = 1,
               feather: int = FEATHER, relax: int = RELAX, colour: float = COLOUR) -> BlockCopy:
    """Synthesize an image shaped like ``template [H, W]`` from blocks of ``reference [h, w, C]`` (see module;
    the greedy pass is :func:`place_blocks`, the choice among a block's candidates :func:`_choose`); the block
    indexes are built on up to ``threads`` threads."""
    rng = np.random.default_rng(seed)
    H, W = template.shape
    grey = reference.mean(axis=2)
    guide = histogram_match(template, grey[valid] if valid.any() else grey)
    sizes = sorted({int(s) | 1 for s in block_sizes} | {hole_size | 1}, reverse=True)
    # one generator per size, so the indexes can be built on threads (the k-d tree builds release the GIL)
    seeds = rng.integers(0, 2**63, len(sizes))
    build = lambda i: _block_index(grey, valid, sizes[i], np.random.default_rng(seeds[i]), engine)  # noqa: E731
    if threads > 1 and engine == "fast":
        with concurrent.futures.ThreadPoolExecutor(min(threads, len(sizes))) as pool:
            built = dict(zip(sizes, pool.map(build, range(len(sizes)))))
    else:
        built = {s: build(i) for i, s in enumerate(sizes)}
    hole_index = built[hole_size | 1] or next((built[s] for s in sizes[::-1] if built[s] is not None), None)
    indexes = [built[s] for s in sorted({int(s) | 1 for s in block_sizes}, reverse=True) if built[s] is not None]
    if hole_index is None:
        from btforge.errors import BtforgeInputError
        raise BtforgeInputError("liu.synthesize 'references'", f"a warped reference has no valid "
                                f"{hole_size} x {hole_size} block", "give larger reference images")
    pad = max([i.size for i in indexes] + [hole_index.size]) // 2
    padded = np.ascontiguousarray(np.pad(guide, pad, mode="reflect"), np.float32)
    grey = np.ascontiguousarray(grey, np.float32)
    response = harris_response(guide) + rng.uniform(0, 1e-12, (H, W))   # random tie-break
    rank = np.empty(H * W, np.int64)
    rank[np.argsort(-response, axis=None, kind="stable")] = np.arange(H * W, 0, -1)
    canvas = _Canvas((H, W), reference, valid, pad + RING)

    def cost(s, pixels):
        queries = _gather(padded, pad, pixels, indexes[s].size)
        return _choose(indexes[s], queries, grey, canvas, pixels, indexes[s].size, colour)

    def paste(size_index, pixels, centres):
        for s, ix in enumerate(indexes):
            canvas.paste(pixels[size_index == s], centres[size_index == s], ix.size)

    placed = place_blocks(rank.reshape(H, W), [ix.size for ix in indexes], cost, context=RING, on_round=paste)
    hole_pixels = int((canvas.uncovered()).sum())
    queries = placed.queries + _fill_holes(canvas, hole_index, padded, pad, grey, colour)
    source = canvas.core(canvas.source).astype(np.int32)
    mean_cost = float(placed.costs.mean()) if len(placed.costs) else 0.0
    if relax > 0:
        source = relax_block_seams(source, reference, valid, relax)
    if feather > 0:
        out = feather_seams(source, reference, valid, feather, guide)
    else:
        out = reference[source[..., 0], source[..., 1]].astype(np.float32)
    return BlockCopy(out, source, len(placed.pixels), hole_pixels, mean_cost, queries, placed.rounds)


@functools.lru_cache(maxsize=64)
def _ring(size: int, width: int) -> np.ndarray:
    """Offsets ``[n, 2]`` of the cells of the ``width`` rings just outside a ``size x size`` block."""
    r = size // 2
    k = range(-r - width, r + width + 1)
    return _frozen(np.array([(i, j) for i in k for j in k if max(abs(i), abs(j)) > r], np.int64))


@functools.lru_cache(maxsize=64)
def _compass(size: int) -> np.ndarray:
    """The 8 compass points ``[8, 2]`` of the first ring around a block: the blocks covering them, continued,
    are candidates."""
    r = size // 2 + 1
    return _frozen(np.array([(i, j) for i in (-r, 0, r) for j in (-r, 0, r) if i or j], np.int64))


class _Canvas:
    """The block copy as it grows: each pixel's reference source row and column (-1: not covered yet) and colour,
    and the reference with its validity, all in frames with a ``margin`` (uncovered, invalid) on every side, so
    the cells around any block or candidate are flat indices, with no clipping."""

    def __init__(self, shape, reference: np.ndarray, valid: np.ndarray, margin: int):
        self.frame, self.ref_frame = _Frame(tuple(shape), margin), _Frame(valid.shape, margin)
        self.m = m = margin
        self.source = np.full(self.frame.padded + (2,), -1, np.int64)
        self.colour = np.zeros(self.frame.padded + (reference.shape[2],), np.float32)
        ref = np.pad(reference.astype(np.float32), ((m, m), (m, m), (0, 0)))
        self.reference = ref.reshape(-1, reference.shape[2])
        self.valid = np.pad(valid, m).reshape(-1)
        texels = reference[valid] if valid.any() else reference.reshape(-1, reference.shape[2])
        # a continuation onto no data counts as a random texel: the mean squared difference of two of them
        self.unseen = float(2 * texels.astype(np.float64).var(0).mean())

    def core(self, array: np.ndarray) -> np.ndarray:
        m, (H, W) = self.m, self.frame.shape
        return array[m:m + H, m:m + W]

    def uncovered(self) -> np.ndarray:
        return self.core(self.source)[..., 0] < 0

    def paste(self, pixels: np.ndarray, centres: np.ndarray, size: int) -> None:
        """Copy the ``size x size`` reference blocks at ``centres [n, 2]`` to ``pixels [n, 2]``, clipped at the
        edge (the cells pasted into the margin are cleared again)."""
        cells = self.frame.block(self.frame.flat(pixels), size).ravel()
        rows, cols = _square_rows_cols(size)
        source = self.source.reshape(-1, 2)
        source[cells, 0] = (centres[:, :1] + rows[None]).ravel()
        source[cells, 1] = (centres[:, 1:] + cols[None]).ravel()
        self.colour.reshape(-1, self.colour.shape[2])[cells] = self.reference[
            self.ref_frame.block(self.ref_frame.flat(centres), size).ravel()]
        m = self.m
        self.source[:m], self.source[-m:], self.source[:, :m], self.source[:, -m:] = -1, -1, -1, -1

    def disagreement(self, pixels: np.ndarray, centres: np.ndarray, ring: np.ndarray) -> np.ndarray:
        """``[n, k]`` mean squared colour difference (per channel) between the covered ``ring [R, 2]`` cells
        around ``pixels [n, 2]`` and what the reference blocks at ``centres [n, k, 2]`` continue to there (0
        where no ring cell is covered yet)."""
        n, k = centres.shape[:2]
        out = np.zeros((n, k), np.float32)
        cells = self.frame.flat(pixels)[:, None] + _flat(ring, self.frame.padded[1])[None]        # [n, R]
        covered = self.source.reshape(-1, 2)[cells, 0] >= 0
        block, cell = np.nonzero(covered)          # only the covered cells are compared (sorted by block)
        if len(block) == 0:
            return out
        have = self.colour.reshape(-1, self.colour.shape[2])[cells[block, cell]]                # [P, C]
        ahead = (self.ref_frame.flat(centres.reshape(-1, 2)).reshape(n, k)[block]
                 + _flat(ring, self.ref_frame.padded[1])[cell][:, None])                         # [P, k]
        delta = self.reference[ahead] - have[:, None]                                           # [P, k, C]
        diff = np.einsum("pkc,pkc->pk", delta, delta) / np.float32(delta.shape[2])
        diff = np.where(self.valid[ahead], diff, np.float32(self.unseen))
        near, starts, count = np.unique(block, return_index=True, return_counts=True)
        out[near] = np.add.reduceat(diff, starts, axis=0) / count[:, None]
        return out

    def continuations(self, pixels: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The reference centres ``[n, p, 2]`` that continue the blocks covering ``pixels + points`` to
        ``pixels``, and whether each exists ``[n, p]`` (its cell is covered and the centre lies in the
        reference)."""
        cells = self.frame.flat(pixels)[:, None] + _flat(points, self.frame.padded[1])[None]
        src = self.source.reshape(-1, 2)[cells]
        centres = src - points[None]
        h, w = self.ref_frame.shape
        ok = (src[..., 0] >= 0) & (centres >= 0).all(-1) & (centres[..., 0] < h) & (centres[..., 1] < w)
        return centres, ok


@functools.lru_cache(maxsize=64)
def _square_rows_cols(size: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column offsets of a ``size x size`` square's cells about its centre, in :func:`_square`'s order."""
    r = np.arange(-(size // 2), size // 2 + 1)
    return _frozen(np.repeat(r, size)), _frozen(np.tile(r, size))


def _flat(offsets: np.ndarray, stride: int) -> np.ndarray:
    """Flat offsets of ``offsets [n, 2]`` (rows, columns) in an array of row length ``stride``."""
    return offsets[:, 0] * stride + offsets[:, 1]


def _choose(index: _Index, queries: np.ndarray, grey: np.ndarray, canvas: _Canvas, pixels: np.ndarray,
            size: int, colour: float) -> tuple[np.ndarray, np.ndarray]:
    """``(costs [n], centres [n, 2])``: the reference block to paste as ``size x size`` at each of ``pixels``.

    Candidates: the ``CANDIDATES`` blocks nearest to the template's (``queries [n, D]``, the k-d tree), and the
    continuations of the blocks already covering the 8 compass points just outside the block.  Cost: the
    normalised template SSD plus ``colour`` times the colour disagreement of the block's continuation with the
    cells already covered around it (:meth:`_Canvas.disagreement`), so a block is chosen to join its
    neighbours in colour, which the grey template cannot see."""
    lossless = index.axes.shape[0] == index.axes.shape[1]
    centred = queries - index.mean
    idx, _ = index.search.query(centred if lossless else centred @ index.axes, CANDIDATES)
    found = index.centres[idx]                                          # [n, k, 2]
    joins, ok = canvas.continuations(pixels, _compass(size))
    ok[ok] = index.inside[joins[ok][:, 0], joins[ok][:, 1]]
    joins = np.where(ok[..., None], joins, found[:, :1])                # (unusable ones: the nearest match again)
    centres = np.concatenate([found, joins], 1)
    n, k = centres.shape[:2]
    blocks = _gather(grey, 0, centres.reshape(-1, 2), index.size).reshape(n, k, -1)
    costs = ((blocks - queries[:, None]) ** 2).mean(-1)
    if colour > 0:
        costs = costs + colour * canvas.disagreement(pixels, centres, _ring(size, RING))
    best = costs.argmin(1)
    return costs[np.arange(n), best], centres[np.arange(n), best]


def _fill_holes(canvas: _Canvas, index: _Index, padded: np.ndarray, pad: int, grey: np.ndarray,
                colour: float) -> int:
    """Cover every pixel the greedy pass left uncovered, from the holes' rims inwards, each pixel taking the
    centre of the block :func:`_choose` picks for the ``index.size`` template block about it (as a 1 x 1
    block, so its neighbours are what it must join).  A wave is the uncovered pixels next to covered ones, in
    four interleaved batches (row and column parity) so no two pixels of a batch touch.  Returns the searches
    made."""
    searches = 0
    H, W = canvas.frame.shape
    parity = np.add.outer(np.arange(H) % 2 * 2, np.arange(W) % 2)
    while True:
        uncovered = canvas.uncovered()
        if not uncovered.any():
            return searches
        rim = ndimage.binary_dilation(~uncovered, np.ones((3, 3), bool)) & uncovered
        wave = rim if rim.any() else uncovered
        for batch in range(4):
            found = np.argwhere(wave & (parity == batch))
            for start in range(0, len(found), HOLE_CHUNK):   # (a batch's pixels do not touch: any split will do)
                pixels = found[start:start + HOLE_CHUNK]
                queries = _gather(padded, pad, pixels, index.size)
                _, centres = _choose(index, queries, grey, canvas, pixels, 1, colour)
                canvas.paste(pixels, centres, 1)
            searches += len(found)


def relax_block_seams(source: np.ndarray, reference: np.ndarray, valid: np.ndarray, sweeps: int) -> np.ndarray:
    """``source [H, W, 2]`` after ``sweeps`` of the Wang tiles' texel-level seam relaxation
    (:func:`btforge.plugins.wang.relax.relax_seams`) in the reference's colours: each pixel may keep its reference
    texel or take the continuation of a neighbouring block, whichever shows the least colour jump against its
    neighbours, so block boundaries move to where the blocks agree in colour (which the grey template matching
    cannot see) and one-pixel islands vanish.  Continuations onto invalid reference pixels (outside the warped
    image) cost so much that they are never taken."""
    from btforge.plugins.wang.relax import relax_seams
    colours = reference.astype(np.float32).copy()
    colours[~valid] = 1e6
    return relax_seams(source, colours, np.ones(source.shape[:2], bool), sweeps).astype(source.dtype)


NEIGHBOUR_STEPS = ((0, 1), (0, -1), (1, 0), (-1, 0))


def feather_seams(source: np.ndarray, reference: np.ndarray, valid: np.ndarray, band: int,
                  guide: np.ndarray | None = None) -> np.ndarray:
    """The image ``reference[source]`` with its block boundaries blended in reflectance space.

    Each pixel within ``band`` texels of a boundary (a neighbour whose source does not continue its own) is
    mixed with the neighbouring block's *continuation* at that pixel (the reference texel the other block would
    have put there), with weight ``(band - d + 1) / band`` at distance ``d`` against 1 for its own texel: at the
    boundary both sides show the mean of the two blocks, so the jump across it is that of the reference, while
    pixels further in keep more of their own texel.  Continuations outside the reference's valid pixels are
    skipped.  With a ``guide [H, W]`` (the histogram-matched template), a continuation's weight also falls with
    its grey level's distance from the guide's, ``exp(-(grey - guide)^2 / (2 s^2))`` with ``s`` half the
    guide's spread: a block boundary along a shadow's edge stays sharp where the template says it is.  Returns ``[H, W, C]`` float32; ``source`` is unchanged (it still names each pixel's own texel).
    """
    H, W = source.shape[:2]
    h, w = reference.shape[:2]
    ref = reference.astype(np.float64)
    grey = ref.mean(-1)
    spread = 2 * (GUIDE_SPREAD * float(np.std(guide))) ** 2 if guide is not None else 0.0
    total = ref[source[..., 0], source[..., 1]].copy()
    weight = np.ones((H, W))
    for step in NEIGHBOUR_STEPS:
        continuous = np.ones((H, W), bool)       # own block continues this far along the ray
        for d in range(1, band + 1):
            here, there = _shifted_pair((H, W), step, d)
            if here is None:
                break
            inner = (slice(here[0].start, here[0].stop), slice(here[1].start, here[1].stop))
            prev = _shift_slices((H, W), step, d - 1, here)
            seam = np.any(source[there] != source[prev] + np.multiply(step, 1), axis=-1)
            first = continuous[inner] & seam
            candidate = source[there] - np.multiply(step, d)
            ok = first & (candidate >= 0).all(-1) & (candidate[..., 0] < h) & (candidate[..., 1] < w)
            rows, cols = np.nonzero(ok)
            cy, cx = candidate[rows, cols, 0], candidate[rows, cols, 1]
            keep = valid[cy, cx]
            rows, cols, cy, cx = rows[keep], cols[keep], cy[keep], cx[keep]
            wd = np.full(len(rows), (band - d + 1) / band)
            if spread > 0:
                wd *= np.exp(-(grey[cy, cx] - guide[inner][rows, cols]) ** 2 / spread)
            total[inner][rows, cols] += wd[:, None] * ref[cy, cx]
            weight[inner][rows, cols] += wd
            continuous[inner] &= ~seam
    return (total / weight[..., None]).astype(np.float32)


def _shifted_pair(shape, step, d):
    """Slices ``(here, there)`` of an ``[H, W]`` grid with ``there = here + d * step`` (``(None, None)`` when no
    pixel has a neighbour that far)."""
    H, W = shape
    dy, dx = step[0] * d, step[1] * d
    if abs(dy) >= H or abs(dx) >= W:
        return None, None
    here = (slice(max(0, -dy), H - max(0, dy)), slice(max(0, -dx), W - max(0, dx)))
    there = (slice(max(0, dy), H - max(0, -dy)), slice(max(0, dx), W - max(0, -dx)))
    return here, there


def _shift_slices(shape, step, d, here):
    """The slices of the pixels ``d * step`` after the pixels ``here``."""
    dy, dx = step[0] * d, step[1] * d
    return (slice(here[0].start + dy, here[0].stop + dy), slice(here[1].start + dx, here[1].stop + dx))
