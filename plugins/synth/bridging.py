"""Bridging patches over straight seams, offered to the re-cut (:mod:`.recut`) as a third kind of proposal.

A straight seam between two flat areas of slightly different colour survives the re-cut: the continuations of
its two sides differ everywhere along the band by about the same amount, so the cheapest cut between them is the
straight one.  What removes it is a third piece of the exemplar that joins both sides, such as a place where the
exemplar itself passes from the one colour to the other.  Graphcut Textures (Kwatra et al. 2003) places new
patches over its costliest seams for the same reason.

Only runs whose mean appearance step across the seam is at least the exemplar's mean step between neighbours
are bridged: the others already look like the exemplar's own edges.  Per such run, a diamond-shaped region
centred on the run (the run's half length plus :data:`MARGIN` along it, :data:`ACROSS` texels across) is matched
against every placement in the exemplar: the sum of squared appearance differences over the region, computed for
all placements at once by FFT correlation.  The placements that just
continue a source already in the region (the re-cut's own proposals) are left out; the best :data:`TRIES`
placements at least :data:`APART` texels apart are offered, one expansion move each (all runs at once).  The
region is a diamond because the cut may take all of it: its sides are staircases, never straight runs.
"""
from __future__ import annotations

import numpy as np

from .visibility import STRAIGHT_RUN, run_labels

#: Half width in texels of a bridging region across its seam.
ACROSS = 8
#: Texels a bridging region reaches beyond each end of its run.
MARGIN = 4
#: Bridging placements offered per run.
TRIES = 3
#: Least distance in texels between two placements offered for one run, and from the continuation of a source.
APART = 3


