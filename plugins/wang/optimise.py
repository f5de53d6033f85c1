"""Texture optimisation of the tiles' interiors with their borders pinned.

Graph-cut filling leaves cuts where patches only roughly agree, most of them along the frame a tile's interior
was filled against.  The finished tiles then go through the shared refinement
(:func:`btforge.plugins.synth.refine.refine_map`: overlapping windows matched to the exemplar with an occurrence
term, whole windows kept where they match best and cut where the appearance agrees, then corrections), laid side
by side in one map so that the occurrence term spreads the whole set over the exemplar; the straight seams left are
re-cut with bridging pieces (:mod:`btforge.plugins.synth.bridging`) as quilting's are.  A ring of ``pin`` texels
along every tile border is held: those texels are the halves of the edge strips that every tile of the same edge
colour shares, so the tiles stay valid Wang tiles whatever happens inside.
"""
from __future__ import annotations

import math

import numpy as np

from btforge.buffers import CoordMap

ITERATIONS = 4     # texture-optimisation rounds
OCCURRENCE = 0.1   # weight of the refinement's occurrence term
PIN = 2            # texels along each tile border that keep their source


def border_ring(w: int, pin: int) -> np.ndarray:
    """``[w, w]`` mask of the ``pin`` outermost rows and columns of a tile."""
    ring = np.ones((w, w), bool)
    if 0 < 2 * pin < w:
        ring[pin:w - pin, pin:w - pin] = False
    return ring


def mosaic(tiles: np.ndarray, columns: int) -> np.ndarray:
    """``tiles [T, w, w, ...]`` laid row by row, ``columns`` across, into one array (empty cells zero)."""
    t, w = tiles.shape[:2]
    rows = -(-t // columns)
    padded = np.zeros((rows * columns, *tiles.shape[1:]), tiles.dtype)
    padded[:t] = tiles
    grid = padded.reshape(rows, columns, w, w, *tiles.shape[3:]).swapaxes(1, 2)
    return np.ascontiguousarray(grid.reshape(rows * w, columns * w, *tiles.shape[3:]))


def unmosaic(image: np.ndarray, t: int, w: int) -> np.ndarray:
    """The inverse of :func:`mosaic` for ``t`` tiles of ``w``."""
    rows, columns = image.shape[0] // w, image.shape[1] // w
    grid = image.reshape(rows, w, columns, w, *image.shape[2:]).swapaxes(1, 2)
    return np.ascontiguousarray(grid.reshape(rows * columns, w, w, *image.shape[2:])[:t])


def optimise_tiles(features: np.ndarray, tile_coords: np.ndarray, *, iterations: int = ITERATIONS,
                   occurrence: float = OCCURRENCE, pin: int = PIN, seed: int = 0) -> np.ndarray:
    """``tile_coords [T, w, w, 2]`` after ``iterations`` rounds of the shared refinement over appearance vectors
    ``features [H, W, D]``, every tile's ``pin``-texel border ring held (module docstring)."""
    from btforge.plugins.synth.bridging import TRIES as BRIDGE_TRIES
    from btforge.plugins.synth.refine import refine_map
    if iterations <= 0:
        return tile_coords
    t, w = tile_coords.shape[:2]
    columns = math.ceil(math.sqrt(t))
    ring = border_ring(w, max(1, pin))
    pinned = mosaic(np.broadcast_to(ring, (t, w, w)), columns)
    pinned[mosaic(np.ones((t, w, w), bool), columns) == 0] = True   # empty cells of the last row
    laid = CoordMap(mosaic(tile_coords, columns), features.shape[:2])
    src = refine_map(features, laid, iterations=iterations, occurrence=occurrence, seed=seed, pinned=pinned,
                     bridges=BRIDGE_TRIES).coords
    out = unmosaic(src, t, w)
    return out.astype(tile_coords.dtype)

