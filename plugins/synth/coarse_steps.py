"""Straight-step visibility: brightness steps along straight lines between pieces, at a coarser scale than seams.

A synthesizer whose refinement breaks each copied piece's edge into many small seams can still leave a step in
brightness between two pieces, spread along a straight line: every seam edge is small, so seam visibility and
straight-seam visibility (per edge) miss it, while the eye sees the line at once.  This measure looks at the
pieces and the radiance at that coarser scale:

* the coarse map: the 4-connected pieces copied as one (constant source offset) of at least
  :data:`STEP_PIECE` texels, every other texel taking the offset of its nearest such piece (the small pieces a
  refinement scatters along an edge are absorbed, and the edge between the large pieces remains);
* the lines: axis-aligned segments of :data:`STEP_SEGMENT` texels, with a band :data:`STEP_BAND` texels wide
  on each side, :data:`STEP_GAP` texels from the line (a step spread over a few texels falls between the bands);
  a line lies on a coarse straight seam when at least :data:`STEP_SHARE` of its texels cross a coarse-map
  seam within :data:`STEP_GAP` texels of it;
* the step of a line: the difference of the two bands' means (colour), taken as the least over the segment's
  :data:`STEP_PARTS` parts along the whole segment's direction of difference (a step the eye follows holds
  along the whole line; a curved content edge crossing it does not), over the bands' own spread (RMS deviation
  plus :data:`STEP_FLOOR`: a step on flat ground shows, the same step in busy texture hides), averaged over
  lights;
* visibility: the mean step over the lines on coarse straight seams, over the mean of the steps the exemplar
  has at those lines' sources (for each texel beside the line, the exemplar's step across the line beside its
  source).  1: the steps along the pieces' straight edges are those the copied content has anyway.

Plain NumPy: summed-area tables give every band mean (0.15-0.25 s for a 256 x 256 output at 8 lights on a
shared 2-core machine).  A wrapping map's wrap-around lines are not measured.
"""
from __future__ import annotations

import numpy as np

from btforge.buffers import CoordMap

from .visibility import dominant_source, seam_masks

#: Length in texels of the line segments whose steps are measured.
STEP_SEGMENT = 32
#: Width in texels of the band on each side of a line.
STEP_BAND = 4
#: Texels between a line and each band (and how far a coarse seam may wander from the line).
STEP_GAP = 2
#: Parts of a segment the step must hold along.
STEP_PARTS = 4
#: Share of a segment's texels that must cross a coarse seam for the line to count.
STEP_SHARE = 0.75
#: Smallest piece (texels) the coarse map keeps.
STEP_PIECE = 64
#: Added to the bands' spread (domain units, about 2 % of white): a step on perfectly flat bands stays finite.
STEP_FLOOR = 0.02


def straight_step_visibility(out_enc: np.ndarray, ex_enc: np.ndarray, coords: CoordMap) -> float | None:
    """Mean step across lines on the map's coarse straight seams over the exemplar's steps at their sources
    (``out_enc``, ``ex_enc``: ``[L, H, W, C]`` relit images in one domain); None when no line qualifies, or the
    textures are too small for one segment and its bands."""
    smallest = max(STEP_SEGMENT, 2 * (STEP_BAND + STEP_GAP) + 1)
    if min(*out_enc.shape[1:3], *ex_enc.shape[1:3]) < smallest:
        return None
    src = dominant_source(coords)
    coarse = coarse_offsets(src)
    if coarse is None:
        return None
    out_tables, ex_tables = SummedAreas(out_enc), SummedAreas(ex_enc)
    steps, expected = 0.0, 0.0
    for axis in (0, 1):  # lines between rows, then between columns (everything transposed)
        src_t = src if axis == 0 else src.transpose(1, 0, 2)[..., ::-1]
        coarse_t = coarse if axis == 0 else coarse.transpose(1, 0, 2)
        on_seam = coarse_seam_share(coarse_t) >= STEP_SHARE
        steps += float(line_steps(out_tables.along(axis))[on_seam].sum())
        expected += float(steps_at_sources(line_steps(ex_tables.along(axis)), src_t)[on_seam].sum())
    if expected <= 0.0:
        return None
    return steps / expected


