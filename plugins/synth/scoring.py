"""Measured synthesis quality: compare a synthesized reflectance texture with its exemplar, light by light.

The ``synth.score`` stage relights both textures at a set of lights and measures, in an exposure-normalised
perceptual domain, how well the output reproduces the exemplar's local statistics (sliced Wasserstein distance
of patches, coherence, completeness), how much of it is a verbatim copy, how visible its seams are, and whether
every output texel comes from one exemplar place under all lights (what distinguishes a synthesis of
reflectance functions from independent 2D syntheses of each image).

Everything is NumPy/SciPy on the host: the work is patch extraction, small matrix products, sorting and k-d
tree queries, which BLAS and SciPy already do well on a CPU.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from btforge import Param, declare_stage
from btforge.buffers import (SRGB8_TO_LINEAR, CoordMap, PerTexel, ReflectanceModel, SampleStack, Scores, capability,
                             unit_directions)
from btforge.errors import BtforgeInputError

from . import visibility
from .coarse_steps import straight_step_visibility
from .features import downsample, encoded, white_points
from .search_base import cores

#: Patches per image that enter one sliced-Wasserstein comparison (all of them when there are fewer).
SWD_PATCH_CAP = 16384
#: Patches indexed by one nearest-neighbour tree (exemplar patches for coherence, output ones for completeness).
TREE_CAP = 65536
#: Dimensions kept by the PCA that patches are reduced to before the tree search.
PCA_DIMS = 16
#: Candidates found in PCA space and re-ranked by their exact (full-dimensional) patch distance.
RERANK_K = 4
#: A stack light counts as the one asked for when the directions are within this angle (degrees).
LIGHT_MATCH_DEG = 0.1
#: Lights used when neither input is a stack and no ``lights`` are given.
DEFAULT_PROBE_LIGHTS = 8
#: The map-free consistency samples ``samples // CONSISTENCY_SHARE`` texels ...
CONSISTENCY_SHARE = 4
#: ... each judged by up to COVERING_STEPS x COVERING_STEPS of the patches that cover it.
COVERING_STEPS = 4
#: Candidate offsets checked when estimating verbatim islands without a coordinate map.
MAX_VERBATIM_OFFSETS = 64
#: Histogram bins of the texture statistics (intensity and gradient magnitude).
STATISTICS_BINS = 32
#: Autocorrelation lags of the texture statistics: |dy|, |dx| up to this many texels.
AUTOCORRELATION_RADIUS = 8
#: Shuffled-block layouts whose sliced Wasserstein distances are averaged into the baseline.
BASELINE_LAYOUTS = 2


# ----------------------------------------------------------------------------------------------- relighting


def _zenith_view(stack: SampleStack) -> int:
    return int(np.argmax(stack.views[:, 2]))


def _relit_view(buffer: PerTexel) -> PerTexel:
    """A stack cut to the one view :func:`_relight` uses, so a multi-view capture is not replayed view by view."""
    if isinstance(buffer, SampleStack) and buffer.n_view > 1:
        v = _zenith_view(buffer)
        return dataclasses.replace(buffer, samples=buffer.samples[v:v + 1], views=buffer.views[v:v + 1])
    return buffer


def _relight(buffer: PerTexel, lights: np.ndarray, role: str) -> np.ndarray:
    """Linear radiance ``[L, H, W, C]`` float32 of ``buffer`` at ``lights`` (top view)."""
    if isinstance(buffer, SampleStack):
        cos_tol = np.cos(np.radians(LIGHT_MATCH_DEG))
        dots = lights.astype(np.float64) @ buffer.lights.astype(np.float64).T
        best = np.argmax(dots, axis=1)
        missing = np.flatnonzero(dots[np.arange(len(lights)), best] < cos_tol)
        if missing.size:
            i = int(missing[0])
            raise BtforgeInputError(
                f"score '{role}'",
                f"expected a stack with every light asked for, found {missing.size} of {len(lights)} missing "
                f"(first: light {i}, [{lights[i, 0]:.4f}, {lights[i, 1]:.4f}, {lights[i, 2]:.4f}])",
                "relight a model at these lights, score a model instead of a stack, or leave 'lights' out to use "
                "the exemplar stack's own lights")
        view = _zenith_view(buffer)
        frames = buffer.samples[view][best]
        if buffer.encoding != "linear":
            frames = SRGB8_TO_LINEAR[frames]
        return np.ascontiguousarray(frames, dtype=np.float32)
    if isinstance(buffer, ReflectanceModel):
        return np.ascontiguousarray(buffer.evaluate(lights)[0], dtype=np.float32)
    raise BtforgeInputError(f"score '{role}'",
                            f"expected a SampleStack or a ReflectanceModel, found {buffer.type_name}",
                            "score radiance stacks or fitted models; other per-texel data cannot be relit")


def _channels(buffer: PerTexel) -> tuple[str, ...]:
    return tuple(buffer.channels)


def _score_lights(output, exemplar, lights, paths) -> tuple[np.ndarray, str]:
    """The lights to relight at and where they came from."""
    if lights is not None:
        from btforge.plugins.relight import resolve_lights
        directions, _ = resolve_lights(lights, paths)
        return unit_directions("lights", directions, owner="synth.score"), "param"
    if isinstance(exemplar, SampleStack):
        return exemplar.lights, "exemplar"
    if isinstance(output, SampleStack):
        return output.lights, "output"
    from .features import probe_lights
    return probe_lights(DEFAULT_PROBE_LIGHTS), f"{DEFAULT_PROBE_LIGHTS} probe lights"


# ----------------------------------------------------------------------------------------------- patches


def _patch_source(image: np.ndarray, patch: int, wrap: bool) -> np.ndarray:
    """A ``[gh, gw, C, p, p]`` view of every patch; with ``wrap`` one patch per texel (periodic padding)."""
    if wrap:
        image = np.pad(image, ((0, patch - 1), (0, patch - 1), (0, 0)), mode="wrap")
    return sliding_window_view(image, (patch, patch), axis=(0, 1))


def _gather(view: np.ndarray, flat_index: np.ndarray) -> np.ndarray:
    """Patch vectors ``[n, C*p*p]`` float32 at flat grid indices of a patch view."""
    rows, cols = np.divmod(flat_index, view.shape[1])
    return view[rows, cols].reshape(len(flat_index), -1).astype(np.float32, copy=False)


def _pick(rng: np.random.Generator, n: int, cap: int) -> np.ndarray:
    """All of ``range(n)`` when ``n <= cap``, else ``cap`` distinct indices, sorted."""
    if n <= cap:
        return np.arange(n)
    return np.sort(rng.choice(n, cap, replace=False))


def _sorted_quantiles(sorted_values: np.ndarray, n: int) -> np.ndarray:
    """The empirical quantile function of sorted columns, evaluated at ``(k + 0.5) / n``, ``k < n``."""
    m = sorted_values.shape[0]
    if m == n:
        return sorted_values
    pos = np.clip((np.arange(n) + 0.5) / n * m - 0.5, 0, m - 1)
    lo = np.floor(pos).astype(np.int64)
    hi = np.minimum(lo + 1, m - 1)
    frac = (pos - lo).astype(np.float32)[:, None]
    return sorted_values[lo] * (1 - frac) + sorted_values[hi] * frac


def _sorted_projections(patches: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """``[n, projections]``: the patches projected on each unit direction, each column sorted."""
    return np.sort(patches @ directions.T, axis=0)


def _sliced_wasserstein(pa: np.ndarray, pb: np.ndarray) -> float:
    """Mean over directions of the 1-D Wasserstein-1 distance between two sets of sorted projections."""
    n = min(len(pa), len(pb))
    return float(np.mean(np.abs(_sorted_quantiles(pa, n) - _sorted_quantiles(pb, n))))


class _NearestPatches:
    """Nearest-neighbour search among patches: PCA-reduced k-d tree, candidates re-ranked exactly."""

    def __init__(self, patches: np.ndarray, basis: np.ndarray, mean: np.ndarray):
        from scipy.spatial import cKDTree
        self.patches = patches
        self.basis, self.mean = basis, mean
        self.tree = cKDTree((patches - mean) @ basis)

    def query(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Index into the indexed patches and RMS distance per element, for each query patch."""
        k = min(RERANK_K, len(self.patches))
        # each query is answered alone: the same lists on any number of workers
        _, cand = self.tree.query((queries - self.mean) @ self.basis, k=k, workers=cores())
        cand = cand.reshape(len(queries), k)
        diff = self.patches[cand] - queries[:, None, :]
        sq = np.einsum("nkd,nkd->nk", diff, diff)
        best = np.argmin(sq, axis=1)
        rows = np.arange(len(queries))
        return cand[rows, best], np.sqrt(sq[rows, best] / queries.shape[1])


