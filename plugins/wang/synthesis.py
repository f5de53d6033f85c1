"""Wang-tile synthesis after Leung et al. 2007, "Tileable BTF", section 3.2: four steps per tile set.

Geometry (``w`` tile size, ``h`` edge thickness, ``q = h / 2``).  Every tile edge is the centre line of an
*edge strip*: a horizontal colour's strip is ``h x w`` (its upper half lies in the tile above, its lower half in
the tile below), a vertical colour's ``w x h``.  Every tile corner is the centre of an ``h x h`` *vertex square*
made of four corner samples, one per incident strip: the strip right of the vertex brings its left corner ``L``
(the square's right half), the one left of it its right corner ``R``, the one below its top corner ``T``, the
one above its bottom corner ``B``.  Each quadrant of the square is covered by one horizontal and one vertical
corner half and is split between them by a cut.

1. **Corner sampling**: one ``h x h`` exemplar patch per corner sample, chosen among the patches nearest a random
   reference patch of typical contrast (candidate search by the shared :func:`search.knn`) so that every pair meeting in a quadrant
   differs little; then the cut of every (quadrant, horizontal colour, vertical colour) combination is computed once and
   cached.  Of ``CORNER_TRIALS`` such samplings, the one whose assembled vertex squares show the least seam is
   kept.  A quadrant's cut keeps horizontal-strip pixels along the tile border the horizontal strip straddles
   and vertical-strip pixels along the other border, so both borders see one continuous strip right up to the
   vertex; the two pieces meet only inside the quadrant.
2. **Edge synthesis**: each strip's middle, between its two corner samples, by graph-cut patch filling.
3. **Frame**: each tile's border ring from the halves of its four strips and the cached corner cuts.
4. **Interior**: the same filling with the frame held fixed.

**Graph-cut patch filling** (Kwatra et al. 2003, with the paper's per-pixel bookkeeping): every pixel to fill
starts with error infinity.  Each step centres a window on an unfilled pixel next to filled ones, finds the
exemplar placement with the least error over the window's known pixels (OpenCL, :mod:`placement`), picks among the
``PICK_BEST`` best by the seed, cuts the window between old and new content with a minimum cut (:mod:`cuts`; known
pixels outside the fill region and on the window's rim stay old, unfilled ones take the new patch) and keeps the
patch only if it fills pixels or lowers the summed per-pixel error of the region.  A pixel's error is its worst
seam: for each 4-neighbour copied from elsewhere, the mean distance between each side and the other side's own
continuation.  Filling stops when every pixel is filled; the report counts the pixels left above ``THRESHOLD`` x
the exemplar's median neighbouring-texel distance.  (Patches laid after that over the worst pixels changed
nothing, since no pixel tied the cut to the new side; tied to the worst pixel's neighbourhood they moved no measure
beyond the seeds' spread.)  A placement's error also counts how often earlier patches already laid the exemplar
texels under it (``usage_weight``, :func:`window_means`), in squared median neighbour distances or (``usage_unit``
"match") in the filling's own match level (the median error per known texel of the placements drawn among, after
Kaspar et al. 2015's self-tuning weights), so the tile set spreads over the whole exemplar; it draws only from
places without rare texels and in the ``typical`` share (:meth:`Filler.allowed_places`).  Each finished strip and
interior is then relaxed texel by texel (:mod:`relax`).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from btforge.buffers import CoordMap
from btforge.errors import BtforgeInputError
from btforge.plugins.synth.features import window_sums
from btforge.plugins.synth.refine import refine_map
from btforge.plugins.synth.search import knn

from .cuts import grid_edges, min_cut, min_cut_edges
from .optimise import RECUT_BAND
from .placement import PlacementSearch
from .relax import SWEEPS, relax_seams

PICK_BEST = 4          # a placement is drawn among this many best ones
THRESHOLD = 0.5        # per-pixel error threshold, times the exemplar's median neighbouring-texel distance
SEARCH_STRIDE = 2      # placements are searched on every second texel, then refined among their neighbours ...
STRIDE_FROM = 96       # ... in exemplars at least this large
USAGE_WEIGHT = 4.0     # per known texel, a placement over texels already used once costs this many usage units
# more (Filler._usage_cost): spreads the tiles over the whole exemplar instead of its few best-matching places
USAGE_UNITS = ("neighbour", "match")  # the usage term's unit: squared median neighbour distance, or match level
CORNER_CANDIDATES = 32  # diverse corner patches considered per tile set
DESCRIPTOR_CELLS = 4   # a corner patch is described by DESCRIPTOR_CELLS^2 cell means for the candidate search
CORNER_TRIALS = 8      # corner samplings drawn; the one whose vertex squares have the least seam is kept
TYPICAL = (30, 70)     # percentiles of window contrast corner samples are drawn between
CENTRE = 2             # the central CENTRE x CENTRE texels of corner patches ...
CENTRE_WEIGHT = 4.0    # ... weigh this much more in their search and choice
NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0))
#: Side of the least-used exemplar piece laid at each tile's centre, as a share of the tile side: half (32 of 64).
#: On 192 x 192 crops (seeds 0-1) it took SWD over the shuffled blocks from 1.76 to 1.37 (held-out procedural), 1.76
#: to 1.07 (tablet) and 4.55 to 2.05 (RealRTI item5), with seams within 0.03 on the stationary exemplars; a share of
#: 0.625 (40 texels) raised plaster's SWD to 1.63 and the held-out exemplar's seams to 1.33, and choosing the place by
#: its fit to the frame among the least-used tenth or quarter kept less of the gain (Benchmarks).
CENTRE_SHARE = 0.5
#: Length of the least-used exemplar piece laid at the middle of each edge strip, as a share of the tile side: half
#: (32 of a strip of 64).  Grown from its two corner samples alone, every strip continued the few, mutually similar
#: exemplar areas the corners came from, and the tiling showed their lanes along every tile border (the held-out
#: procedural exemplar: brown lanes between coloured tile centres).  On eleven 192 x 192 crops (seeds 0-1) it lowers SWD
#: over the shuffled blocks on ten (stones 1.74 -> 1.10, fibres 1.61 -> 1.16, the held-out procedural exemplar 1.70
#: -> 1.37) at seams 0.01-0.18 higher; pieces of 24, 40 or 48 texels missed more targets (Benchmarks).
EDGE_CENTRE_SHARE = 0.5
#: Default share of the exemplar's places the tiles' pieces may come from, the most typical first (see
#: ``Filler.allowed_places``): every place.  0.85 keeps a rare part (the demo's gold) out of the tiles and lowered seams on
#: the paintings of the synthesis bench (icon crop 1.38 -> 1.19), but on a stationary exemplar it leaves out places
#: at random and costs patch statistics (stones at 192: SWD 1.06 -> 1.41, medians of 8 seeds; Benchmarks).
TYPICAL_SHARE = 1.0
#: A texel is rare where its unusualness exceeds the upper quartile of all texels' by this many interquartile ranges;
#: pieces holding a rare texel stay out of the tiles (``Filler.allowed_places``).  At 5, the gold corner of the demo's icon
#: patch is rare (5.6 % of its texels, every window touching the gold left out) and no texel of the stationary
#: exemplars of the synthesis bench is (procedural, stones, plaster, fibres, the tablet, item2, item5 at 192).
RARE_FENCE = 5.0
#: ... unless the windows holding rare texels are at least this share of all: then the rare texels are the texture's.
RARE_PLACES_MAX = 0.5


@dataclasses.dataclass
class Synthesis:
    """What :func:`synthesize_tiles` built: the tiles' coordinates and how they were made."""

    tile_coords: np.ndarray      # [T, w, w, 2] int32
    tile_colors: np.ndarray      # [T, 4] int32 N, E, S, W
    corner_positions: dict       # slot name -> exemplar (row, col) of its h x h patch
    corner_cut_costs: dict       # "quadrant h v" -> cut cost
    timings: dict                # step -> seconds
    counts: dict                 # step -> patches placed / kept
    unresolved: int              # filled pixels left above the threshold