class ExemplarSpectrum:
    """The exemplar's appearance ``texels [eh, ew, d]`` and its squared norms, in the frequency domain once, so
    that each region's match against every placement costs one transform of the region and one inverse."""

    def __init__(self, texels: np.ndarray):
        from scipy import fft
        self.texels = texels
        self.shape = texels.shape[:2]
        values = texels.astype(np.float32)  # single precision: distances rank placements, several units apart
        self.values = fft.rfft2(values, axes=(0, 1))
        self.norms = fft.rfft2((values ** 2).sum(axis=-1))
        steps = [np.diff(values, axis=axis) for axis in (0, 1)]
        self.neighbour_step = float(np.mean([(step ** 2).sum(axis=-1).mean() for step in steps]))

    def distances(self, region: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Sum of squared differences between ``region [rh, rw, d]`` (where ``mask``) and the exemplar at every
        placement ``[eh - rh + 1, ew - rw + 1]``.  A circular correlation of the exemplar's size holds every
        placement that lies wholly inside the exemplar without wrapping."""
        from scipy import fft
        rh, rw = mask.shape
        weight = mask.astype(np.float32)
        flipped = (region * weight[..., None])[::-1, ::-1]
        spectrum = self.norms * _padded_rfft2(weight[::-1, ::-1], self.shape)
        spectrum -= 2.0 * (self.values * _padded_rfft2(flipped, self.shape)).sum(axis=-1)
        full = fft.irfft2(spectrum, s=self.shape)
        return full[rh - 1:, rw - 1:] + float((flipped ** 2).sum())


def _padded_rfft2(region: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``rfft2`` over the first two axes of ``region`` zero-padded to ``shape``: the rows first, so that only the
    region's own rows are transformed (the padding rows are zero), then the columns (about 1.7 x faster for a
    region a tenth of the exemplar's height)."""
    from scipy import fft
    return fft.fft(fft.rfft(region, n=shape[1], axis=1), n=shape[0], axis=0)


def diamond(half_along: float, half_across: float, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``mask, dy, dx`` of a diamond around the origin: ``half_along`` along a run in direction ``axis`` (0:
    down the rows), ``half_across`` across it."""
    half_y, half_x = (half_along, half_across) if axis == 0 else (half_across, half_along)
    dy, dx = np.mgrid[-int(half_y):int(half_y) + 1, -int(half_x):int(half_x) + 1]
    return np.abs(dy) / half_y + np.abs(dx) / half_x <= 1.0, dy, dx


def straight_run_centres(run_mask: np.ndarray, axis: int, step: np.ndarray | None = None,
                         least: float = 0.0) -> list[tuple[int, int, int]]:
    """``(row, col, length)`` per straight run of seam edges in ``run_mask`` (``axis`` 0: vertical runs of edges
    between a texel and its right neighbour; 1: horizontal runs between a texel and the one below) whose mean
    ``step`` (per edge, optional) is at least ``least``; the centre is the texel on the first side of the run's
    middle edge."""
    from scipy import ndimage
    labels, _ = run_labels(run_mask, axis)
    runs = []
    for label, (rows, cols) in enumerate(ndimage.find_objects(labels), start=1):
        length = (rows.stop - rows.start) if axis == 0 else (cols.stop - cols.start)
        visible = step is None or step[rows, cols][labels[rows, cols] == label].mean() >= least
        if length >= STRAIGHT_RUN and visible:
            runs.append(((rows.start + rows.stop - 1) // 2, (cols.start + cols.stop - 1) // 2, length))
    return runs


def bridging_proposals(spectrum: ExemplarSpectrum, src: np.ndarray, wrap: bool,
                       runs: list[tuple[np.ndarray, int]], pinned: np.ndarray, tries: int = TRIES) -> list[np.ndarray]:
    """``tries`` proposal maps (flat exemplar indices, -1: none): in the k-th, the region of every straight
    run of ``runs`` (``(run_mask, axis)`` pairs, as :func:`.recut.straight_runs` gives them) offers its k-th best
    placement (module docstring)."""
    h, w = src.shape
    eh, ew = spectrum.shape
    flat = spectrum.texels.reshape(eh * ew, -1)
    proposals = [np.full((h, w), -1, np.int64) for _ in range(tries)]
    appearance = flat[src]
    steps = [((np.roll(appearance, -1, axis=1 - axis) - appearance) ** 2).sum(axis=-1) for axis in (0, 1)]
    for row, col, length, axis in ((*centre, axis) for run_mask, axis in runs
                                   for centre in straight_run_centres(run_mask, axis, steps[axis],
                                                                      spectrum.neighbour_step)):
        mask, dy, dx = diamond(length / 2 + MARGIN, ACROSS, axis)
        if mask.shape[0] > eh or mask.shape[1] > ew:
            continue
        # centred on the edge: the far side of the run's middle edge is one texel on
        rows, cols = row + dy + (axis == 1), col + dx + (axis == 0)
        inside = np.ones_like(mask) if wrap else (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
        rows, cols = (rows % h, cols % w) if wrap else (np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1))
        usable = mask & inside
        here = src[rows, cols]
        distance = spectrum.distances(flat[here], usable)
        _rule_out_continuations(distance, here[usable], dy[usable] - dy.min(), dx[usable] - dx.min(), ew)
        free = usable & ~pinned[rows, cols]
        for proposal in proposals:
            best = np.unravel_index(int(np.argmin(distance)), distance.shape)
            if not np.isfinite(distance[best]):
                break
            _rule_out_near(distance, *best)
            placed = (best[0] + dy - dy.min()) * ew + best[1] + dx - dx.min()
            proposal[rows[free], cols[free]] = placed[free]
    return proposals


def _rule_out_continuations(distance: np.ndarray, sources: np.ndarray, dy: np.ndarray, dx: np.ndarray,
                            ew: int) -> None:
    """Mark as unusable the placements within :data:`APART` of one that continues a source in the region."""
    sy, sx = np.divmod(sources, ew)
    for top, left in set(zip((sy - dy).tolist(), (sx - dx).tolist())):
        _rule_out_near(distance, top, left)


def _rule_out_near(distance: np.ndarray, top: int, left: int) -> None:
    distance[max(0, top - APART):max(0, top + APART + 1), max(0, left - APART):max(0, left + APART + 1)] = np.inf