def _pca_basis(sample: np.ndarray, dims: int) -> tuple[np.ndarray, np.ndarray]:
    mean = sample.mean(axis=0, dtype=np.float64)
    centred = sample.astype(np.float64) - mean
    _, vectors = np.linalg.eigh(centred.T @ centred)
    dims = min(dims, sample.shape[1])
    return vectors[:, ::-1][:, :dims].astype(np.float32), mean.astype(np.float32)


class _CrossLight:
    """Map-free consistency: under each light separately, which exemplar texel does each sampled texel show?

    Every texel is covered by ``patch x patch`` patches; a few of them (corners ``texel - shift``, up to
    COVERING_STEPS shifts per axis) are matched to their nearest exemplar patch, and the best-matching one
    decides: it puts exemplar texel ``match + shift`` under the texel.  A patch across a seam matches badly and
    loses to one inside the copied region, so the place is found wherever regions at least ``patch + 1`` texels
    wide are copied.
    """

    def __init__(self, texels: np.ndarray, patch: int, wrap: bool, size: tuple[int, int],
                 ex_size: tuple[int, int], n_light: int):
        h, w = size
        self.patch, self.wrap, self.texels = patch, wrap, texels
        self.grid = (h, w) if wrap else (h - patch + 1, w - patch + 1)
        self.ex_grid = (ex_size[0] - patch + 1, ex_size[1] - patch + 1)
        shifts = np.unique(np.round(np.linspace(0, patch - 1, min(patch, COVERING_STEPS))).astype(np.int64))
        pairs = np.stack(np.meshgrid(shifts, shifts, indexing="ij"), axis=-1).reshape(-1, 2)
        corners = texels[:, None, :] - pairs[None]                                   # [n, S, 2]
        if wrap:
            corners %= np.array([h, w])
            self.shift = np.broadcast_to(pairs, corners.shape)
        else:
            corners = np.clip(corners, 0, np.array(self.grid) - 1)
            self.shift = texels[:, None, :] - corners
        flat, inverse = np.unique(corners[..., 0] * self.grid[1] + corners[..., 1], return_inverse=True)
        self.cover_flat, self.cover_inverse = flat, inverse.reshape(corners.shape[:2])
        n = len(texels)
        self.places = np.empty((n_light, n, 2), np.int64)
        self.place_rms = np.empty((n_light, n), np.float32)
        self.place_patch = np.empty((n_light, n), np.int64)
        self.place_shift = np.empty((n_light, n, 2), np.int64)

    def add(self, light: int, ex_view: np.ndarray, out_view: np.ndarray, nearest: "_NearestPatches",
            tree_index: np.ndarray) -> None:
        found, dist = nearest.query(_gather(out_view, self.cover_flat))
        corner = np.stack(np.divmod(tree_index[found], ex_view.shape[1]), axis=1)[self.cover_inverse]
        err = dist[self.cover_inverse]
        rows = np.arange(len(self.texels))
        best = np.argmin(err, axis=1)
        self.place_shift[light] = self.shift[rows, best]
        self.places[light] = corner[rows, best] + self.place_shift[light]
        self.place_rms[light] = err[rows, best]
        self.place_patch[light] = self.cover_flat[self.cover_inverse[rows, best]]

    def agreement(self, ex_enc: np.ndarray, out_enc: np.ndarray, tolerance: float) -> float:
        """Share of texels whose places under all lights lie within 1 texel of their median place.

        Where a light's patch is ambiguous (flat, shadowed), the median place counts as agreeing when its patch
        explains that light's output patch as well as the best match did (within ``tolerance`` RMS).
        """
        centre = np.round(np.median(self.places, axis=0)).astype(np.int64)
        agree = np.abs(self.places - centre[None]).max(axis=2) <= 1                    # [L, n]
        for li in range(len(self.places)):
            todo = np.flatnonzero(~agree[li])
            corner = centre[todo] - self.place_shift[li, todo]
            inside = ((corner >= 0) & (corner < np.array(self.ex_grid))).all(axis=1)
            todo, corner = todo[inside], corner[inside]
            if not todo.size:
                continue
            a = _gather(_patch_source(ex_enc[li], self.patch, False), corner[:, 0] * self.ex_grid[1] + corner[:, 1])
            b = _gather(_patch_source(out_enc[li], self.patch, self.wrap), self.place_patch[li, todo])
            rms = np.sqrt(((a - b) ** 2).mean(axis=1))
            agree[li, todo] = rms <= self.place_rms[li, todo] + tolerance
        return float(agree.all(axis=0).mean())