# ----------------------------------------------------------------------------------------------- bookkeeping


def pixel_errors(coords: np.ndarray, feats: np.ndarray) -> np.ndarray:
    """Per canvas pixel, its worst seam error (module docstring); ``inf`` where unfilled, 0 where continuous."""
    h, w = coords.shape[:2]
    hf, wf = feats.shape[:2]
    filled = coords[..., 0] >= 0
    err = np.zeros((h, w), np.float64)
    for dy, dx in NEIGHBOURS:
        ys = slice(max(0, -dy), h - max(0, dy))
        xs = slice(max(0, -dx), w - max(0, dx))
        yq = slice(max(0, dy), h - max(0, -dy))
        xq = slice(max(0, dx), w - max(0, -dx))
        cp, cq = coords[ys, xs], coords[yq, xq]
        both = filled[ys, xs] & filled[yq, xq]
        step = np.array([dy, dx])
        seam = both & np.any(cq != cp + step, axis=-1)
        if not seam.any():
            continue
        p, q = cp[seam], cq[seam]
        ahead = np.clip(p + step, 0, [hf - 1, wf - 1])
        behind = np.clip(q - step, 0, [hf - 1, wf - 1])
        cost = 0.5 * (np.linalg.norm(feats[ahead[:, 0], ahead[:, 1]] - feats[q[:, 0], q[:, 1]], axis=1)
                      + np.linalg.norm(feats[p[:, 0], p[:, 1]] - feats[behind[:, 0], behind[:, 1]], axis=1))
        view = err[ys, xs]
        idx = np.nonzero(seam)
        view[idx] = np.maximum(view[idx], cost)
    err[~filled] = np.inf
    return err


def neighbour_distances(feats: np.ndarray) -> np.ndarray:
    """Distances between every horizontally and vertically adjacent pair of exemplar texels."""
    f = feats.astype(np.float64)
    return np.concatenate([np.linalg.norm(f[:, 1:] - f[:, :-1], axis=-1).ravel(),
                           np.linalg.norm(f[1:] - f[:-1], axis=-1).ravel()])


def _rim(shape) -> np.ndarray:
    rim = np.zeros(shape, bool)
    rim[0, :] = rim[-1, :] = rim[:, 0] = rim[:, -1] = True
    return rim


def _region_cost(err: np.ndarray, region: np.ndarray) -> tuple[int, float]:
    values = err[region]
    finite = np.isfinite(values)
    return int((~finite).sum()), float(values[finite].sum())


def window_means(values: np.ndarray, window: tuple[int, int], stride: int = 1) -> np.ndarray:
    """Mean of ``values [H, W, ...]`` over the ``window`` at every placement on the grid of ``stride`` (the layout
    of :func:`placement.placement_errors_numpy`), per trailing channel."""
    ph, pw = window
    return (window_sums(values, window)[::stride, ::stride] / (ph * pw)).astype(np.float32)