def coarse_offsets(src: np.ndarray) -> np.ndarray | None:
    """``[H, W, 2]`` source offset of each texel's nearest piece of at least :data:`STEP_PIECE` texels (a piece:
    4-connected texels whose sources are exemplar neighbours); None when there is no such piece."""
    from scipy.ndimage import distance_transform_edt, label
    h, w = src.shape[:2]
    offsets = src - np.stack(np.mgrid[0:h, 0:w], axis=-1)
    across_columns, across_rows = seam_masks(src[..., 0], src[..., 1], False)
    # texels at even positions, the links between them at odd ones: a seam is a missing link
    linked = np.zeros((2 * h - 1, 2 * w - 1), bool)
    linked[::2, ::2] = True
    linked[::2, 1::2] = ~across_columns[:, :-1]
    linked[1::2, ::2] = ~across_rows[:-1, :]
    pieces = label(linked)[0][::2, ::2]
    large = np.bincount(pieces.ravel())[pieces] >= STEP_PIECE
    if not large.any():
        return None
    nearest = distance_transform_edt(~large, return_distances=False, return_indices=True)
    return offsets[nearest[0], nearest[1]]


def coarse_seam_share(coarse: np.ndarray) -> np.ndarray:
    """``[lines, W - segment + 1]`` share of each segment's columns that cross a coarse seam (a change of coarse
    offset between rows) within :data:`STEP_GAP` texels of the line; line ``i`` lies between rows
    ``i + STEP_BAND + STEP_GAP - 1`` and ``i + STEP_BAND + STEP_GAP``, segment ``j`` spans columns ``j ..``."""
    h = coarse.shape[0]
    changes = (coarse[1:] != coarse[:-1]).any(axis=-1)      # pair (r, r + 1) at index r
    before = np.zeros((h, coarse.shape[1]), np.int32)
    before[1:] = np.cumsum(changes, axis=0)                   # before[r]: changes in pairs 0 .. r - 1
    first = np.arange(STEP_BAND + STEP_GAP, h - STEP_BAND - STEP_GAP + 1)   # first row below each line
    low = np.clip(first - 1 - STEP_GAP, 0, h - 1)
    high = np.clip(first + STEP_GAP, 0, h - 1)
    return segment_means((before[high] - before[low] > 0).astype(np.float64))


def segment_means(values: np.ndarray) -> np.ndarray:
    """Means of ``values [n, W]`` over every run of :data:`STEP_SEGMENT` consecutive columns."""
    total = np.zeros((values.shape[0], values.shape[1] + 1))
    total[:, 1:] = np.cumsum(values, axis=1)
    return (total[:, STEP_SEGMENT:] - total[:, :-STEP_SEGMENT]) / STEP_SEGMENT


class SummedAreas:
    """Summed-area tables of an image stack ``[L, H, W, C]`` and of its squared colour norm, channels first (so
    that sums over colour are sums of planes), from which every window mean is four look-ups."""

    def __init__(self, images: np.ndarray):
        planes = np.moveaxis(np.asarray(images, np.float64), -1, 0)             # [C, L, H, W]
        self.values = _summed(planes)
        self.squares = _summed(np.square(planes).sum(axis=0, keepdims=True))

    def along(self, axis: int) -> "SummedAreas":
        """The tables of the image transposed (lines between columns) when ``axis`` is 1."""
        if axis == 0:
            return self
        flipped = object.__new__(SummedAreas)
        flipped.values, flipped.squares = (np.ascontiguousarray(t.transpose(0, 1, 3, 2))
                                           for t in (self.values, self.squares))
        return flipped

    @property
    def shape(self) -> tuple[int, int]:
        return self.values.shape[2] - 1, self.values.shape[3] - 1

    def means(self, height: int, width: int, squares: bool = False) -> np.ndarray:
        """``[C, L, H - height + 1, W - width + 1]`` means over every window (by its top-left texel)."""
        t = self.squares if squares else self.values
        sums = t[..., height:, width:] - t[..., :-height, width:] - t[..., height:, :-width] + t[..., :-height, :-width]
        return (sums / (height * width)).astype(np.float32)


