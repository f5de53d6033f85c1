"""Image quilting of reflectance functions with an exact projection-kernel rejection search.

Blocks of the exemplar are laid down in raster order (Efros & Freeman 2001) on the per-texel appearance vectors
of :func:`~btforge.plugins.synth.features.texel_features` (for a PTM: orthonormal Legendre coefficients, where
vector distance is function distance - Hel-Or, Malzbender & Gelb 2003).  For each block position the overlap with
what is already synthesized is compared with the same overlap of every exemplar block, one is picked at random
among those within ``(1 + tolerance)`` of the best, and the blocks are joined by a minimum-error boundary cut or
by linear blending.

The search (:mod:`.quilt_search`: brute force, or the exact projection-kernel rejection of Hel-Or & Hel-Or
2002, which keeps the brute force's picks) is the costly part; its module says how it works.

Candidates are all block positions lying wholly inside the exemplar (the exemplar is not treated as periodic).
"""
from __future__ import annotations

import collections
import dataclasses
import math
import statistics
import time

import numpy as np

from btforge import Param
from btforge.buffers import CoordMap, PerTexel
from btforge.errors import BtforgeInputError

from .features import texel_features
from .quilt_search import SEARCHES, QuiltSearch
from .quilt_seams import _region, _span, blend_alpha, cut_mask
from .synthesizer import declare_synthesizer


SEAMS = ("cut", "blend")


# ----------------------------------------------------------------------------------------------- layout


@dataclasses.dataclass(frozen=True)
class AxisLayout:
    """Where blocks start along one axis and how much each overlaps its neighbours.

    ``before[i]`` is block i's overlap with block i - 1 (0 for the first block); ``after[i]`` its overlap with
    block 0 across the periodic boundary (non-zero only for the last block of a wrapped layout).  ``canvas`` is the
    length synthesized: the output size when wrapping (indices wrap modulo it), else enough whole blocks to cover
    the output, which is then cropped.
    """

    starts: tuple[int, ...]
    before: tuple[int, ...]
    after: tuple[int, ...]
    canvas: int


