"""A start of exemplar pieces laid side by side, spread evenly over the exemplar and matched at their edges.

The output is tiled, in scanline order, with ``block x block`` copies of the exemplar.  Their origins are
stratified: the exemplar's origins are cut into strata about a block apart, and every stratum gives one piece
before any gives a second, so the whole exemplar is used about evenly.  Which of the open strata gives the next
piece, and where in it, is chosen by seam cost (as Graphcut Textures places a patch where it fits what is already
there): ``candidates`` origins are drawn from the open strata, and the one whose edges continue the pieces already
laid beside it best is taken.  Random pieces (``candidates: 1``) meet as unrelated colour areas along straight
block edges, which later passes can rarely hide; matched pieces continue the areas they meet.

The strata even out the pieces' origins, not the exemplar texels they cover: within a stratum the seam cost picks
the origins whose pieces are smoothest, and on a painting whose ornate border fills a few strata only in part the
start held the plain face almost alone.  With a copy ``budget`` (:func:`~.synthesizer.within_copy_budget`) a
piece whose exemplar area has been copied more than its share is not taken while others are.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .features import edge_padded, window_sums
from .synthesizer import within_copy_budget

#: Origins compared per piece by default (drawn from the open strata, several per stratum).
CANDIDATES = 64


@dataclasses.dataclass(frozen=True)
class Strata:
    """The exemplar's block origins cut into ``gy x gx`` strata about a block apart (row bounds ``lo_y``, column
    bounds ``lo_x``)."""

    lo_y: np.ndarray
    lo_x: np.ndarray

    @classmethod
    def of(cls, exemplar_size: tuple[int, int], block: int) -> "Strata":
        span_y, span_x = exemplar_size[0] - block + 1, exemplar_size[1] - block + 1
        gy, gx = max(1, round(span_y / block)), max(1, round(span_x / block))
        return cls((np.arange(gy + 1) * span_y) // gy, (np.arange(gx + 1) * span_x) // gx)

    @property
    def count(self) -> int:
        return (len(self.lo_y) - 1) * (len(self.lo_x) - 1)

    def origins(self, rng: np.random.Generator, strata: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One uniformly random origin (rows, columns) inside each of ``strata``."""
        iy, ix = np.divmod(strata, len(self.lo_x) - 1)
        oy = self.lo_y[iy] + (rng.random(len(strata)) * (self.lo_y[iy + 1] - self.lo_y[iy])).astype(np.int64)
        ox = self.lo_x[ix] + (rng.random(len(strata)) * (self.lo_x[ix + 1] - self.lo_x[ix])).astype(np.int64)
        return oy, ox


