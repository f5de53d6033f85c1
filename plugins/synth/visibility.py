"""What the eye sees in a synthesized texture: seams, straight block edges, uneven use of the exemplar.

Each measure reads the coordinate map (which output neighbours come from exemplar neighbours) and the relit
images (how large the radiance jump across each output neighbour pair is):

* seam visibility: the mean radiance jump between adjacent output texels whose sources are not adjacent in the
  exemplar, over the mean jump between adjacent exemplar texels (1: seams look like the exemplar's own edges);
* straight-seam visibility: the same over the seam edges lying in straight runs of :data:`STRAIGHT_RUN` or more
  texels (the edges of copied blocks, which the eye picks out first), left out along the borders of a tiling's
  tiles (straight by design, named by the map's ``tile``);
* evenness: ``exp(entropy) / n`` of the output's use of the exemplar's ``8 x 8``-texel cells (1: every cell used
  equally; an output that collapses onto a few regions scores low);
* lattice share: for a tiling, the share of the output's radiance variance, or of its local contrast, that sits
  at the same place in every tile, whichever is larger (0: the tiles' content is placed independently of the
  lattice; 1: every tile the same, a periodic texture);
* the shuffled-block baseline: exemplar blocks laid at random, the layout a synthesizer's patch statistics are
  compared with.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from btforge.buffers import CoordMap

#: Seam edges in straight runs at least this long count as the edges of copied blocks.
STRAIGHT_RUN = 12
#: Side in texels of the exemplar cells whose use the evenness measures.
EVENNESS_CELL = 8
#: Side of the box over which the lattice share averages an image's local contrast (the outline of a piece as a
#: band a few texels wide).  On Wang tilings of the synthesis bench's crops 3 and 5 agree (0.14-0.23); a grid of
#: squares in colours of their own per tile scores 0.59 at 3, 0.39 at 5, where the tile borders' own edges blur into the
#: squares' outlines.
CONTRAST_BOX = 3
#: Side of the blocks of the shuffled-block baseline (capped at half the exemplar's shorter side).
BASELINE_BLOCK = 32

#: The targets a synthesizer's output should meet at its defaults, by measure: seams no more visible than 1.3 x
#: the exemplar's own neighbour steps; straight seams at most 1.2, where they are :data:`STRAIGHT_SHARE_FROM` of
#: the seam edges or more (a few short straight stretches are not the edges of copied blocks); evenness at least
#: 0.5; patch statistics at most 1.5 x as far from the exemplar's as shuffled blocks'.
SEAM_TARGET, STRAIGHT_TARGET, EVENNESS_TARGET, SWD_TARGET = 1.3, 1.2, 0.5, 1.5
STRAIGHT_SHARE_FROM = 0.02


def dominant_source(coords: CoordMap) -> np.ndarray:
    """``[H, W, 2]`` exemplar texel each output texel mostly copies (the blend partner where its weight > 0.5)."""
    src = coords.coords
    if coords.blend_weight.size:
        src = np.where((coords.blend_weight > 0.5)[..., None], coords.blend_coords, src)
    return src.astype(np.int64)


@dataclasses.dataclass(frozen=True)
class SeamEdges:
    """Output neighbour pairs whose sources are not exemplar neighbours.

    ``across_columns[r, c]`` is the pair ``(r, c), (r, c + 1)`` (``c`` up to ``W - 1``: the last column pairs
    with the first when the map wraps), ``across_rows[r, c]`` the pair ``(r, c), (r + 1, c)``.  ``*_straight``
    mark the seam edges in straight runs (a vertical run of ``across_columns`` edges, a horizontal one of
    ``across_rows`` edges) of at least :data:`STRAIGHT_RUN`, tile borders left out.
    """

    across_columns: np.ndarray
    across_rows: np.ndarray
    columns_straight: np.ndarray
    rows_straight: np.ndarray

    @property
    def count(self) -> int:
        return int(self.across_columns.sum() + self.across_rows.sum())

    @property
    def straight_count(self) -> int:
        return int(self.columns_straight.sum() + self.rows_straight.sum())


def seam_edges(coords: CoordMap, run: int = STRAIGHT_RUN) -> SeamEdges:
    """The seam edges of a map (its dominant sources; with ``wrap`` the wrap-around pairs too)."""
    src = dominant_source(coords)
    across_columns, across_rows = seam_masks(src[..., 0], src[..., 1], coords.wrap)
    tile = int(getattr(coords, "tile", 0) or 0)
    candidates_c, candidates_r = across_columns.copy(), across_rows.copy()
    if tile > 0:  # a tiling's tile borders are straight by design
        candidates_c[:, (np.arange(coords.width) + 1) % tile == 0] = False
        candidates_r[(np.arange(coords.height) + 1) % tile == 0, :] = False
    return SeamEdges(across_columns, across_rows, in_long_runs(candidates_c, 0, run),
                     in_long_runs(candidates_r, 1, run))


def seam_masks(rows: np.ndarray, cols: np.ndarray, wrap: bool) -> tuple[np.ndarray, np.ndarray]:
    """``across_columns, across_rows`` (as in :class:`SeamEdges`) of a map whose texels copy exemplar texels
    ``(rows, cols)`` (``[H, W]`` each)."""
    across_columns = (np.roll(rows, -1, axis=1) != rows) | (np.roll(cols, -1, axis=1) != cols + 1)
    across_rows = (np.roll(rows, -1, axis=0) != rows + 1) | (np.roll(cols, -1, axis=0) != cols)
    if not wrap:
        across_columns[:, -1] = False
        across_rows[-1, :] = False
    return across_columns, across_rows


def run_labels(mask: np.ndarray, axis: int) -> tuple[np.ndarray, int]:
    """``scipy.ndimage.label`` of ``mask`` with runs along ``axis`` as the components: labels and their count."""
    from scipy.ndimage import label
    structure = np.zeros((3, 3), bool)
    if axis == 0:
        structure[:, 1] = True
    else:
        structure[1, :] = True
    return label(mask, structure=structure)


def in_long_runs(mask: np.ndarray, axis: int, run: int) -> np.ndarray:
    """Elements of ``mask`` in runs of at least ``run`` consecutive True values along ``axis``."""
    labels, n = run_labels(mask, axis)
    if n == 0:
        return np.zeros_like(mask)
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return sizes[labels] >= run


def neighbour_jumps(images: np.ndarray, wrap: bool) -> tuple[np.ndarray, np.ndarray]:
    """Radiance jumps ``[L, H, W]`` between each texel and its right and lower neighbours (colour norm, the last
    column and row pairing with the first; those pairs are meaningful only when the image wraps)."""
    across_columns = np.linalg.norm(np.roll(images, -1, axis=2) - images, axis=3)
    across_rows = np.linalg.norm(np.roll(images, -1, axis=1) - images, axis=3)
    if not wrap:
        across_columns[:, :, -1] = 0.0
        across_rows[:, -1, :] = 0.0
    return across_columns, across_rows


def exemplar_jump(ex_enc: np.ndarray) -> float:
    """Mean radiance jump between adjacent exemplar texels (both directions, all lights)."""
    gx = np.linalg.norm(np.diff(ex_enc, axis=2), axis=3)
    gy = np.linalg.norm(np.diff(ex_enc, axis=1), axis=3)
    return float((gx.sum() + gy.sum()) / max(1, gx.size + gy.size))


@dataclasses.dataclass(frozen=True)
class Visibility:
    seam_visibility: float | None           # mean seam jump / mean exemplar jump
    straight_seam_visibility: float | None  # the same over straight seam edges
    straight_seam_share: float              # straight seam edges / seam edges
    seam_edge_share: float                  # seam edges / all output neighbour pairs


def seam_visibility(out_enc: np.ndarray, ex_enc: np.ndarray, coords: CoordMap) -> Visibility:
    """Seam and straight-seam visibility of ``out_enc [L, H, W, C]`` (the map's relit output) against the
    exemplar ``ex_enc``, in the same exposure-normalised domain.  Where the map blends texels beside a seam edge
    (feathering, quilting's linear blend), the step moves onto the pairs beside the edge, which are not seam
    edges: the edge then counts with the largest jump over the pairs along its normal that the blended texels
    span, against the exemplar's mean largest of as many consecutive jumps (:func:`banded_jumps`)."""
    edges = seam_edges(coords)
    jump_c, jump_r = neighbour_jumps(out_enc, coords.wrap)
    if coords.blend_weight.size:
        blended = coords.blend_weight > 0
        jump_c, span_c = banded_jumps(jump_c, edges.across_columns, blended, 1, coords.wrap)
        jump_r, span_r = banded_jumps(jump_r, edges.across_rows, blended, 0, coords.wrap)
        references = exemplar_band_jumps(ex_enc, int(max(span_c.max(), span_r.max())))
    else:
        span_c = span_r = None
        references = np.array([0.0, exemplar_jump(ex_enc)])

    def ratio(mask_c, mask_r):
        n = int(mask_c.sum() + mask_r.sum())
        if n == 0 or references[1] <= 0:
            return None
        total = jump_c[:, mask_c].sum() + jump_r[:, mask_r].sum()
        if span_c is None:
            return float(total / (n * out_enc.shape[0]) / references[1])
        reference = references[span_c[mask_c]].sum() + references[span_r[mask_r]].sum()
        return float(total / (out_enc.shape[0] * reference)) if reference > 0 else None

    pairs = coords.height * (coords.width - (0 if coords.wrap else 1)) + coords.width * (
        coords.height - (0 if coords.wrap else 1))
    return Visibility(ratio(edges.across_columns, edges.across_rows),
                      ratio(edges.columns_straight, edges.rows_straight),
                      edges.straight_count / edges.count if edges.count else 0.0,
                      edges.count / max(1, pairs))


#: The farthest from a seam edge, in texels on either side, that the blended band of a seam is followed.
MAX_BAND = 8


def banded_jumps(jumps: np.ndarray, edges: np.ndarray, blended: np.ndarray, axis: int, wrap: bool):
    """``jumps [L, H, W]`` (as :func:`neighbour_jumps` gives them along ``axis``) with each seam edge of ``edges``
    replaced by the largest jump over the pairs its blended band spans, and ``[H, W]`` how many pairs that is
    (1 where no texel beside the edge is blended).  The band runs outwards from the edge while the texels are
    blended (``blended [H, W]``), up to :data:`MAX_BAND` on either side."""
    h, w = edges.shape
    length = w if axis == 1 else h
    out = jumps.copy()
    span = np.ones((h, w), np.int64)
    rows, cols = np.nonzero(edges)
    along = cols if axis == 1 else rows
    best = jumps[:, rows, cols].copy()
    count = np.ones(len(rows), np.int64)
    for side in (-1, 1):
        alive = np.ones(len(rows), bool)
        for step in range(1, MAX_BAND + 1):
            texel = along - step + 1 if side < 0 else along + step   # the texel the band must reach
            pair = along - step if side < 0 else along + step        # the pair it closes on its far side
            if wrap:
                texel, pair = texel % length, pair % length
            alive &= (texel >= 0) & (texel < length) & (pair >= 0) & (pair < length - (0 if wrap else 1))
            at = (rows, np.where(alive, texel, 0)) if axis == 1 else (np.where(alive, texel, 0), cols)
            alive &= blended[at]
            if not alive.any():
                break
            idx = np.flatnonzero(alive)
            there = (rows[idx], pair[idx]) if axis == 1 else (pair[idx], cols[idx])
            best[:, idx] = np.maximum(best[:, idx], jumps[:, there[0], there[1]])
            count[idx] += 1
    out[:, rows, cols] = best
    span[rows, cols] = count
    return out, span


def exemplar_band_jumps(ex_enc: np.ndarray, longest: int) -> np.ndarray:
    """``[longest + 1]``: at ``k`` the mean over the exemplar (both directions, all lights) of the largest of ``k``
    consecutive neighbour jumps (0 at ``k = 0``; at 1 :func:`exemplar_jump`; a ``k`` longer than the exemplar's
    rows or columns takes their whole length)."""
    jumps = [np.linalg.norm(np.diff(ex_enc, axis=2), axis=3),                    # along rows: the last axis
             np.linalg.norm(np.diff(ex_enc, axis=1), axis=3).swapaxes(1, 2)]    # along columns, made the last
    jumps = [j for j in jumps if j.shape[-1] > 0]
    largest = list(jumps)
    means = [0.0]
    for k in range(1, longest + 1):
        if k > 1:   # the largest of k consecutive: of k - 1, and the jump after them (while the run fits)
            largest = [np.maximum(m[..., :-1], j[..., k - 1:]) if m.shape[-1] > 1 else m
                       for m, j in zip(largest, jumps)]
        means.append(float(sum(m.sum() for m in largest) / max(1, sum(m.size for m in largest))))
    return np.array(means)


def missed_targets(scores) -> list[str]:
    """The targets ``scores`` (``synth.score``'s values, or medians of them) miss, of ``seams``, ``straight``,
    ``evenness`` and ``swd``, in that order; a measure without a value (no seam, no map) misses nothing."""
    def value(key):
        found = scores.get(key)
        return None if found is None else float(found)

    seams, straight = value("seam_visibility"), value("straight_seam_visibility")
    share, even, swd = value("straight_seam_share") or 0.0, value("evenness"), value("swd_vs_shuffled_blocks")
    misses = {"seams": seams is not None and seams > SEAM_TARGET,
              "straight": straight is not None and share >= STRAIGHT_SHARE_FROM and straight > STRAIGHT_TARGET,
              "evenness": even is not None and even < EVENNESS_TARGET,
              "swd": swd is not None and swd > SWD_TARGET}
    return [name for name, missed in misses.items() if missed]


def cell_bounds(length: int, cell: int = EVENNESS_CELL) -> np.ndarray:
    """Cell index of each of ``length`` texels: ``round(length / cell)`` cells of near-equal size."""
    n = max(1, round(length / cell))
    return (np.arange(length) * n) // length


def evenness(coords: CoordMap, cell: int = EVENNESS_CELL) -> float:
    """``exp(entropy) / n`` of the use of the exemplar's ``n`` cells (about ``cell x cell`` texels each; a blended
    texel counts for both its sources, by weight): 1 = every cell used equally, 1 / n = one cell only."""
    eh, ew = coords.source_size
    row_cell, col_cell = cell_bounds(eh, cell), cell_bounds(ew, cell)
    n_cols = int(col_cell[-1]) + 1
    n = (int(row_cell[-1]) + 1) * n_cols

    def cells_of(c):
        return (row_cell[c[..., 0]] * n_cols + col_cell[c[..., 1]]).ravel()

    if coords.blend_weight.size:
        w = coords.blend_weight.ravel().astype(np.float64)
        use = (np.bincount(cells_of(coords.coords), 1 - w, n) + np.bincount(cells_of(coords.blend_coords), w, n))
    else:
        use = np.bincount(cells_of(coords.coords), minlength=n).astype(np.float64)
    p = use[use > 0] / use.sum()
    return float(np.exp(-(p * np.log(p)).sum()) / n)


def lattice_share(out_enc: np.ndarray, tile: int) -> float | None:
    """How much of ``out_enc [L, H, W, C]`` every ``tile x tile`` tile repeats at the same place, which the eye
    sees as a lattice: the larger of the :func:`recurring_share` of the relit values (the same band along every
    border, the same feature at every corner) and of their :func:`local_contrast`, standardised per tile
    (:func:`tile_standardised`: the outlines of pieces laid at the same place in every tile, whatever their
    colours, such as a grid of light and dark squares).  None without two whole tiles or without variance under
    some light."""
    values = recurring_share(out_enc, tile)
    if values is None:
        return None
    outlines = recurring_share(tile_standardised(local_contrast(out_enc), tile)[..., None], tile)
    return max(values, 0.0 if outlines is None else outlines)


def tile_standardised(images: np.ndarray, tile: int) -> np.ndarray:
    """``images [L, H, W]``'s whole ``tile x tile`` tiles, each less its mean over its own standard deviation (a
    flat tile: 0): where a tile's edges lie, whatever their strength, so that pieces whose colours differ from tile
    to tile but whose outlines lie at the same place count as recurring."""
    lights, height, width = images.shape
    rows, cols = height // tile, width // tile
    x = images[:, :rows * tile, :cols * tile].astype(np.float64).reshape(lights, rows, tile, cols, tile)
    centred = x - x.mean(axis=(2, 4), keepdims=True)
    spread = np.sqrt((centred ** 2).mean(axis=(2, 4), keepdims=True))
    standard = np.divide(centred, spread, out=np.zeros_like(centred), where=spread > 1e-12 * (1 + np.abs(x).max()))
    return standard.reshape(lights, rows * tile, cols * tile)


def recurring_share(out_enc: np.ndarray, tile: int) -> float | None:
    """The share of ``out_enc [L, H, W, C]``'s variance that depends only on the place inside a ``tile x tile``
    tile (its whole tiles, averaged over lights).

    A one-way analysis of variance with the ``tile^2`` places as groups and the ``n`` tiles as observations: the
    variance of the mean tile over its places, less the ``1 / n`` of the within-place variance that chance alone
    leaves in a mean of ``n`` tiles, over the total variance.  Estimates below 0 (chance) are reported as 0.
    None without two whole tiles or without variance under some light."""
    lights, height, width, channels = out_enc.shape
    rows, cols = (height // tile, width // tile) if tile > 0 else (0, 0)
    n = rows * cols
    if n < 2:
        return None
    x = out_enc[:, :rows * tile, :cols * tile].astype(np.float64)
    x = x.reshape(lights, rows, tile, cols, tile, channels).transpose(0, 2, 4, 1, 3, 5)
    x = x.reshape(lights, tile, tile, n, channels)
    place_mean = x.mean(axis=3, keepdims=True)
    grand_mean = place_mean.mean(axis=(1, 2), keepdims=True)
    between = ((place_mean - grand_mean) ** 2).sum(-1).mean(axis=(1, 2, 3))
    chance = ((x - place_mean) ** 2).sum(-1).mean(axis=(1, 2, 3)) / (n - 1)   # unbiased within-place variance / n
    total = ((x - grand_mean) ** 2).sum(-1).mean(axis=(1, 2, 3))
    # a constant image's variance is rounding left by the means, 1e-16 of its square or less
    if not np.all(total > 1e-12 * (x ** 2).sum(-1).mean(axis=(1, 2, 3))):
        return None
    return float(np.clip(np.mean((between - chance) / total), 0.0, 1.0))


def local_contrast(out_enc: np.ndarray, box: int = CONTRAST_BOX) -> np.ndarray:
    """``[L, H, W]``: the radiance jumps to the next texel across and down (:func:`neighbour_jumps`; at the image's
    last column and row the jump back, so that the border's jumps are drawn like the others) combined as a
    gradient magnitude, averaged over ``box x box`` texels: where the image has edges, whatever their colours."""
    from scipy.ndimage import uniform_filter
    across, down = neighbour_jumps(out_enc.astype(np.float64), wrap=False)
    if across.shape[2] > 1:
        across[:, :, -1] = across[:, :, -2]
    if down.shape[1] > 1:
        down[:, -1, :] = down[:, -2, :]
    return uniform_filter(np.sqrt(across ** 2 + down ** 2), size=(1, box, box), mode="nearest")


def shuffled_blocks(exemplar_size: tuple[int, int], size: tuple[int, int], block: int = BASELINE_BLOCK,
                    seed: int = 0) -> CoordMap:
    """The baseline a synthesizer must beat: ``block x block`` exemplar blocks laid at random, without matching
    (``block`` capped at the exemplar's shorter side)."""
    (eh, ew), (h, w) = exemplar_size, size
    block = max(1, min(block, eh, ew))
    rng = np.random.default_rng(seed)
    by, bx = -(-h // block), -(-w // block)
    oy = rng.integers(0, eh - block + 1, (by, bx))
    ox = rng.integers(0, ew - block + 1, (by, bx))
    rows, cols = np.mgrid[0:h, 0:w]
    coords = np.stack([oy[rows // block, cols // block] + rows % block,
                       ox[rows // block, cols // block] + cols % block], axis=-1).astype(np.int32)
    return CoordMap(coords, (eh, ew), wrap=False)


def baseline_block(exemplar_size: tuple[int, int]) -> int:
    """The shuffled-block baseline's block side for an exemplar: :data:`BASELINE_BLOCK`, at most half its
    shorter side (so that a baseline has blocks to shuffle)."""
    return max(1, min(BASELINE_BLOCK, min(exemplar_size) // 2))