def axis_layout(size: int, block: int, overlap: int, wrap: bool) -> AxisLayout:
    """Block placement along one axis (see :class:`AxisLayout`).

    Without wrap, blocks step by ``block - overlap`` and the last one may run past ``size``.  With wrap, the
    ``n = ceil(size / step)`` blocks must tile a period of exactly ``size``, so steps are spread evenly
    (``floor(size / n)`` or one more): overlaps are ``overlap`` or a little wider, never narrower.
    """
    step = block - overlap
    if not wrap:
        n = max(1, -(-(size - overlap) // step))
        starts = tuple(i * step for i in range(n))
        return AxisLayout(starts, (0,) + (overlap,) * (n - 1), (0,) * n, (n - 1) * step + block)
    n = -(-size // step)
    starts = tuple(i * size // n for i in range(n))
    ends = starts[1:] + (size,)
    seams = tuple(block - (e - s) for s, e in zip(starts, ends))  # seam i joins block i and block i + 1 (mod n)
    return AxisLayout(starts, (0,) + seams[:-1], (0,) * (n - 1) + (seams[-1],), size)


def validate(exemplar_size: tuple[int, int], size, block: int, overlap: int, wrap: bool, tolerance: float = 0.0):
    """Raise :class:`BtforgeInputError` naming the parameter when the quilting parameters cannot work."""
    ex_h, ex_w = exemplar_size
    if block < 3:
        raise BtforgeInputError("quilt 'block'", f"expected at least 3 texels, found {block}",
                                "use a block of about the size of the exemplar's features, e.g. 32")
    if block > min(ex_h, ex_w):
        raise BtforgeInputError("quilt 'block'",
                                f"expected a block that fits in the {ex_h} x {ex_w} exemplar, found {block}",
                                f"use block <= {min(ex_h, ex_w)}")
    if overlap < 1 or 2 * overlap >= block:
        raise BtforgeInputError("quilt 'overlap'",
                                f"expected 1 <= overlap < block / 2 = {block / 2:g}, found {overlap}",
                                f"use e.g. overlap {max(1, block // 6)} (block // 6)")
    if len(size) != 2 or min(size) < block:
        raise BtforgeInputError("quilt 'size'",
                                f"expected an [H, W] of at least the block ({block}) each, found {list(size)}",
                                f"use a size of at least [{block}, {block}] or a smaller block")
    if tolerance < 0 or not math.isfinite(tolerance):
        raise BtforgeInputError("quilt 'tolerance'", f"expected a finite value >= 0, found {tolerance}",
                                "use e.g. 0.1: blocks within 10% of the best overlap error are eligible")
    if wrap:
        step = block - overlap
        for axis, n in zip(("height", "width"), size):
            layout = axis_layout(n, block, overlap, True)
            widest = max(layout.before + layout.after)
            if 2 * widest >= block:
                raise BtforgeInputError(
                    "quilt 'size'", f"a periodic {axis} of {n} needs block overlaps of {widest} texels, expected "
                    f"< block / 2 = {block / 2:g}",
                    f"use a multiple of block - overlap = {step}, e.g. {-(-n // step) * step}")



# ----------------------------------------------------------------------------------------------- synthesis


@dataclasses.dataclass
class QuiltResult:
    coords: CoordMap
    stats: dict


def quilt_features(feats: np.ndarray, size, block: int = 32, overlap: int = 6, *, search: str = "rejection",
                   seam: str = "cut", tolerance: float = 0.1, wrap: bool = False, seed: int = 0,
                   engine: str = "opencl") -> QuiltResult:
    """Quilt appearance vectors ``feats [H, W, D]`` into a coordinate map of ``size = (H, W)``.

    ``engine='numpy'`` runs the searches on the NumPy references instead of OpenCL.  Returns the map and
    statistics (blocks, candidates, per-projection rejected fractions, timings).
    """
    start_time = time.perf_counter()
    feats = np.ascontiguousarray(feats, np.float32)
    if feats.ndim != 3:
        raise BtforgeInputError("quilt 'exemplar'", f"expected [H, W, D] appearance vectors, found shape {feats.shape}",
                                "pass texel_features(buffer), which gives every per-texel buffer that shape")
    if not np.isfinite(feats).all():
        raise BtforgeInputError("quilt 'exemplar'", f"expected finite texel values, found "
                                f"{int((~np.isfinite(feats)).sum())} NaN/Inf", "repair the exemplar before synthesis")
    if search not in SEARCHES:
        raise BtforgeInputError("quilt 'search'", f"expected one of {SEARCHES}, found {search!r}",
                                "use 'rejection' (fast, exact) or 'brute' (the reference)")
    if seam not in SEAMS:
        raise BtforgeInputError("quilt 'seam'", f"expected one of {SEAMS}, found {seam!r}",
                                "use 'cut' (minimum-error boundary) or 'blend' (linear blending)")
    height, width = (int(v) for v in size)
    validate(feats.shape[:2], (height, width), block, overlap, wrap, tolerance)

    lay_y = axis_layout(height, block, overlap, wrap)
    lay_x = axis_layout(width, block, overlap, wrap)
    uses = collections.Counter((ty, by, lx, rx) for ty, by in zip(lay_y.before, lay_y.after)
                               for lx, rx in zip(lay_x.before, lay_x.after))
    uses.pop((0, 0, 0, 0), None)  # the first block is not searched
    searcher = QuiltSearch(feats, block, method=search, tolerance=tolerance, engine=engine)
    projections = searcher.budget(uses)
    canvas_h, canvas_w = lay_y.canvas, lay_x.canvas
    dims = feats.shape[2]
    primary = np.zeros((canvas_h, canvas_w, 2), np.int32)
    second = np.zeros((canvas_h, canvas_w, 2), np.int32)
    weight = np.zeros((canvas_h, canvas_w), np.float32)
    canvas = np.zeros((canvas_h, canvas_w, dims), np.float32)   # what the output's appearance vectors will be
    grid = np.indices((block, block), dtype=np.int32).transpose(1, 2, 0)
    rng = np.random.default_rng(seed)
    blend = seam == "blend"
    placed: dict[tuple[int, int], tuple[int, int]] = {}

    for i, y in enumerate(lay_y.starts):
        rows = _span(y, block, canvas_h)
        for j, x in enumerate(lay_x.starts):
            region = _region(rows, _span(x, block, canvas_w))
            key = (lay_y.before[i], lay_y.after[i], lay_x.before[j], lay_x.after[j])
            first = key == (0, 0, 0, 0)
            if first:
                pick = int(rng.integers(searcher.n_cand))
            else:
                shape = searcher.shape(key, projections[key])
                # Blocks continuing the neighbours' exemplar positions often match well: they seed the threshold.
                hints = tuple(searcher.candidate(placed[(a, b)][0] + y - lay_y.starts[a],
                                                 placed[(a, b)][1] + x - lay_x.starts[b])
                              for a, b in ((i, j - 1), (i - 1, j), (i - 1, j - 1)) if (a, b) in placed)
                pick = searcher.pick(shape, canvas[region], rng, hints)
            r0, c0 = divmod(pick, searcher.cols)
            placed[(i, j)] = (r0, c0)
            new_feats = feats[r0:r0 + block, c0:c0 + block]
            new_coords = grid + np.array([r0, c0], np.int32)
            if first:
                primary[region] = new_coords
                second[region] = new_coords
                weight[region] = 0
                canvas[region] = new_feats
            elif not blend:
                old = canvas[region]
                err = np.einsum("ijk,ijk->ij", old - new_feats, old - new_feats)
                show = cut_mask(err, key)
                primary[region] = np.where(show[..., None], new_coords, primary[region])
                canvas[region] = np.where(show[..., None], new_feats, old)
            else:
                alpha = blend_alpha(block, key)
                old_w = weight[region]
                dominant = np.where((old_w > 0.5)[..., None], second[region], primary[region])
                whole = alpha >= 1
                first_texel = np.where(whole[..., None], new_coords, dominant)
                w = np.where(whole, np.float32(0), alpha)
                primary[region] = first_texel
                second[region] = new_coords
                weight[region] = w
                canvas[region] = ((1 - w)[..., None] * feats[first_texel[..., 0], first_texel[..., 1]]
                                  + w[..., None] * new_feats)

    coords = primary[:height, :width]
    if blend:
        w = weight[:height, :width]
        other = np.where((w > 0)[..., None], second[:height, :width], coords)
        result = CoordMap(np.ascontiguousarray(coords), (feats.shape[0], feats.shape[1]), np.ascontiguousarray(other),
                          np.ascontiguousarray(w), wrap=wrap)
    else:
        result = CoordMap(np.ascontiguousarray(coords), (feats.shape[0], feats.shape[1]), wrap=wrap)
    stats = {
        "search": search,
        "blocks": len(lay_y.starts) * len(lay_x.starts),
        "candidates": searcher.n_cand,
        "features": dims,
        "overlap_shapes": len(searcher.shapes),
        "queries": searcher.queries,
        "full_distances": searcher.full_distances,
        "full_distance_fraction": round(searcher.full_distances / max(1, searcher.queries * searcher.n_cand), 5),
        "projections": {"/".join(map(str, k)): len(s.funcs) for k, s in searcher.shapes.items() if s.funcs is not None},
        "rejected_after_projection": searcher.rejected_fractions(),
        "host_distances": searcher.host_distances,
        "precompute_s": round(searcher.precompute_s, 4),
        "search_s": round(searcher.search_s, 4),
        "total_s": round(time.perf_counter() - start_time, 4),
    }
    return QuiltResult(result, stats)


# ----------------------------------------------------------------------------------------------- stage


@declare_synthesizer(
    "synth.quilt", deprecated_names=("quilt",),
    params=[
        Param("block", "int", 32, "block side in texels", low=3),
        Param("overlap", "int", 0, "overlap between neighbouring blocks in texels (1 <= overlap < block / 2); "
              "0 picks block // 6 (at least 1)", low=0),
        Param("search", "choice", "rejection", "rejection: exact projection-kernel search (fast); brute: every "
              "candidate's full distance (reference)", choices=SEARCHES),
        Param("seam", "choice", "cut", "cut: minimum-error boundary cut; blend: linear blending across overlaps",
              choices=SEAMS),
        Param("tolerance", "float", 0.1, "candidates within (1 + tolerance) x the best overlap error are eligible; "
              "one is picked at random", low=0.0),
    ],
)
def quilt(ctx, exemplar, *, size, wrap, seed, block, overlap, search, seam, tolerance):
    """Synthesize a larger texture by image quilting of per-texel reflectance functions.

    Exemplar blocks are laid in raster order (Efros & Freeman 2001) on the texels' appearance vectors (for a PTM
    the orthonormal Legendre coefficients, where vector distance equals function distance - Hel-Or, Malzbender &
    Gelb 2003; for a stack the radiance under every light; PCA-reduced to 32 dimensions when longer).  Each block is chosen at random among the exemplar
    blocks (every position lying wholly inside the exemplar) whose overlap with the already synthesized texture has
    a sum of squared differences within ``(1 + tolerance)`` x the best, and joined by a minimum-error boundary cut
    (``seam: cut``) or linear blending (``seam: blend``, recorded as the map's blend weights).  With ``wrap`` the
    last row and column of blocks are also matched against the first, so the result tiles seamlessly; block
    overlaps are then spread evenly and may be a texel wider than ``overlap``.

    ``search: rejection`` (Hel-Or & Hel-Or 2002) projects every candidate's overlap, once per overlap shape, onto up
    to 1024 orthonormal Haar functions of the overlap (one feature dimension each, most energetic first); for each
    block, the sum of squared projected differences is a lower bound on the full distance and rules out almost all
    candidates, and only the survivors get full distances.  Safety margins make it exact: it returns the same
    eligible blocks, hence the same picks, as ``search: brute``.  The stored projections take up to 128 MB.

    Outputs
    -------
    coords : CoordMap
        ``[H, W, 2]`` exemplar coordinates (replay on any representation with ``materialize``).

    Notes
    -----
    ``rejected_after_projection`` lists the mean fraction of candidates ruled out after each projection;
    ``full_distance_fraction`` the fraction whose full distance was computed.
    """
    overlap = overlap or max(1, block // 6)
    validate((exemplar.height, exemplar.width), size, block, overlap, wrap, tolerance)  # before any work
    feats = texel_features(exemplar)
    result = quilt_features(feats, size, block, overlap, search=search, seam=seam, tolerance=tolerance, wrap=wrap,
                            seed=seed)
    for key, value in result.stats.items():
        ctx.note(key, value)
    return {"coords": result.coords}


STAGES = [quilt]


# ----------------------------------------------------------------------------------------------- benchmark


def smooth_fields(size: int, channels: int, seed: int = 0, sigma: float = 3.0) -> np.ndarray:
    """``[size, size, channels]`` float32 periodic random fields, Gaussian-smoothed, zero mean, unit variance."""
    from scipy.ndimage import gaussian_filter
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((channels, size, size))
    fields = np.stack([gaussian_filter(n, sigma, mode="wrap") + 0.35 * gaussian_filter(n, sigma / 3, mode="wrap")
                       for n in noise], axis=-1)
    fields -= fields.mean(axis=(0, 1))
    fields /= fields.std(axis=(0, 1)) + 1e-12
    return fields.astype(np.float32)


def smooth_ptm_exemplar(size: int = 128, seed: int = 0):
    """An lrgb PTM (orthonormal basis) whose 6 coefficients and 3 colours are random smooth fields."""
    from btforge.plugins.ptm.model import PTMModel
    f = smooth_fields(size, 9, seed)
    scale = np.array([0.15, 0.08, 0.08, 0.05, 0.04, 0.04], np.float32)
    coeffs = f[..., :6] * scale
    coeffs[..., 0] += 0.8  # the constant term: mean brightness
    albedo = np.clip(0.55 + 0.15 * f[..., 6:], 0.0, 1.0)
    return PTMModel(coeffs[:, :, None, :].astype(np.float32), albedo.astype(np.float32), "lrgb", "linear",
                    basis="orthonormal")


def _central_crop(exemplar: PerTexel, size: int) -> PerTexel:
    h, w = min(size, exemplar.height), min(size, exemplar.width)
    y0, x0 = (exemplar.height - h) // 2, (exemplar.width - w) // 2
    rows, cols = np.meshgrid(np.arange(y0, y0 + h), np.arange(x0, x0 + w), indexing="ij")
    return exemplar.remap(rows, cols)


def benchmark_quilt(exemplar_size: int = 128, output_size: int = 512, block: int = 32, seed: int = 0,
                    repeat: int = 3, *, exemplar: PerTexel | None = None, overlap: int = 6,
                    tolerance: float = 0.1) -> dict:
    """Time brute-force and rejection quilting on the same exemplar and check their picks are identical.

    The exemplar is the central ``exemplar_size`` crop of ``exemplar`` when given, else an lrgb PTM of random smooth
    fields (9-D appearance vectors: 6 orthonormal coefficients + 3 colours).  Kernels are compiled by a warm-up
    run first; each search then runs ``repeat`` times and medians are reported (seconds), with the speed-up, the mean
    fraction of candidates rejected after each projection, and the fraction whose full distance was computed.
    """
    from btforge.backend import get_backend
    if exemplar is not None:
        source = _central_crop(exemplar, exemplar_size)
    else:
        source = smooth_ptm_exemplar(exemplar_size, seed)
    feats = texel_features(source)
    size = (output_size, output_size)
    small = feats[:min(feats.shape[0], 2 * block), :min(feats.shape[1], 2 * block)]
    for method in SEARCHES:  # compile the kernels outside the timings
        quilt_features(small, (block * 2, block * 2), block, overlap, search=method, seed=seed)
    times: dict[str, list[float]] = {m: [] for m in SEARCHES}
    cpu: dict[str, list[float]] = {m: [] for m in SEARCHES}
    results = {}
    for _ in range(repeat):  # interleaved, so both searches see the same machine load
        for method in ("brute", "rejection"):
            t0, c0 = time.perf_counter(), time.process_time()
            res = quilt_features(feats, size, block, overlap, search=method, tolerance=tolerance, seed=seed)
            times[method].append(time.perf_counter() - t0)
            cpu[method].append(time.process_time() - c0)
            if method in results and not np.array_equal(results[method].coords.coords, res.coords.coords):
                raise AssertionError(f"{method} quilting is not deterministic")
            results[method] = res
    identical = bool(np.array_equal(results["brute"].coords.coords, results["rejection"].coords.coords))
    rej = results["rejection"].stats
    brute_s, rejection_s = statistics.median(times["brute"]), statistics.median(times["rejection"])
    return {
        "device": get_backend().description,
        "exemplar": "given (central crop)" if exemplar is not None else "random smooth fields (lrgb PTM)",
        "exemplar_size": list(feats.shape[:2]),
        "features": int(feats.shape[2]),
        "output_size": list(size),
        "block": block,
        "overlap": overlap,
        "tolerance": tolerance,
        "blocks": rej["blocks"],
        "candidates": rej["candidates"],
        "brute_s": round(brute_s, 3),
        "rejection_s": round(rejection_s, 3),
        "speedup": round(brute_s / rejection_s, 2),
        "brute_cpu_s": round(statistics.median(cpu["brute"]), 3),
        "rejection_cpu_s": round(statistics.median(cpu["rejection"]), 3),
        "speedup_cpu": round(statistics.median(cpu["brute"]) / statistics.median(cpu["rejection"]), 2),
        "brute_search_s": results["brute"].stats["search_s"],
        "rejection_search_s": rej["search_s"],
        "rejection_precompute_s": rej["precompute_s"],
        "rejected_after_projection": rej["rejected_after_projection"],
        "full_distance_fraction": rej["full_distance_fraction"],
        "identical_picks": identical,
        "times": {m: [round(t, 3) for t in v] for m, v in times.items()},
    }