# ----------------------------------------------------------------------------------------------- coords metrics


def _island_share(keys: np.ndarray, min_size: float) -> float:
    """Share of texels in 4-connected regions of equal ``keys`` with more than ``min_size`` texels."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    h, w = keys.shape
    index = np.arange(h * w).reshape(h, w)
    same_x = keys[:, 1:] == keys[:, :-1]
    same_y = keys[1:] == keys[:-1]
    a = np.concatenate([index[:, :-1][same_x], index[:-1][same_y]])
    b = np.concatenate([index[:, 1:][same_x], index[1:][same_y]])
    graph = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(h * w, h * w))
    _, labels = connected_components(graph, directed=False)
    sizes = np.bincount(labels)
    return float(sizes[sizes > min_size].sum() / (h * w))


def _verbatim_from_matches(out_enc, ex_enc, positions, matched, exact, min_size, tolerance, n_grid) -> float:
    """Verbatim share without a map: offsets found by exact patch matches, verified texel by texel."""
    from scipy.ndimage import label
    _, h, w, _ = out_enc.shape
    _, eh, ew, _ = ex_enc.shape
    if not exact.any():
        return 0.0
    offsets = matched[exact] - positions[exact]
    unique, counts = np.unique(offsets, axis=0, return_counts=True)
    # An island above min_size texels holds about min_size * density samples; keep offsets seen often enough.
    expected = min_size * len(positions) / max(n_grid, 1)
    keep = counts >= max(2.0, 0.25 * expected) if expected >= 2 else counts >= 1
    unique, counts = unique[keep], counts[keep]
    order = np.argsort(-counts, kind="stable")[:MAX_VERBATIM_OFFSETS]
    covered = np.zeros((h, w), bool)
    for dr, dc in unique[order]:
        r0, r1 = max(0, -dr), min(h, eh - dr)
        c0, c1 = max(0, -dc), min(w, ew - dc)
        if r1 <= r0 or c1 <= c0:
            continue
        a = out_enc[:, r0:r1, c0:c1]
        b = ex_enc[:, r0 + dr:r1 + dr, c0 + dc:c1 + dc]
        same = (np.abs(a - b).max(axis=(0, 3)) <= tolerance)
        labels, n = label(same)
        if n == 0:
            continue
        sizes = np.bincount(labels.reshape(-1))
        sizes[0] = 0
        big = sizes > min_size
        covered[r0:r1, c0:c1] |= big[labels]
    return float(covered.mean())


# ----------------------------------------------------------------------------------------------- texture statistics


@dataclasses.dataclass(frozen=True)
class TextureStatistics:
    """First- and second-order statistics of one grey image: what a texture "looks like" regardless of layout."""

    intensity: np.ndarray        # [B] histogram of intensities (sums to 1)
    gradient: np.ndarray         # [B] histogram of forward-difference gradient magnitudes (sums to 1)
    autocorrelation: np.ndarray  # [(R + 1) (2R + 1) - R - 1] normalised autocorrelation at lags (dy >= 0), lag 0 left out


def texture_statistics(image: np.ndarray, intensity_edges: np.ndarray, gradient_edges: np.ndarray,
                       wrap: bool = False) -> TextureStatistics:
    """Statistics of ``[H, W]`` values: histograms over the given bin edges (values beyond them fall into the end
    bins) and the autocorrelation up to :data:`AUTOCORRELATION_RADIUS`, divided by the variance (1 at lag 0; a
    flat image has 0 at every lag).  ``wrap``: gradients and correlations continue across the edges."""
    x = np.asarray(image, np.float64)
    h, w = x.shape
    if wrap:
        gy, gx = np.roll(x, -1, axis=0) - x, np.roll(x, -1, axis=1) - x
        gradient = np.hypot(gy, gx).ravel()
    else:
        gradient = np.hypot(np.diff(x, axis=0)[:, :-1], np.diff(x, axis=1)[:-1]).ravel()

    def histogram(values, edges):
        counts, _ = np.histogram(np.clip(values, edges[0], edges[-1]), bins=edges)
        return counts / max(1, counts.sum())

    r = min(AUTOCORRELATION_RADIUS, h - 1, w - 1)
    centred = x - x.mean()
    shape = (h, w) if wrap else (h + r, w + r)
    spectrum = np.fft.rfft2(centred, shape)
    correlation = np.fft.irfft2(spectrum * np.conj(spectrum), shape)
    dy, dx = np.mgrid[0:r + 1, -r:r + 1]
    keep = (dy > 0) | (dx > 0)
    dy, dx = dy[keep], dx[keep]
    pairs = np.full(dy.shape, h * w, np.float64) if wrap else (h - dy) * (w - np.abs(dx)).astype(np.float64)
    variance = float((centred ** 2).mean())
    values = correlation[dy % shape[0], dx % shape[1]] / pairs
    auto = values / variance if variance > 1e-12 else np.zeros_like(values)
    if r < AUTOCORRELATION_RADIUS:  # a tiny image: the lags it lacks count as uncorrelated
        full = (AUTOCORRELATION_RADIUS + 1) * (2 * AUTOCORRELATION_RADIUS + 1) - AUTOCORRELATION_RADIUS - 1
        auto = np.concatenate([auto, np.zeros(full - len(auto))])
    return TextureStatistics(histogram(x.ravel(), intensity_edges), histogram(gradient, gradient_edges), auto)


def statistics_distance(a: TextureStatistics, b: TextureStatistics) -> float:
    """Total-variation distances of the two histograms plus the RMS difference of the autocorrelations."""
    tv = 0.5 * (np.abs(a.intensity - b.intensity).sum() + np.abs(a.gradient - b.gradient).sum())
    return float(tv + np.sqrt(np.mean((a.autocorrelation - b.autocorrelation) ** 2)))


def texture_statistics_ratio(out_enc: np.ndarray, ex_enc: np.ndarray, wrap: bool) -> tuple[float, float]:
    """The output-exemplar distance of texture statistics over the exemplar's own (its halves' distance),
    averaged over lights; ``(ratio, halves' distance)``.  1 = as close to the exemplar as it is to itself.

    Images are ``[L, H, W, C]`` in the score's domain; the statistics are of the channel mean.  Bin edges come
    from the exemplar under each light (intensity: its range; gradient: up to twice its 99th percentile).  The
    halves are the left/right and the top/bottom halves of the exemplar, averaged.
    """
    ratios_out, ratios_self = [], []
    for ex, out in zip(ex_enc.mean(axis=3), out_enc.mean(axis=3)):
        low, high = float(ex.min()), float(ex.max())
        intensity_edges = np.linspace(low, high if high > low else low + 1.0, STATISTICS_BINS + 1)
        grad = np.hypot(np.diff(ex, axis=0)[:, :-1], np.diff(ex, axis=1)[:-1])
        top = 2.0 * float(np.percentile(grad, 99)) if grad.size else 0.0
        gradient_edges = np.linspace(0.0, top if top > 0 else 1.0, STATISTICS_BINS + 1)

        def stats(image, image_wrap=False):
            return texture_statistics(image, intensity_edges, gradient_edges, image_wrap)

        h, w = ex.shape
        halves = [(ex[:, :w // 2], ex[:, w // 2:]), (ex[:h // 2], ex[h // 2:])]
        ratios_self.append(np.mean([statistics_distance(stats(a), stats(b)) for a, b in halves]))
        ratios_out.append(statistics_distance(stats(out, wrap), stats(ex)))
    own, distance = float(np.mean(ratios_self)), float(np.mean(ratios_out))
    if own > 0:
        return distance / own, own
    return (0.0 if distance == 0 else float("inf")), own  # a texture-less exemplar: only itself matches it


@dataclasses.dataclass(frozen=True)
class PatchMatches:
    """Nearest-patch metrics of one comparison, and the matches the map-free estimates are built from."""

    coherence: float            # mean RMS distance of sampled output patches to their nearest exemplar patch
    completeness: float         # mean RMS distance of sampled exemplar patches to their nearest output patch
    matched: np.ndarray         # [L, S, 2] exemplar patch position matched to each sampled output patch
    match_rms: np.ndarray       # [L, S] its RMS distance
    out_positions: np.ndarray   # [S, 2] the sampled output patches' positions
    n_out_grid: int             # output patch positions
    consistency_matched: float  # the map-free cross-light consistency


def nearest_patch_metrics(ex_enc: np.ndarray, out_enc: np.ndarray, *, patch: int, match_patch: int, samples: int,
                          seed: int, wrap: bool, tolerance: float) -> PatchMatches:
    """Coherence and completeness (nearest patches both ways) per light, with the cross-light matches."""
    n_light, eh, ew, _ = ex_enc.shape
    _, h, w, _ = out_enc.shape
    rng = np.random.default_rng([seed, 2])
    ex_views = [_patch_source(im, patch, False) for im in ex_enc]
    out_views = [_patch_source(im, patch, wrap) for im in out_enc]
    ex_grid_w, out_grid_h, out_grid_w = ex_views[0].shape[1], out_views[0].shape[0], out_views[0].shape[1]
    n_ex_grid = ex_views[0].shape[0] * ex_grid_w
    n_out_grid = out_grid_h * out_grid_w
    ex_tree_idx = _pick(rng, n_ex_grid, TREE_CAP)
    out_tree_idx = _pick(rng, n_out_grid, TREE_CAP)
    out_query = _pick(rng, n_out_grid, samples)
    ex_query = _pick(rng, n_ex_grid, samples)
    # Texels for the map-free consistency, each judged by the exemplar patches that best explain it.
    texels = np.stack(np.divmod(_pick(rng, h * w, max(16, samples // CONSISTENCY_SHARE)), w), axis=1)
    cross = _CrossLight(texels, match_patch, wrap, (h, w), (eh, ew), n_light)
    if match_patch != patch:
        m_ex_grid = (eh - match_patch + 1) * (ew - match_patch + 1)
        m_tree_idx = _pick(rng, m_ex_grid, TREE_CAP)
        m_sample = _pick(rng, m_ex_grid, samples)

    coherence, completeness = [], []
    matched = np.empty((n_light, len(out_query), 2), np.int64)
    match_rms = np.empty((n_light, len(out_query)), np.float32)
    for li in range(n_light):
        ex_tree_patches = _gather(ex_views[li], ex_tree_idx)
        out_q = _gather(out_views[li], out_query)
        ex_q = _gather(ex_views[li], ex_query)
        basis, mean = _pca_basis(np.concatenate([out_q, ex_q]), PCA_DIMS)
        to_exemplar = _NearestPatches(ex_tree_patches, basis, mean)
        found, dist = to_exemplar.query(out_q)
        coherence.append(float(dist.mean()))
        matched[li] = np.stack(np.divmod(ex_tree_idx[found], ex_grid_w), axis=1)
        match_rms[li] = dist
        _, dist = _NearestPatches(_gather(out_views[li], out_tree_idx), basis, mean).query(ex_q)
        completeness.append(float(dist.mean()))
        if match_patch == patch:
            cross.add(li, ex_views[li], out_views[li], to_exemplar, ex_tree_idx)
        else:
            m_ex = _patch_source(ex_enc[li], match_patch, False)
            m_out = _patch_source(out_enc[li], match_patch, wrap)
            m_basis, m_mean = _pca_basis(_gather(m_ex, m_sample), PCA_DIMS)
            cross.add(li, m_ex, m_out, _NearestPatches(_gather(m_ex, m_tree_idx), m_basis, m_mean), m_tree_idx)
    out_positions = np.stack(np.divmod(out_query, out_grid_w), axis=1)
    return PatchMatches(float(np.mean(coherence)), float(np.mean(completeness)), matched, match_rms, out_positions,
                        n_out_grid, cross.agreement(ex_enc, out_enc, tolerance))


def sliced_wasserstein_levels(ex_enc: np.ndarray, out_enc: np.ndarray, *, patch: int, scales: int,
                              projections: int, seed: int, wrap: bool) -> list[float]:
    """The sliced Wasserstein distance of patch distributions per Gaussian-pyramid level, averaged over lights
    (levels too small for a patch are left out)."""
    return sliced_wasserstein_of_outputs(ex_enc, [(out_enc, wrap)], patch=patch, scales=scales,
                                         projections=projections, seed=seed)[0]


def sliced_wasserstein_of_outputs(ex_enc: np.ndarray, outputs: list[tuple[np.ndarray, bool]], *, patch: int,
                                  scales: int, projections: int, seed: int) -> list[list[float]]:
    """:func:`sliced_wasserstein_levels` of several outputs (``(out_enc [L, H, W, C], wrap)`` each: the output and
    the shuffled-block baselines) against one exemplar.  Per level the exemplar's directions and sample are drawn
    once, and per light its projections are sorted once and serve every output before the next light's are made
    (a few MB alive at a time).  Each output draws its sample from the random state that follows the exemplar's,
    as it would alone, so every figure is the one a call of its own gives."""
    swd_levels: list[list[float]] = [[] for _ in outputs]
    ex_level = list(ex_enc)
    out_levels = [list(out_enc) for out_enc, _ in outputs]
    live = list(range(len(outputs)))            # the outputs still large enough for a patch
    for level in range(scales):
        if level:
            ex_level = [downsample(im, "reflect") for im in ex_level]
            for i in live:
                out_levels[i] = [downsample(im, "wrap" if outputs[i][1] else "reflect") for im in out_levels[i]]
        live = [i for i in live if min(out_levels[i][0].shape[:2]) >= patch]
        if min(ex_level[0].shape[:2]) < patch or not live:
            break
        rng = np.random.default_rng([seed, 1, level])
        directions = rng.standard_normal((projections, ex_level[0].shape[2] * patch * patch)).astype(np.float32)
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        ex_views = [_patch_source(im, patch, False) for im in ex_level]
        ex_pick = _pick(rng, ex_views[0].shape[0] * ex_views[0].shape[1], SWD_PATCH_CAP)
        after_exemplar = rng.bit_generator.state
        views, picks = {}, {}
        for i in live:
            out_rng = np.random.default_rng()
            out_rng.bit_generator.state = after_exemplar
            views[i] = [_patch_source(im, patch, outputs[i][1]) for im in out_levels[i]]
            picks[i] = _pick(out_rng, views[i][0].shape[0] * views[i][0].shape[1], SWD_PATCH_CAP)
        per_light = {i: [] for i in live}
        for light, ex_view in enumerate(ex_views):
            ex_sorted = _sorted_projections(_gather(ex_view, ex_pick), directions)
            for i in live:
                out_sorted = _sorted_projections(_gather(views[i][light], picks[i]), directions)
                per_light[i].append(_sliced_wasserstein(out_sorted, ex_sorted))
        for i in live:
            swd_levels[i].append(float(np.mean(per_light[i])))
    return swd_levels


def seam_ratio_of(out_enc: np.ndarray, block: int, coords: CoordMap | None, wrap: bool) -> tuple[float | None, list[str]]:
    """Mean gradient across the known boundaries over the mean gradient elsewhere, and where the boundaries came
    from (None when no boundary is known)."""
    masks = _seam_masks(out_enc.shape[1], out_enc.shape[2], block, coords)
    n_light = out_enc.shape[0]
    gx = np.linalg.norm(np.diff(out_enc, axis=2), axis=3)  # [L, H, W-1]
    gy = np.linalg.norm(np.diff(out_enc, axis=1), axis=3)  # [L, H-1, W]
    seam_sum, seam_n, rest_sum, rest_n = 0.0, 0, 0.0, 0
    seam_source = []
    if masks is not None:
        sx, sy, seam_source = masks[0], masks[1], [masks[2]]
        for g, m in ((gx, sx), (gy, sy)):
            seam_sum += float(g[:, m].sum())
            seam_n += int(m.sum()) * n_light
            rest_sum += float(g[:, ~m].sum())
            rest_n += int((~m).sum()) * n_light
    else:
        rest_sum = float(gx.sum() + gy.sum())
        rest_n = gx.size + gy.size
    if wrap:
        wx = np.linalg.norm(out_enc[:, :, 0] - out_enc[:, :, -1], axis=-1)
        wy = np.linalg.norm(out_enc[:, 0] - out_enc[:, -1], axis=-1)
        seam_sum += float(wx.sum() + wy.sum())
        seam_n += wx.size + wy.size
        seam_source.append("wrap")
    if seam_n and rest_n and rest_sum > 0:
        return (seam_sum / seam_n) / (rest_sum / rest_n), seam_source
    return None, seam_source


def verbatim_share_of_map(coords: CoordMap, min_island: float) -> float:
    """Share of output texels in 4-connected regions of constant source offset larger than ``min_island``."""
    h, w = coords.height, coords.width
    ew = coords.source_size[1]
    src = visibility.dominant_source(coords)
    rows, cols = np.mgrid[0:h, 0:w]
    keys = (src[..., 0] - rows + h) * (2 * w + ew + 1) + (src[..., 1] - cols + w)
    return _island_share(keys, min_island)


def _seam_masks(h: int, w: int, block: int, coords: CoordMap | None) -> tuple[np.ndarray, np.ndarray, str] | None:
    """Masks of texel pairs ``(j, j+1)`` across a boundary: ``[H, W-1]`` horizontal, ``[H-1, W]`` vertical."""
    if block > 0:
        sx = np.broadcast_to(((np.arange(w - 1) + 1) % block == 0)[None, :], (h, w - 1))
        sy = np.broadcast_to(((np.arange(h - 1) + 1) % block == 0)[:, None], (h - 1, w))
        return sx, sy, "block grid"
    if coords is not None:
        c = coords.coords.astype(np.int64)
        sx = (c[:, 1:, 0] != c[:, :-1, 0]) | (c[:, 1:, 1] != c[:, :-1, 1] + 1)
        sy = (c[1:, :, 0] != c[:-1, :, 0] + 1) | (c[1:, :, 1] != c[:-1, :, 1])
        return sx, sy, "coords"
    return None


# ----------------------------------------------------------------------------------------------- the stage


@declare_stage(
    "synth.score", deprecated_names=("score",),
    inputs={"output": "PerTexel", "exemplar": "PerTexel", "coords": "CoordMap", "tiles": "Buffer"},
    optional_inputs=("output", "coords", "tiles"),
    outputs={"scores": "Scores"},
    params=[
        Param("lights", "lights", None, "lights to compare at, as [[x, y, z], ...] or a .lp file; leave out to use "
              "the exemplar stack's lights (else the output stack's, else 8 lights spread over the hemisphere)"),
        Param("patch", "int", 7, "patch size in texels for every patch metric", low=1, high=63),
        Param("scales", "int", 3, "levels of the Gaussian pyramid for the sliced Wasserstein distance", low=1, high=10),
        Param("seed", "int", 0, "seed of the random projections and patch samples", low=0),
        Param("block", "int", 0, "the synthesizer's block step in texels: seams are measured between texels j - 1 "
              "and j for every multiple j of it (for quilt: block - overlap, where each block's overlap begins; cut "
              "seams wander inside the overlap, so this is approximate).  0 = unknown: seams are where the map "
              "wired to 'coords' jumps, which is the accurate option", low=0),
        Param("wrap", "bool", None, "the output is meant to tile: its wrap-around boundary counts as a seam and its "
              "patches wrap around; left out: the wrap of the map wired to 'coords' (false without one)"),
        Param("domain", "choice", "srgb", "where images are compared after exposure normalisation: sRGB-encoded or "
              "log2 radiance (both about [0, 1])", choices=("srgb", "log")),
        Param("projections", "int", 64, "random projections of the sliced Wasserstein distance", low=1, high=4096),
        Param("samples", "int", 2048, "output and exemplar patches sampled for coherence, completeness and the "
              "map-free consistency and verbatim estimates", low=16),
        Param("consistency_patch", "int", 0, "patch size of the map-free consistency; 0 = 'patch'.  It finds "
              "where copied regions at least this + 1 texels wide come from: lower it (e.g. 3) for synthesizers "
              "that copy smaller pieces", low=0, high=63),
        Param("tolerance", "float", 0.01, "largest difference (in domain units) still counted as an exact copy",
              low=0.0),
        Param("verbatim_area", "float", 0.25, "a copied island counts as verbatim when larger than this fraction of "
              "the exemplar's area", low=0.0),
        Param("consistency_threshold", "float", 0.8, "'consistent' is true when consistency reaches this", low=0.0,
              high=1.0),
    ],
)
def score(ctx, exemplar, output=None, coords=None, tiles=None, *, lights, patch, scales, seed, block, wrap, domain,
          projections, samples, consistency_patch, tolerance, verbatim_area, consistency_threshold):
    """Measure synthesis quality: patch statistics, copying, seams and cross-light consistency.

    Both textures are relit at each light (a stack must hold the lights asked for, and its view nearest the
    zenith is used; a model is evaluated for the top view) and compared image by image.  Each light is exposed
    so that the exemplar's 99.5th percentile maps to 1; the values are then sRGB-encoded (not clipped above 1)
    or, with ``domain: log``, mapped by ``log2(x + 2^-8) / 8 + 1``.  Distances below are in these units (about
    [0, 1]).

    Inputs
    ------
    output : PerTexel, optional
        The synthesized texture: a SampleStack or any ReflectanceModel.  Needed unless ``tiles`` is wired.
    exemplar : PerTexel
        The texture it was synthesized from, with the same number of channels.
    coords : CoordMap, optional
        The synthesis result that produced ``output``; makes the verbatim share, the seams and the consistency
        exact instead of estimated.  In tile-set mode, a layout of ``tiles`` (a tiling of it), also measured.
    tiles : Buffer, optional
        Tile-set mode: a set of pieces that textures are laid out from, measured by its class's own
        ``seam_scores(exemplar, coords)`` (a Wang-tile set: seam ratios over every valid adjacency and 2 x 2
        corner configuration, BTFel statistics, and for a tiling wired to ``coords`` its colour mismatches, tile
        use and periodicity).  Those figures join the scores; without ``output`` they are the scores.

    Outputs
    -------
    scores : Scores
        ``swd``
            Sliced Wasserstein distance between the distributions of ``patch x patch x C`` patches (``projections``
            random unit directions fixed by ``seed``; sorted projections give the 1-D Wasserstein-1 distance by
            quantile matching), averaged over directions, over ``scales`` Gaussian-pyramid levels (``swd_0`` ...
            per level, up to 16384 sampled patches per image and level) and over lights.  Lower is better.
        ``texture_statistics``
            Distance of texture statistics between output and exemplar divided by the same distance between the
            exemplar's own halves (left/right and top/bottom, averaged), averaged over lights: 1 means the output
            is as close to the exemplar as the exemplar is to itself, lower is better.  Statistics of the
            channel mean per light: histograms of intensity and of gradient magnitude (32 bins over the
            exemplar's range; total-variation distance) and the normalised autocorrelation up to 8 texels of
            lag (RMS difference).  ``texture_statistics_self`` is the halves' distance.
        ``coherence``
            Mean over sampled output patches of the RMS difference to the nearest exemplar patch (does every
            part of the output look like some part of the exemplar?).  Lower is better.
        ``completeness``
            Mean over sampled exemplar patches of the RMS difference to the nearest output patch (does the output
            show everything the exemplar has?).  Lower is better.  Nearest neighbours: patches reduced to 16
            PCA dimensions, 4 candidates from a k-d tree, re-ranked by exact distance; a tree holds at most
            65536 patches (a random subset of a larger image, which makes the figures slight overestimates).
        ``verbatim_share``
            Share of output texels inside copied islands larger than ``verbatim_area`` x the exemplar area (by
            default a quarter of it).  With ``coords``: 4-connected regions where the source offset ``coords -
            position`` is constant (a blended texel counts with its heavier source).  Without: offsets of exact
            patch matches (RMS within ``tolerance`` under every light), each verified texel by texel and split
            into connected regions.
        ``seam_ratio``
            Mean gradient magnitude (forward difference, colour norm) across boundaries divided by the mean
            gradient between all other neighbouring texels, both averaged over lights; 1 means invisible
            seams.  Boundaries are every ``block`` texels (the block step: ``block - overlap`` for ``synth.quilt``),
            else where ``coords`` is discontinuous (the seams exactly), plus the last-to-first row and column
            when ``wrap`` (by default the map's own); empty (no value) when none of these is known.  It is
            measured against the output's own texture, not the exemplar's, so it is not ``seam_visibility``.
        ``seam_visibility``
            With ``coords``: the mean radiance jump (colour norm, averaged over lights) between adjacent output
            texels whose sources are not adjacent in the exemplar (a blended texel counts with its heavier
            source; with a wrapping map the wrap-around pairs too), over the mean jump between adjacent exemplar
            texels.  1 = seams are as visible as the exemplar's own texel-to-texel changes; above about 1.3
            they show.  ``seam_edge_share`` is the share of output neighbour pairs that are seams.
        ``straight_seam_visibility`` and ``straight_seam_share``
            The same over the seam edges lying in straight runs of 12 or more texels (the edges of copied
            blocks, which the eye picks out first), and their share of the seam edges.  A tiling's tile
            borders (the map's ``tile``) are straight by design and left out.  Empty when no seam is straight.
        ``straight_step_visibility``
            With ``coords``: brightness steps along the straight edges between copied pieces, at a coarser scale
            than seams (a refinement that breaks a piece's edge into many small seams hides a step there from
            the per-edge figures, not from the eye).  Pieces of 64 texels or more copied as one; every other
            texel joins its nearest such piece.  Lines are axis-aligned segments of 32 texels with a band 4
            texels wide on each side, 2 texels away; a line counts where 3/4 of it crosses an edge between those
            pieces within 2 texels.  A line's step is the difference of the band means (colour) that holds along
            all four quarters of the segment, over the bands' own spread (+ 0.02), averaged over lights.  The
            figure is the mean step over the counted lines over the mean step the exemplar has at their texels'
            sources: 1 = the steps along the pieces' straight edges are those of the copied content; above
            about 1.3 straight edges between pieces show.  Empty when no line counts.
        ``evenness``
            With ``coords``: ``exp(entropy) / n`` of the output's use of the exemplar's ``n`` cells of about
            8 x 8 texels (blended texels count for both sources, by weight).  1 = every cell used equally; an
            output that collapses onto a few exemplar regions scores low, a constant-source map ``1 / n``.
        ``lattice_share``
            With ``coords`` that lay tiles (a ``wang.tiling``; the map's ``tile``): the share of the output's
            variance that sits at the same place in every whole tile, averaged over lights (one-way analysis of
            variance with the tile's places as groups, less what chance leaves in the mean of that many tiles),
            or the same share of its local contrast standardised per tile, whichever is larger.  0 = the tiles'
            content is placed independently of the lattice (a quilted output read as 16 tiles scores about 0);
            1 = every tile is the same.  What the eye sees as a lattice: the same band along every tile border,
            the same feature at every corner, pieces whose outlines lie at the same place in every tile whatever
            their colours, tiles repeated.  Empty for other maps.
        ``swd_vs_shuffled_blocks``
            ``swd`` over ``swd_shuffled_blocks``: the same distance for exemplar blocks of
            ``shuffled_block_side`` texels (32, at most half the exemplar's side) laid at random at the output's
            size, replayed and relit like the output (mean of 2 layouts).  Below 1 the synthesis reproduces the
            exemplar's patch statistics better than random blocks do.
        ``consistency`` and ``consistent``
            Whether each output texel comes from the same exemplar place under every light.  With ``coords``:
            the share of texels equal (within ``tolerance``, under every light) to what the map names, i.e. to
            the exemplar replayed through the map as ``synth.materialize`` replays it (blends included), then relit.
            Without: for sampled output texels
            (``samples / 4``), under each light separately, up to 16 of the ``consistency_patch``-sized patches
            covering the texel are matched to their nearest exemplar patch and the best-matching one names the
            exemplar texel under it; a texel is consistent when the places named under all lights lie within
            1 texel (Chebyshev) of their median, or where they do not, the median place explains that light's
            patch as well as its own best match (within ``tolerance``: flat or shadowed patches are ambiguous).
            A synthesis of reflectance functions (one map replayed) scores near 1, independent per-light 2D
            syntheses near 0.  Copied pieces narrower than ``consistency_patch + 1`` texels cannot be traced
            (they score low even when consistent): lower ``consistency_patch`` for such synthesizers, or wire
            the map.  ``consistent`` is ``consistency >= consistency_threshold`` (0.8 by default);
            ``consistency_matched`` always holds the map-free estimate.
        ``swd_0`` ..., ``scales_used``, ``lights``, ``lights_source``, ``domain``, ``wrap``, ``*_method``,
        ``seam_source``
            How the figures were found.

    Costs: a 256 x 256 output against a 128 x 128 exemplar at 8 lights scores in about 3 s (plus about 1 s for
    the shuffled-block baseline) (measured with one
    BLAS thread on a shared 2-core CPU).

    Everything is also noted in the run report, with the lights, the domain and how each figure was found.
    """
    layout = capability(tiles, "seam_scores", "seam scores: it is not a set of pieces that textures are laid out "
                        "from", "wire a tile set to 'tiles'")(exemplar, coords) if tiles is not None else {}
    if output is None:
        if tiles is None:
            raise BtforgeInputError("synth.score", "expected 'output' (a synthesized texture) or 'tiles' (a tile set) "
                                    "wired, found neither", "wire the texture to measure to 'output', or a tile "
                                    "set to 'tiles'")
        return _noted(ctx, layout)
    if wrap is None:
        wrap = bool(coords.wrap) if coords is not None else False
    _check_channels(ctx, output, exemplar)
    lights_used, lights_source = _score_lights(output, exemplar, lights, ctx.paths)
    ex_lin = _relight(exemplar, lights_used, "exemplar")
    out_lin = _relight(output, lights_used, "output")
    _check_sizes(ex_lin.shape[1:3], out_lin.shape[1:3], coords, patch, consistency_patch or patch)
    whites = white_points(ex_lin)
    ex_enc = encoded(ex_lin, whites, domain)
    out_enc = encoded(out_lin, whites, domain)
    relit = _Relit(exemplar, lights_used, whites, domain, ex_enc, out_enc)

    swd_per_level, baseline = _swd_with_baseline(relit, wrap, patch=patch, scales=scales, projections=projections,
                                                 seed=seed)
    found = nearest_patch_metrics(ex_enc, out_enc, patch=patch, match_patch=consistency_patch or patch,
                                  samples=samples, seed=seed, wrap=wrap, tolerance=tolerance)
    if ex_enc.shape[0] < 2:
        ctx.warn("consistency across lights needs at least 2 lights; with one it is trivially 1")
    seam_ratio, seam_source = seam_ratio_of(out_enc, block, coords, wrap)
    statistics_ratio, statistics_self = texture_statistics_ratio(out_enc, ex_enc, wrap)
    swd = float(np.mean(swd_per_level))
    values = {
        "swd": swd,
        "texture_statistics": statistics_ratio,
        "texture_statistics_self": statistics_self,
        **{f"swd_{i}": v for i, v in enumerate(swd_per_level)},
        "coherence": found.coherence,
        "completeness": found.completeness,
        **_verbatim(relit, coords, found, verbatim_area * ex_enc.shape[1] * ex_enc.shape[2], tolerance),
        "seam_ratio": seam_ratio,
        "seam_source": " + ".join(seam_source) if seam_source else "none",
        **_eye_measures(relit, coords),
        **baseline,
        **_consistency(relit, coords, found, tolerance, consistency_threshold),
        "lights": ex_enc.shape[0],
        "lights_source": lights_source,
        "domain": domain,
        "wrap": bool(wrap),
        "scales_used": len(swd_per_level),
        "sampled_patches": int(len(found.out_positions)),
        **layout,
    }
    return _noted(ctx, values)


@dataclasses.dataclass(frozen=True)
class _Relit:
    """Both textures relit and encoded, and what is needed to relight anything else the same way."""

    exemplar: PerTexel
    lights: np.ndarray
    whites: np.ndarray
    domain: str
    ex_enc: np.ndarray
    out_enc: np.ndarray

    def replay(self, coords: CoordMap) -> np.ndarray:
        """The exemplar replayed through ``coords`` as ``synth.materialize`` replays it (blended records, then
        relit), encoded: blending relit radiance instead differs wherever evaluation is not linear in the
        records (clamps, sRGB codes, sRGB-space PTMs)."""
        replayed = coords.apply(_relit_view(self.exemplar))
        return encoded(_relight(replayed, self.lights, "exemplar"), self.whites, self.domain)


def _check_channels(ctx, output: PerTexel, exemplar: PerTexel) -> None:
    n_channel, out_channel = len(_channels(exemplar)), len(_channels(output))
    if out_channel != n_channel:
        raise BtforgeInputError("synth.score", f"expected output and exemplar with the same channels, found {out_channel} "
                                f"({', '.join(_channels(output))}) and {n_channel} ({', '.join(_channels(exemplar))})",
                                "score textures of the same colour space")
    if _channels(output) != _channels(exemplar):
        ctx.warn(f"channel names differ: {_channels(output)} vs {_channels(exemplar)}; compared in order")


def _check_sizes(ex_size, out_size, coords: CoordMap | None, patch: int, match_patch: int) -> None:
    """Every problem with the sizes at once: textures smaller than a patch, a map of another size."""
    problems = []
    for role, (hh, ww) in (("output", out_size), ("exemplar", ex_size)):
        for size, what, hint in ((patch, "the patch size", "lower 'patch'"),
                                 (match_patch, "the consistency patch size", "lower 'consistency_patch'")):
            if min(hh, ww) < size:
                problems.append((f"score '{role}'", f"expected at least {size} x {size} texels ({what}), found "
                                 f"{hh} x {ww}", hint))
    if coords is not None:
        (eh, ew), (h, w) = ex_size, out_size
        if coords.source_size != (eh, ew):
            problems.append(("score 'coords'", f"expected a map into the {eh} x {ew} exemplar, found one into "
                             f"{coords.source_size[0]} x {coords.source_size[1]}",
                             "wire the exemplar the map was synthesized from (the synthesizer's input)"))
        if (coords.height, coords.width) != (h, w):
            problems.append(("score 'coords'", f"expected a map of the output's size {h} x {w}, found "
                             f"{coords.height} x {coords.width}", "wire the map whose materialized result is 'output'"))
    if problems:
        where = "; ".join(p[0] for p in problems)
        raise BtforgeInputError(where if len(problems) > 1 else problems[0][0],
                                "; ".join(p[1] for p in problems), "; ".join(dict.fromkeys(p[2] for p in problems)))


def _consistency(relit: _Relit, coords, found: "PatchMatches", tolerance: float, threshold: float) -> dict:
    """Cross-light consistency: exact through the map when there is one, else the map-free estimate."""
    if coords is not None:
        replay_enc = relit.replay(coords)
        consistency = float((np.abs(relit.out_enc - replay_enc).max(axis=(0, 3)) <= tolerance).mean())
        method = "coords"
    else:
        consistency, method = found.consistency_matched, "patch matches"
    return {"consistency": consistency, "consistent": bool(consistency >= threshold), "consistency_method": method,
            "consistency_matched": found.consistency_matched}


def _verbatim(relit: _Relit, coords, found: "PatchMatches", min_island: float, tolerance: float) -> dict:
    """Share of the output copied in islands larger than ``min_island`` texels, and how it was found."""
    if coords is not None:
        return {"verbatim_share": verbatim_share_of_map(coords, min_island), "verbatim_method": "coords"}
    matched, match_rms = found.matched, found.match_rms
    exact = (match_rms <= tolerance).all(axis=0) & (np.abs(matched - matched[:1]).max(axis=(0, 2)) == 0)
    share = _verbatim_from_matches(relit.out_enc, relit.ex_enc, found.out_positions, matched[0], exact, min_island,
                                   tolerance, found.n_out_grid)
    return {"verbatim_share": share, "verbatim_method": "patch matches"}


def _eye_measures(relit: _Relit, coords: CoordMap | None) -> dict:
    """Seam, straight-seam and straight-step visibility, evenness and a tiling's lattice share, read from the map
    (None without one)."""
    if coords is None:
        return {"seam_visibility": None, "straight_seam_visibility": None, "straight_seam_share": None,
                "seam_edge_share": None, "straight_step_visibility": None, "evenness": None, "lattice_share": None}
    seen = visibility.seam_visibility(relit.out_enc, relit.ex_enc, coords)
    return {"seam_visibility": seen.seam_visibility, "straight_seam_visibility": seen.straight_seam_visibility,
            "straight_seam_share": seen.straight_seam_share, "seam_edge_share": seen.seam_edge_share,
            "straight_step_visibility": straight_step_visibility(relit.out_enc, relit.ex_enc, coords),
            "evenness": visibility.evenness(coords),
            "lattice_share": visibility.lattice_share(relit.out_enc, int(coords.tile or 0))}


def _swd_with_baseline(relit: _Relit, wrap: bool, *, patch: int, scales: int, projections: int,
                       seed: int) -> tuple[list[float], dict]:
    """The output's sliced Wasserstein distance per level, and the figures of the shuffled-block baseline: the
    same distance for exemplar blocks laid out at the output's size (mean of :data:`BASELINE_LAYOUTS` layouts,
    replayed and relit like the output, with the same projections and exemplar sample), and the output's
    distance over it."""
    ex_enc = relit.ex_enc
    block = visibility.baseline_block(ex_enc.shape[1:3])
    layouts = [visibility.shuffled_blocks(ex_enc.shape[1:3], relit.out_enc.shape[1:3], block,
                                          seed=seed * BASELINE_LAYOUTS + layout) for layout in range(BASELINE_LAYOUTS)]
    outputs = [(relit.out_enc, wrap)] + [(relit.replay(shuffled), False) for shuffled in layouts]
    levels = sliced_wasserstein_of_outputs(ex_enc, outputs, patch=patch, scales=scales, projections=projections,
                                           seed=seed)
    swd = float(np.mean(levels[0]))
    baseline = float(np.mean([float(np.mean(layout)) for layout in levels[1:]]))
    return levels[0], {"swd_shuffled_blocks": baseline,
                       "swd_vs_shuffled_blocks": swd / baseline if baseline > 0 else None,
                       "shuffled_block_side": block}


def _noted(ctx, values: dict) -> dict:
    for key, value in values.items():
        ctx.note(key, value)
    return {"scores": Scores(values)}


STAGES = [score]