def _summed(planes: np.ndarray) -> np.ndarray:
    table = np.zeros(planes.shape[:-2] + (planes.shape[-2] + 1, planes.shape[-1] + 1))
    np.cumsum(planes, axis=-2, out=table[..., 1:, 1:])
    np.cumsum(table[..., 1:, 1:], axis=-1, out=table[..., 1:, 1:])
    return table


def line_steps(tables: SummedAreas) -> np.ndarray:
    """``[lines, W - segment + 1]`` step across each horizontal line segment (see the module docstring), averaged
    over lights; lines and segments indexed as in :func:`coarse_seam_share`."""
    part = STEP_SEGMENT // STEP_PARTS
    lines = tables.shape[0] - 2 * (STEP_BAND + STEP_GAP) + 1
    below = STEP_BAND + 2 * STEP_GAP                           # offset from a line's upper band to its lower one
    part_means = tables.means(STEP_BAND, part)                 # [C, L, H - band + 1, W - part + 1]
    n = part_means.shape[3] - (STEP_PARTS - 1) * part         # = W - segment + 1
    parts = [part_means[..., k * part:k * part + n] for k in range(STEP_PARTS)]
    band_means = sum(parts) / STEP_PARTS                       # a segment's band is its parts' bands side by side
    differences = [p[:, :, :lines] - p[:, :, below:below + lines] for p in parts]
    direction = band_means[:, :, :lines] - band_means[:, :, below:below + lines]
    direction /= np.maximum(np.sqrt(_colour_sum(np.square(direction))), 1e-12)
    held = _colour_sum(differences[0] * direction)
    for d in differences[1:]:
        np.minimum(held, _colour_sum(d * direction), out=held)
    return (np.maximum(held, 0.0) / (band_spread(tables, band_means, lines, below) + STEP_FLOOR)).mean(axis=0)


def _colour_sum(planes: np.ndarray) -> np.ndarray:
    """Sum over the first (colour) axis, plane by plane (faster than a reduction over a short leading axis)."""
    total = planes[0].copy()
    for plane in planes[1:]:
        total += plane
    return total


def band_spread(tables: SummedAreas, band_means: np.ndarray, lines: int, below: int) -> np.ndarray:
    """``[L, lines, W - segment + 1]`` RMS deviation of the two bands' texels from their own means."""
    squares = tables.means(STEP_BAND, STEP_SEGMENT, squares=True)[0]
    variance = np.maximum(squares - _colour_sum(np.square(band_means)), 0.0)
    return np.sqrt(0.5 * (variance[:, :lines] + variance[:, below:below + lines]))


def steps_at_sources(exemplar_steps: np.ndarray, src: np.ndarray) -> np.ndarray:
    """The exemplar's steps where an output's texels come from, per output line segment: each texel above a line
    brings the exemplar's step across the line below its source, each texel below one the step across the line
    above its source (segments centred on the source's column, clipped to the exemplar's lines)."""
    reach = STEP_BAND + STEP_GAP
    n_lines, n_segments = exemplar_steps.shape

    def step_at(first_row_below, column):
        return exemplar_steps[np.clip(first_row_below - reach, 0, n_lines - 1),
                              np.clip(column - STEP_SEGMENT // 2, 0, n_segments - 1)]

    as_upper = step_at(src[..., 0] + 1, src[..., 1])
    as_lower = step_at(src[..., 0], src[..., 1])
    first = np.arange(reach, src.shape[0] - reach + 1)
    return segment_means(0.5 * (as_upper[first - 1] + as_lower[first]))