def matched_blocks(rng: np.random.Generator, features: np.ndarray, size: tuple[int, int], block: int,
                   candidates: int = CANDIDATES, wrap: bool = False, budget: float = 0.0) -> np.ndarray:
    """Flat exemplar sources ``[H * W]`` int32 of ``block x block`` pieces of ``features [eh, ew, d]`` (module
    docstring); ``wrap``: the last row and column of pieces are matched across the output's edges too; ``budget``
    > 0: only candidates within that copy budget are taken (the least-used always are)."""
    eh, ew = features.shape[:2]
    ho, wo = size
    b = max(1, min(block, eh, ew))
    strata = Strata.of((eh, ew), b)
    used = np.zeros(strata.count, np.int64)
    copied = np.zeros((eh, ew), np.int64)   # how often each exemplar texel has been laid
    padded = edge_padded(features)
    squares = np.einsum("nd,nd->n", padded, padded)
    src = np.full((ho, wo), -1, np.int64)
    for y0 in range(0, ho, b):
        for x0 in range(0, wo, b):
            open_strata = np.flatnonzero(used == used.min())
            per_stratum = max(1, -(-candidates // len(open_strata))) if candidates > 1 else 1
            drawn = np.repeat(open_strata, per_stratum) if candidates > 1 else rng.choice(open_strata, 1)
            oy, ox = strata.origins(rng, drawn)
            hh, ww = min(b, ho - y0), min(b, wo - x0)
            best = 0
            if candidates > 1:
                cost = edge_costs(ew, padded, squares, src, (y0, x0, hh, ww), oy, ox, wrap)
                if budget > 0:
                    use = window_sums(copied, (b, b))[oy, ox]
                    cost = np.where(within_copy_budget(use, copied.sum(), copied.size, b * b, budget), cost, np.inf)
                best = int(np.argmin(cost))
            used[drawn[best]] += 1
            copied[oy[best]:oy[best] + hh, ox[best]:ox[best] + ww] += 1
            rows, cols = np.mgrid[0:hh, 0:ww]
            src[y0:y0 + hh, x0:x0 + ww] = (oy[best] + rows) * ew + ox[best] + cols
    return src.ravel().astype(np.int32)


def edge_costs(ew: int, padded: np.ndarray, squares: np.ndarray, src: np.ndarray,
               region: tuple[int, int, int, int], oy: np.ndarray, ox: np.ndarray, wrap: bool) -> np.ndarray:
    """Seam cost, per candidate origin ``(oy, ox)``, of copying the block there into ``region`` (y0, x0, h, w)
    of ``src`` beside the texels already laid (``src >= 0``) on its four sides; ``padded`` is
    :func:`~.features.edge_padded` of an exemplar ``ew`` texels wide, ``squares`` its rows' squared norms.

    The cost of a seam edge between a laid texel (source a) and a block texel (source c), ``(dy, dx)`` from it,
    is how far each differs from the exemplar texel the other's source has in its place:
    ``|F(a + (dy, dx)) - F(c)|^2 + |F(a) - F(c - (dy, dx))|^2`` (zero where c continues a).
    """
    ho, wo = src.shape
    y0, x0, hh, ww = region
    cost = np.zeros(len(oy), np.float64)
    along_rows, along_cols = np.arange(hh), np.arange(ww)
    sides = (  # (outside texels' rows, columns), the block texels' offsets in the block, direction into it
        ((y0 + along_rows, np.full(hh, x0 - 1)), (along_rows, np.zeros(hh, np.int64)), (0, 1)),
        ((y0 + along_rows, np.full(hh, x0 + ww)), (along_rows, np.full(hh, ww - 1)), (0, -1)),
        ((np.full(ww, y0 - 1), x0 + along_cols), (np.zeros(ww, np.int64), along_cols), (1, 0)),
        ((np.full(ww, y0 + hh), x0 + along_cols), (np.full(ww, hh - 1), along_cols), (-1, 0)),
    )
    # Texels are read from the padded exemplar by flat index: a source's neighbour is at most one texel outside.
    stride = ew + 2
    origin = (oy + 1) * stride + ox + 1
    for (out_rows, out_cols), (in_rows, in_cols), (dy, dx) in sides:
        inside = (out_rows >= 0) & (out_rows < ho) & (out_cols >= 0) & (out_cols < wo)
        if wrap:
            out_rows, out_cols, inside = out_rows % ho, out_cols % wo, np.ones_like(inside)
        laid = np.zeros_like(inside)
        laid[inside] = src[out_rows[inside], out_cols[inside]] >= 0
        if not laid.any():
            continue
        a_rows, a_cols = np.divmod(src[out_rows[laid], out_cols[laid]], ew)
        a = (a_rows + 1) * stride + a_cols + 1
        c = origin[:, None] + (in_rows[laid] * stride + in_cols[laid])          # [n, m]
        step = dy * stride + dx
        # |x - y|^2 summed as |x|^2 - 2 x.y + |y|^2: the candidates' texels are gathered once per term
        for block_side, laid_side in ((c, a + step), (c - step, a)):
            y = padded[laid_side]
            cost += squares[block_side].sum(axis=1) - 2.0 * np.einsum("nmd,md->n", padded[block_side], y)
            cost += float(np.einsum("md,md->", y, y))
    return cost