class Filler:
    """Graph-cut patch filling of canvases over one exemplar (see the module docstring)."""

    def __init__(self, feats: np.ndarray, search: PlacementSearch, rng: np.random.Generator, cut: str,
                 usage_weight: float = USAGE_WEIGHT, usage_unit: str = USAGE_UNITS[0],
                 typical_share: float = TYPICAL_SHARE, rare: float = RARE_FENCE):
        self.feats, self.search, self.rng, self.cut = feats, search, rng, cut
        self.placed = self.kept = 0
        self.usage = np.zeros(feats.shape[:2], np.float64)   # how often each exemplar texel has been laid so far
        self.usage_weight, self.usage_unit = usage_weight, usage_unit
        reference = float(np.median(neighbour_distances(feats)))
        self.neighbour_cost = usage_weight * reference * reference
        self.match_levels: list[float] = []   # error per known texel of the drawn placements, every search so far
        self.seconds = {"search": 0.0, "cut": 0.0, "bookkeeping": 0.0}  # where the filling's time goes
        self.allowed: dict[tuple, np.ndarray] = {}   # (window, share, rare) -> mask, see allowed_places
        self.typical_share = typical_share   # the share of the exemplar's places (most typical first) pieces come from
        self.rare = rare                     # the fence, in interquartile ranges, beyond which a texel is rare
        self._unusual: np.ndarray | None = None

    def unusualness(self) -> np.ndarray:
        """``[H, W]``: each texel's appearance distance from the median texel's (computed once)."""
        if self._unusual is None:
            flat = self.feats.reshape(-1, self.feats.shape[2])
            self._unusual = np.linalg.norm(self.feats - np.median(flat, axis=0), axis=2)
        return self._unusual

    def allowed_places(self, window: tuple[int, int]) -> np.ndarray:
        """Flat mask of the piece places (top-left corners) pieces may come from.  A texel's unusualness is its
        appearance's distance from the median texel's.  A place is left out where it holds a rare texel (beyond
        the ``rare`` fence; unless such places are ``RARE_PLACES_MAX`` of all or more) or where its most unusual
        texel is not among the ``typical_share`` least unusual.  A rare part of the exemplar (a patch of gold on a
        brown ground) repeats wherever a tile holding it is laid and catches the eye.  (Ranking pieces by their
        mean appearance would keep a piece with a little gold in a corner: it is typical on average.)"""
        key = (window, self.typical_share, self.rare)
        if key not in self.allowed:
            shape = (self.feats.shape[0] - window[0] + 1, self.feats.shape[1] - window[1] + 1)
            allowed = np.ones(shape, bool)
            unusual = self.unusualness() if self.rare > 0 or self.typical_share < 1 else None
            if self.rare > 0:
                q1, q3 = np.percentile(unusual, [25, 75])
                rare = (unusual > q3 + self.rare * (q3 - q1)).astype(np.float64)
                holding = window_means(rare, window) > 0
                if holding.mean() < RARE_PLACES_MAX:
                    allowed &= ~holding
            if self.typical_share < 1:
                worst = np.lib.stride_tricks.sliding_window_view(unusual, window).max(axis=(2, 3))
                allowed &= worst <= np.quantile(worst, self.typical_share)
            self.allowed[key] = allowed.ravel()
        return self.allowed[key]

    def _target(self, coords, region):
        """An unfilled pixel of ``region`` next to a filled one (any unfilled pixel where none is), at random."""
        unfilled = region & (coords[..., 0] < 0)
        filled = coords[..., 0] >= 0
        grown = filled.copy()
        grown[1:] |= filled[:-1]
        grown[:-1] |= filled[1:]
        grown[:, 1:] |= filled[:, :-1]
        grown[:, :-1] |= filled[:, 1:]
        choice = unfilled & grown
        choice = choice if choice.any() else unfilled
        ys, xs = np.nonzero(choice)
        k = int(self.rng.integers(len(ys)))
        return ys[k], xs[k]

    def _placements(self, coords, y0, x0, window, count: int):
        """The ``count`` placements of least error (plus the usage term) for the window at ``(y0, x0)``, on the
        search grid, and a function that refines one of them to the best placement among its neighbours."""
        ph, pw = window
        part = coords[y0:y0 + ph, x0:x0 + pw]
        known = part[..., 0] >= 0
        offsets = np.argwhere(known).astype(np.int32)
        target = self.feats[part[known][:, 0], part[known][:, 1]]
        stride = SEARCH_STRIDE if min(self.feats.shape[:2]) >= STRIDE_FROM else 1
        errors = self.search.errors(offsets, target, window, stride)
        errors = errors + self._usage_cost(errors, len(offsets), window, stride)
        allowed = self.allowed_places(window)
        if not allowed.all():
            places = allowed.reshape(self.feats.shape[0] - ph + 1, -1)
            errors = np.where(places[::stride, ::stride], errors, np.inf)
        flat = errors.ravel()
        k = min(count, flat.size)
        best = np.argpartition(flat, k - 1)[:k]
        best = best[np.argsort(flat[best], kind="stable")]
        found = [(gy * stride, gx * stride) for gy, gx in (divmod(int(i), errors.shape[1]) for i in best)]
        if stride == 1:
            return found, lambda placement: placement
        return found, lambda placement: self.search.refine(offsets, target, window, *placement, stride - 1)

    def _usage_cost(self, errors: np.ndarray, known: int, window, stride: int):
        """The usage term of every placement in ``errors`` (their match errors over ``known`` texels): weight x
        unit x ``known`` x the mean earlier use of the exemplar texels under the placement.  The unit is the
        squared median neighbour distance (``usage_unit`` "neighbour") or the match level ("match"), which
        is the median, over every search so far, of the ``PICK_BEST``-th best placement's error per known texel
        (the best alone is zero wherever the known texels continue one exemplar patch): the exemplar's own scale of
        patch distances.  A fixed unit such as the distance between neighbouring texels would weigh the
        term against matching differently per exemplar: weakly where texels vary smoothly but whole patches differ
        (a painting), strongly on fine grain whose patches all match about as badly (plaster)."""
        if self.usage_unit == "match" and known:
            drawn = min(PICK_BEST, errors.size)  # the placements a draw chooses among
            self.match_levels.append(float(np.partition(errors.ravel(), drawn - 1)[drawn - 1]) / known)
        if self.usage_weight <= 0 or not known or not self.usage.any():
            return 0.0
        weighted_unit = (self.neighbour_cost if self.usage_unit == "neighbour"
                         else self.usage_weight * float(np.median(self.match_levels)))
        return weighted_unit * known * window_means(self.usage, window, stride)

    def record(self, coords: np.ndarray) -> None:
        """Count the exemplar texels a finished canvas lays (they cost more in later placements)."""
        laid = coords[coords[..., 0] >= 0]
        np.add.at(self.usage, (laid[:, 0], laid[:, 1]), 1.0)

    def _edge_costs(self, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        """Per neighbour pair of the window, what a seam between old and new content there would show:
        ``|A(s) - B(s)| + |A(t) - B(t)|``, where an unfilled pixel's old content is its filled neighbour's
        continuation in the exemplar (what the old patch would have put there)."""
        ph, pw = old.shape[:2]
        s, t = grid_edges((ph, pw))
        old_flat, new_flat = old.reshape(-1, 2), new.reshape(-1, 2)
        step = np.stack(np.divmod(t, pw), 1) - np.stack(np.divmod(s, pw), 1)
        limit = np.array(self.feats.shape[:2]) - 1
        filled = old_flat[:, 0] >= 0
        a_s = np.where(filled[s, None], old_flat[s], np.where(filled[t, None], old_flat[t] - step, new_flat[s]))
        a_t = np.where(filled[t, None], old_flat[t], np.where(filled[s, None], old_flat[s] + step, new_flat[t]))
        a_s, a_t = np.clip(a_s, 0, limit), np.clip(a_t, 0, limit)
        f = self.feats
        return (np.linalg.norm(f[a_s[:, 0], a_s[:, 1]] - f[new_flat[s, 0], new_flat[s, 1]], axis=1)
                + np.linalg.norm(f[a_t[:, 0], a_t[:, 1]] - f[new_flat[t, 0], new_flat[t, 1]], axis=1))

    def fill(self, coords: np.ndarray, region: np.ndarray, window: tuple[int, int]) -> np.ndarray:
        """Fill ``region`` of ``coords [h, w, 2]`` (``-1`` unfilled) in place; pixels outside it stay fixed.
        Returns the per-pixel errors.  Filling stops once the region is covered: a later patch could only move
        seams the relaxation and the texture optimisation of the interiors move anyway."""
        err = pixel_errors(coords, self.feats)
        patches = 0
        while True:
            n_unfilled, total = _region_cost(err, region)
            if n_unfilled == 0:
                return err
            patches += 1
            if patches > 4 * region.sum():  # cannot happen while each kept patch fills a pixel
                raise RuntimeError("patch filling made no progress")
            ph, pw = min(window[0], coords.shape[0]), min(window[1], coords.shape[1])
            ty, tx = self._target(coords, region)
            y0 = int(np.clip(ty - ph // 2, 0, coords.shape[0] - ph))
            x0 = int(np.clip(tx - pw // 2, 0, coords.shape[1] - pw))
            clock = time.perf_counter()
            candidates, refine = self._placements(coords, y0, x0, (ph, pw), PICK_BEST)
            chosen = refine(candidates[int(self.rng.integers(len(candidates)))])
            self.placed += 1
            self.seconds["search"] += time.perf_counter() - clock
            trial, trial_err, after = self._trial(coords, region, (y0, x0, ph, pw), chosen)
            if after[0] < n_unfilled or (after[0] == n_unfilled and after[1] < total - 1e-9):
                coords[...] = trial
                err = trial_err
                self.kept += 1

    def seed_centre(self, coords: np.ndarray, side: int | tuple[int, int]) -> None:
        """Lay a ``side x side`` (or ``side = (rows, cols)``) exemplar piece at the canvas's centre from a place the
        pieces laid so far have used least (ties drawn at random) among the places pieces may come from
        (:meth:`allowed_places`), before the filling joins it to the frame around it.  Without it an interior grows
        inwards from its frame, matching it at every step, so every tile continues the few exemplar areas the
        corner samples came from (on paintings, their flat parts); a strip, likewise, its two corner samples."""
        rows, cols = (side, side) if np.isscalar(side) else side
        ph, pw = min(rows, self.feats.shape[0]), min(cols, self.feats.shape[1])
        means = window_means(self.usage, (ph, pw)).ravel()
        allowed = np.flatnonzero(self.allowed_places((ph, pw)))
        lowest = allowed[means[allowed] <= means[allowed].min() + 1e-6]
        py, px = divmod(int(lowest[self.rng.integers(len(lowest))]), self.feats.shape[1] - pw + 1)
        y0, x0 = (coords.shape[0] - ph) // 2, (coords.shape[1] - pw) // 2
        dy, dx = np.mgrid[0:ph, 0:pw]
        coords[y0:y0 + ph, x0:x0 + pw] = np.stack([py + dy, px + dx], -1)

    def _trial(self, coords, region, box, placement):
        """``(canvas, per-pixel errors, region cost)`` after cutting the patch at exemplar ``placement`` into
        the window ``box = (y0, x0, ph, pw)``: known pixels outside the region and on the window's rim stay old,
        unfilled ones take the new patch, the minimum cut decides the rest."""
        y0, x0, ph, pw = box
        clock = time.perf_counter()
        dy, dx = np.mgrid[0:ph, 0:pw]
        new = np.stack([placement[0] + dy, placement[1] + dx], -1).astype(np.int32)
        old = coords[y0:y0 + ph, x0:x0 + pw]
        inside = region[y0:y0 + ph, x0:x0 + pw]
        filled = old[..., 0] >= 0
        take = inside & ~filled
        rim = _rim((ph, pw))
        if self.cut == "graph" and filled.any():
            keep = filled & (~inside | rim)
            mask = min_cut_edges((ph, pw), self._edge_costs(old, new), keep, take)[0] & inside
        else:
            mask = take
        self.seconds["cut"] += time.perf_counter() - clock
        clock = time.perf_counter()
        trial = coords.copy()
        trial[y0:y0 + ph, x0:x0 + pw][mask] = new[mask]
        trial_err = pixel_errors(trial, self.feats)
        self.seconds["bookkeeping"] += time.perf_counter() - clock
        return trial, trial_err, _region_cost(trial_err, region)


# ----------------------------------------------------------------------------------------------- corners


def _patch_descriptors(feats: np.ndarray, size: int) -> np.ndarray:
    """Cell means of every ``size x size`` window: ``[(H - size + 1) * (W - size + 1), cells^2 * D]``."""
    cells = max(1, min(DESCRIPTOR_CELLS, size))
    step = size // cells
    f = feats.astype(np.float64)
    sat = np.zeros((f.shape[0] + 1, f.shape[1] + 1, f.shape[2]))
    sat[1:, 1:] = f.cumsum(0).cumsum(1)
    n_rows, n_cols = f.shape[0] - size + 1, f.shape[1] - size + 1
    parts = []
    for a in range(cells):
        for b in range(cells):
            y, x = a * step, b * step
            box = (sat[y + step:y + step + n_rows, x + step:x + step + n_cols] - sat[y:y + n_rows, x + step:x + step + n_cols]
                   - sat[y + step:y + step + n_rows, x:x + n_cols] + sat[y:y + n_rows, x:x + n_cols])
            parts.append(box / (step * step))
    # The texels around the vertex weigh most: there the pieces of four different strips touch.
    c0 = size // 2 - CENTRE // 2
    for a in range(CENTRE):
        for b in range(CENTRE):
            parts.append(CENTRE_WEIGHT * f[c0 + a:c0 + a + n_rows, c0 + b:c0 + b + n_cols])
    return np.concatenate(parts, axis=-1).reshape(n_rows * n_cols, -1).astype(np.float32)


def _typical_windows(feats: np.ndarray, size: int) -> np.ndarray:
    """Whether each ``size x size`` window (by flat index of its origin) has typical contrast: its summed distance
    between neighbouring texels lies between the TYPICAL percentiles over all windows.  Corner samples are drawn
    among these only: every vertex shows one, so neither the busiest nor the flattest places of the exemplar (which
    the search for mutually similar samples would otherwise favour) should set the tile borders."""
    f = feats.astype(np.float64)
    grad = np.zeros(f.shape[:2])
    grad[:, :-1] += np.linalg.norm(f[:, 1:] - f[:, :-1], axis=-1)
    grad[:-1, :] += np.linalg.norm(f[1:] - f[:-1], axis=-1)
    box = window_sums(grad, (size, size))
    low, high = np.percentile(box, TYPICAL)
    return ((box >= low) & (box <= high)).ravel()


def corner_windows(feats: np.ndarray, h: int) -> tuple[np.ndarray, np.ndarray]:
    """What every corner sampling of ``feats`` with ``h x h`` samples searches: the windows' descriptors
    (:func:`_patch_descriptors`) and the flat indices of the windows of typical contrast (:func:`_typical_windows`)."""
    return _patch_descriptors(feats, h), np.flatnonzero(_typical_windows(feats, h))


def _diverse(order: np.ndarray, n_cols: int, spacing: int, limit: int) -> list[tuple[int, int]]:
    chosen: list[tuple[int, int]] = []
    for index in order:
        y, x = divmod(int(index), n_cols)
        if all(max(abs(y - cy), abs(x - cx)) >= spacing for cy, cx in chosen):
            chosen.append((y, x))
            if len(chosen) == limit:
                break
    return chosen


# The four quadrants of a vertex square: which corner samples cover it and where the vertex lies in it.
# name: (horizontal sample, vertical sample, rows, cols, vertex corner (row, col) in quadrant coordinates)
QUADRANTS = {
    "UL": ("R", "B", 0, 0, (1, 1)),
    "UR": ("L", "B", 0, 1, (1, 0)),
    "LL": ("R", "T", 1, 0, (0, 1)),
    "LR": ("L", "T", 1, 1, (0, 0)),
}


def quadrant_ties(q: int, vertex: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(horizontal, vertical)`` pixels of a ``q x q`` quadrant tied to each strip: the row through the vertex
    and the column away from it stay with the horizontal strip, the column through the vertex and the row away
    from it with the vertical one; the two corners where both would apply are left to the cut."""
    vr, vc = (q - 1) * vertex[0], (q - 1) * vertex[1]
    horizontal = np.zeros((q, q), bool)
    vertical = np.zeros((q, q), bool)
    horizontal[vr, :] = True
    horizontal[:, q - 1 - vc] = True
    vertical[:, vc] = True
    vertical[q - 1 - vr, :] = True
    # The vertex texel goes to the vertical strip in all four quadrants, so along the vertical border it continues
    # one strip; the inner corner is left to the cut.
    horizontal[vr, vc] = False
    vertical[q - 1 - vr, q - 1 - vc] = False
    return horizontal & ~vertical, vertical & ~horizontal


def straight_split(q: int, vertex: tuple[int, int]) -> np.ndarray:
    """The straight-cut baseline: horizontal strips run through the vertex square, vertical ones stop at them."""
    return np.zeros((q, q), bool)


class Corners:
    """Step 1: a patch per corner sample and the cached cut of every quadrant combination."""

    def __init__(self, feats: np.ndarray, h: int, n_h: int, n_v: int, rng: np.random.Generator, cut: str,
                 windows: tuple[np.ndarray, np.ndarray] | None = None):
        """``windows``: :func:`corner_windows` of ``feats`` and ``h``, when several samplings share them."""
        self.h, self.q, self.n_h, self.n_v = h, h // 2, n_h, n_v
        self.feats = feats
        slots = [f"L{a}" for a in range(n_h)] + [f"R{a}" for a in range(n_h)] + \
                [f"T{c}" for c in range(n_v)] + [f"B{c}" for c in range(n_v)]
        n_cols = feats.shape[1] - h + 1
        desc, typical = corner_windows(feats, h) if windows is None else windows
        reference = int(typical[rng.integers(len(typical))])
        k = min(len(typical), 64 * len(slots))
        order, _ = knn(desc[typical], desc[reference:reference + 1], k, engine="exact")
        order = typical[order]
        pool = _diverse(order[0], n_cols, max(1, self.q), max(CORNER_CANDIDATES, len(slots)))
        if len(pool) < len(slots):
            pool = _diverse(order[0], n_cols, 1, len(slots))
        if len(pool) < len(slots):
            raise BtforgeInputError("wang.tiles", f"the exemplar has fewer than {len(slots)} distinct "
                                    f"{h} x {h} patches for the corner samples", "lower 'edge' or use a larger exemplar")
        self.pool = pool
        assignment = dict(zip(slots, [pool[i] for i in rng.permutation(len(pool))[:len(slots)]]))
        self._terms: dict = {}   # the descent's pairwise cost terms, by the places of their two patches
        self.positions = self._descend(assignment, slots)
        self.cut = cut
        self.masks, self.costs = {}, {}
        for name, (hs, vs, _, _, vertex) in QUADRANTS.items():
            for a in range(n_h):
                for c in range(n_v):
                    mask, cost = self._quadrant_cut(name, f"{hs}{a}", f"{vs}{c}", vertex)
                    self.masks[name, a, c], self.costs[f"{name} {a} {c}"] = mask, cost

    def vertex_square(self, a: int, b: int, c: int, d: int) -> np.ndarray:
        """Exemplar coordinates ``[h, h, 2]`` of the vertex square with horizontal colours ``a`` (left), ``b``
        (right) and vertical ones ``c`` (above), ``d`` (below), as the frames will assemble it."""
        q = self.q
        square = np.zeros((self.h, self.h, 2), np.int32)
        for name, h_colour, v_colour in (("UL", a, c), ("UR", b, c), ("LL", a, d), ("LR", b, d)):
            h_slot, v_slot, qr, qc, _ = QUADRANTS[name]
            hp, vp = self._pieces(name, f"{h_slot}{h_colour}", f"{v_slot}{v_colour}")
            square[qr * q:(qr + 1) * q, qc * q:(qc + 1) * q] = np.where(self.masks[name, h_colour, v_colour][..., None],
                                                                        vp, hp)
        return square

    def seam_score(self) -> float:
        """The worst of mean and 99th-percentile distance across the two centre lines of every vertex square,
        over the same of the distances from those texels to their own exemplar neighbours."""
        q, f, parts, local = self.q, self.feats, [], []
        limit = np.array(f.shape[:2]) - 1
        for a in range(self.n_h):
            for b in range(self.n_h):
                for c in range(self.n_v):
                    for d in range(self.n_v):
                        sq = self.vertex_square(a, b, c, d)
                        for x, y, step in ((sq[:, q - 1], sq[:, q], (0, 1)), (sq[q - 1], sq[q], (1, 0))):
                            parts.append(np.linalg.norm(f[x[:, 0], x[:, 1]] - f[y[:, 0], y[:, 1]], axis=-1))
                            ahead, behind = np.clip(x + step, 0, limit), np.clip(y - np.array(step), 0, limit)
                            local.append(0.5 * (np.linalg.norm(f[x[:, 0], x[:, 1]] - f[ahead[:, 0], ahead[:, 1]], axis=-1)
                                                + np.linalg.norm(f[behind[:, 0], behind[:, 1]] - f[y[:, 0], y[:, 1]], axis=-1)))
        values, local = np.concatenate(parts), np.concatenate(local)
        return max(values.mean() / max(local.mean(), 1e-30),
                   np.percentile(values, 99) / max(np.percentile(local, 99), 1e-30))

    def patch(self, slot: str) -> np.ndarray:
        """Exemplar coordinates ``[h, h, 2]`` of a slot's patch, as laid in its vertex square."""
        y, x = self.positions[slot]
        dy, dx = np.mgrid[0:self.h, 0:self.h]
        return np.stack([y + dy, x + dx], -1).astype(np.int32)

    def _pieces(self, name: str, h_slot: str, v_slot: str, positions=None):
        _, _, qr, qc, _ = QUADRANTS[name]
        rows, cols = slice(qr * self.q, (qr + 1) * self.q), slice(qc * self.q, (qc + 1) * self.q)
        positions = positions or self.positions
        dy, dx = np.mgrid[rows, cols]
        (hy, hx), (vy, vx) = positions[h_slot], positions[v_slot]
        return np.stack([hy + dy, hx + dx], -1), np.stack([vy + dy, vx + dx], -1)

    def _difference(self, name, h_slot, v_slot, positions=None) -> np.ndarray:
        hp, vp = self._pieces(name, h_slot, v_slot, positions)
        return np.linalg.norm(self.feats[hp[..., 0], hp[..., 1]] - self.feats[vp[..., 0], vp[..., 1]], axis=-1)

    def _slot_cost(self, slot: str, positions) -> float:
        """The slot's differences with every sample it meets in a quadrant, plus, across the centre line it
        shares with the samples of the same orientation (``L``/``R``, ``T``/``B``), with those: at the vertex
        itself some pieces of different strips must touch."""
        kind = slot[0]
        partner = {"L": "R", "R": "L", "T": "B", "B": "T"}[kind]
        total = 0.0
        for other in positions:
            if other == slot:
                continue
            centres, wholes = self._pair_terms(positions[slot], positions[other])
            total += centres
            if other[0] == partner:
                total += wholes
        for name, (hs, vs, _, _, _) in QUADRANTS.items():
            if kind == hs:
                total += sum(self._quadrant_term(name, positions[slot], positions[f"{vs}{c}"]) for c in range(self.n_v))
            elif kind == vs:
                total += sum(self._quadrant_term(name, positions[f"{hs}{a}"], positions[slot]) for a in range(self.n_h))
        return total

    def _pair_terms(self, mine_at: tuple, theirs_at: tuple) -> tuple[float, float]:
        """Two patches' difference at their centres (weighted) and over their whole (a quarter), computed once
        per pair of places: the descent meets the same pairs many times."""
        key = ("pair", mine_at, theirs_at)
        if key not in self._terms:
            (y, x), (py, px), c = mine_at, theirs_at, self.q - CENTRE // 2
            mine = self.feats[y:y + self.h, x:x + self.h]
            theirs = self.feats[py:py + self.h, px:px + self.h]
            centre = np.linalg.norm(mine[c:c + CENTRE, c:c + CENTRE] - theirs[c:c + CENTRE, c:c + CENTRE], axis=-1)
            self._terms[key] = (CENTRE_WEIGHT * self.h * centre.sum(), np.linalg.norm(mine - theirs, axis=-1).sum() / 4)
        return self._terms[key]

    def _quadrant_term(self, name: str, h_at: tuple, v_at: tuple) -> float:
        """The summed difference of a quadrant's two pieces with its samples at ``h_at`` and ``v_at`` (once per
        pair of places)."""
        key = (name, h_at, v_at)
        if key not in self._terms:
            self._terms[key] = self._difference(name, "h", "v", {"h": h_at, "v": v_at}).sum()
        return self._terms[key]

    def _descend(self, positions: dict, slots: list[str], sweeps: int = 2) -> dict:
        """Coordinate descent on the summed quadrant differences, each slot on a distinct pool patch."""
        positions = dict(positions)
        for _ in range(sweeps):
            for slot in slots:
                taken = {p for s, p in positions.items() if s != slot}
                best, best_cost = positions[slot], self._slot_cost(slot, positions)
                for candidate in self.pool:
                    if candidate in taken:
                        continue
                    cost = self._slot_cost(slot, {**positions, slot: candidate})
                    if cost < best_cost:
                        best, best_cost = candidate, cost
                positions[slot] = best
        return positions

    def _quadrant_cut(self, name, h_slot, v_slot, vertex):
        difference = self._difference(name, h_slot, v_slot)
        if self.cut == "straight":
            mask = straight_split(self.q, vertex)
            return mask, float("nan")
        keep, take = quadrant_ties(self.q, vertex)
        return min_cut(difference, keep, take)


# ----------------------------------------------------------------------------------------------- tile set


def tile_index(n: int, e: int, s: int, w: int, variant: int, n_h: int, n_v: int, variants: int) -> int:
    """The index of the tile with colours N, E, S, W (N/S horizontal, E/W vertical) and its variant."""
    return (((n * n_v + e) * n_h + s) * n_v + w) * variants + variant


def _strip_canvas(corners: Corners, kind: str, colour: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    h, q = corners.h, corners.q
    if kind == "h":
        coords = np.full((h, w, 2), -1, np.int32)
        coords[:, :q] = corners.patch(f"L{colour}")[:, q:]
        coords[:, w - q:] = corners.patch(f"R{colour}")[:, :q]
    else:
        coords = np.full((w, h, 2), -1, np.int32)
        coords[:q] = corners.patch(f"T{colour}")[q:]
        coords[w - q:] = corners.patch(f"B{colour}")[:q]
    return coords, coords[..., 0] < 0


def _frame(corners: Corners, strips_h, strips_v, n, e, s, west, w: int) -> np.ndarray:
    q = corners.q
    tile = np.full((w, w, 2), -1, np.int32)
    tile[:q] = strips_h[n][q:]
    tile[w - q:] = strips_h[s][:q]
    tile[:, :q] = strips_v[west][:, q:]
    tile[:, w - q:] = strips_v[e][:, :q]
    # corners: (tile rows, tile cols, quadrant, h colour, v colour, horizontal piece, vertical piece)
    spots = [(slice(0, q), slice(0, q), "LR", n, west, strips_h[n][q:, :q], strips_v[west][:q, q:]),
             (slice(0, q), slice(w - q, w), "LL", n, e, strips_h[n][q:, w - q:], strips_v[e][:q, :q]),
             (slice(w - q, w), slice(0, q), "UR", s, west, strips_h[s][:q, :q], strips_v[west][w - q:, q:]),
             (slice(w - q, w), slice(w - q, w), "UL", s, e, strips_h[s][:q, w - q:], strips_v[e][w - q:, :q])]
    for rows, cols, name, a, c, hp, vp in spots:
        tile[rows, cols] = np.where(corners.masks[name, a, c][..., None], vp, hp)
    return tile


def refined_strip(feats: np.ndarray, coords: np.ndarray, region: np.ndarray, seed: int, *, iterations: int,
                  polish: int, seam_weight: float) -> np.ndarray:
    """An edge strip ``coords`` after the shared refinement (:func:`btforge.plugins.synth.refine.refine_map`), its
    corner halves (outside ``region``) held, since the vertex squares the four strips of a vertex share meet there.
    Every tile of the strip's colour lays half of it along its border, and the tiles' own refinement holds only its
    border texel: a cut the filling left in a strip shows in each of those tiles, and the texels beside the held
    texel are chopped into small pieces to continue it.  Refined first, the strip's middle is joined to its corner
    halves and centre piece where the two sides agree.  No occurrence term: one strip uses too little of the
    exemplar for it to mean anything (the filling's usage term spreads the strips over the exemplar).  Its straight
    seams are re-cut in the tiles' wider band (:data:`.optimise.RECUT_BAND`).  No contrast
    term either: at the tiles' weight of 8 it left item1's patch statistics as far off (RealRTI item1, 192 x 192,
    seeds 0-1: SWD over the shuffled blocks 0.79 and 2.37, against 1.87 and 2.09 without it)."""
    laid = CoordMap(coords, feats.shape[:2])
    return np.array(refine_map(feats, laid, iterations=iterations, occurrence=0.0, pinned=~region, polish=polish,
                               seed=seed, seam_weight=seam_weight, recut_band=RECUT_BAND).coords)


def interior_window(w: int, h: int, interior: int = 0) -> int:
    """The side of the windows that fill a tile's interior: ``interior`` where given, else one and a half edge
    strips (``h + h / 2``), at most the interior's span ``w - h``.  Larger windows copy larger exemplar pieces
    (patch statistics nearer the exemplar's) but leave longer straight cuts for the refinement to hide."""
    return min(w - h, interior if interior > 0 else h + h // 2)


def centre_piece_side(w: int, h: int, centre: float) -> int:
    """The side of the piece laid at a tile's centre (or the length of the one at an edge strip's middle):
    ``centre`` x the tile side, at most the span inside the frame's outer halves, or between a strip's two corner
    halves (``w - h``), so the filling always has laid texels to join it to."""
    return min(w - h, int(round(centre * w)))


def check_sizes(exemplar_size, w: int, h: int, colors) -> None:
    problems = []
    if h < 2 or h % 2:
        problems.append(f"'edge' must be even and >= 2, found {h}")
    if w < 2 * h:
        problems.append(f"'tile' must be at least twice 'edge' ({2 * h}), found {w}")
    if min(exemplar_size) < max(w // 2 + h // 2, h + 1):
        problems.append(f"the {exemplar_size[0]} x {exemplar_size[1]} exemplar is too small for tiles of {w} "
                        f"and edges of {h}")
    if len(colors) != 2 or min(colors) < 1:
        problems.append(f"'colors' must be [horizontal, vertical] counts >= 1, found {list(colors)}")
    if problems:
        raise BtforgeInputError("wang.tiles", "; ".join(problems),
                                "the paper's layout: edge = tile / 4, e.g. tile 64, edge 16, colors [2, 2]")


def synthesize_tiles(feats: np.ndarray, w: int = 64, h: int | None = None, colors=(2, 2), variants: int = 1,
                     seed: int = 0, *, cut: str = "graph", engine: str = "opencl", usage_weight: float = USAGE_WEIGHT,
                     relax: int = SWEEPS, usage_unit: str = USAGE_UNITS[0], interior: int = 0,
                     centre: float = CENTRE_SHARE, edge_centre: float = EDGE_CENTRE_SHARE,
                     typical: float = TYPICAL_SHARE,
                     rare: float = RARE_FENCE, strip_refine: dict | None = None) -> Synthesis:
    """Build the complete tile set over appearance vectors ``feats [H, W, D]`` (module docstring); ``interior``:
    the side of the windows that fill the interiors (0: :func:`interior_window`'s default); ``centre``: the side,
    as a share of the tile's, of the least-used exemplar piece laid at each tile's centre first (0: none;
    :func:`centre_piece_side`); ``edge_centre``: the length, as a share of the tile side, of the least-used piece
    laid at each edge strip's middle first (0: none; :func:`centre_piece_side` too); ``typical``: the share of the
    exemplar's places, the most typical first, the centre pieces and the filling's patches come from; ``rare``: the fence beyond which a texel is rare and kept out of
    them (:meth:`Filler.allowed_places`); ``strip_refine``: keywords of :func:`refined_strip` for every finished edge
    strip (``iterations``, ``polish``, ``seam_weight``; none or 0 iterations: the strips stay as filled).

    ``cut='straight'`` replaces every graph cut by a straight one (the baseline the seam tests compare with).
    """
    h = w // 4 if h is None else h
    check_sizes(feats.shape[:2], w, h, colors)
    strip_refine = strip_refine or {}
    refine_strips = strip_refine.get("iterations", 0) > 0
    n_h, n_v = colors
    rng = np.random.default_rng(seed)
    feats = np.ascontiguousarray(feats, np.float32)
    threshold = THRESHOLD * float(np.median(neighbour_distances(feats)))
    search = PlacementSearch(feats, engine)
    filler = Filler(feats, search, rng, cut, usage_weight, usage_unit, typical, rare)
    timings, counts = {}, {}

    start = time.perf_counter()
    windows = corner_windows(feats, h)
    drawn = [Corners(feats, h, n_h, n_v, rng, cut, windows) for _ in range(CORNER_TRIALS)]
    corner_scores = [c.seam_score() for c in drawn]
    corners = drawn[int(np.argmin(corner_scores))]
    timings["corners"] = time.perf_counter() - start

    def run(step, jobs):
        begin, placed, kept = time.perf_counter(), filler.placed, filler.kept
        out = [job() for job in jobs]
        timings[step] = time.perf_counter() - begin
        counts[step] = {"placed": filler.placed - placed, "kept": filler.kept - kept}
        return out

    edge_length = centre_piece_side(w, h, edge_centre)

    def strip(kind, colour):
        def job():
            coords, region = _strip_canvas(corners, kind, colour, w)
            if edge_length:
                filler.seed_centre(coords, (h, edge_length) if kind == "h" else (edge_length, h))
            err = filler.fill(coords, region, (h, h))
            if relax:
                coords[...] = relax_seams(coords, feats, region, relax)
            if refine_strips:
                coords = refined_strip(feats, coords, region, seed, **strip_refine)
            if relax or refine_strips:
                err = pixel_errors(coords, feats)
            filler.record(np.where(region[..., None], coords, -1))
            return coords, err
        return job

    built = run("edges", [strip("h", a) for a in range(n_h)] + [strip("v", c) for c in range(n_v)])
    strips_h = [c for c, _ in built[:n_h]]
    strips_v = [c for c, _ in built[n_h:]]
    unresolved = sum(int(((e > threshold) & np.isfinite(e)).sum()) for _, e in built)

    start = time.perf_counter()
    combos = [(n, e, s, west) for n in range(n_h) for e in range(n_v) for s in range(n_h) for west in range(n_v)]
    frames = {combo: _frame(corners, strips_h, strips_v, *combo, w) for combo in combos}
    timings["frames"] = time.perf_counter() - start

    q = h // 2
    window = (interior_window(w, h, interior),) * 2
    ring = max(1, q // 2)  # the frame's outer half stays; its inner half is overlap the interior's cuts may take
    inside_frame = np.zeros((w, w), bool)   # what the interior filling may change
    inside_frame[ring:w - ring, ring:w - ring] = True
    centre_side = centre_piece_side(w, h, centre)
    tiles = np.zeros((len(combos) * variants, w, w, 2), np.int32)
    colors_out = np.zeros((len(combos) * variants, 4), np.int32)

    def interior_job(combo, variant):
        def job():
            tile = frames[combo].copy()
            if centre_side:
                filler.seed_centre(tile, centre_side)
            err = filler.fill(tile, inside_frame, window)
            if relax:
                tile = relax_seams(tile, feats, inside_frame, relax)
                err = pixel_errors(tile, feats)
            filler.record(np.where(inside_frame[..., None], tile, -1))
            index = tile_index(*combo, variant, n_h, n_v, variants)
            tiles[index], colors_out[index] = tile, combo
            return int(((err > threshold) & np.isfinite(err)).sum())
        return job

    unresolved += sum(run("interiors", [interior_job(c, v) for c in combos for v in range(variants)]))
    counts["filling_seconds"] = {k: round(v, 3) for k, v in filler.seconds.items()}
    return Synthesis(tiles, colors_out, dict(corners.positions), dict(corners.costs), timings, counts, unresolved)
