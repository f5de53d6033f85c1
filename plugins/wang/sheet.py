"""A picture of a tile set: every tile relit at one light, laid out in a grid with its edge colours marked."""
from __future__ import annotations

import numpy as np

from btforge.buffers import ReflectanceModel, SampleStack, linear_to_srgb8

# Distinct marker colours (sRGB 8-bit): horizontal-edge colours first, vertical-edge ones after.
PALETTE = np.array([[230, 40, 40], [40, 170, 60], [40, 90, 230], [240, 200, 30], [200, 60, 200], [30, 200, 200],
                    [250, 130, 20], [120, 70, 30], [150, 150, 150], [0, 0, 0], [255, 255, 255], [100, 0, 160],
                    [0, 110, 110], [180, 180, 0], [255, 120, 160], [60, 60, 120]], np.uint8)


def relit_exemplar(exemplar, light: np.ndarray) -> np.ndarray:
    """Linear RGB ``[H, W, 3]`` of the exemplar at one light: a model evaluated there, a stack's nearest light."""
    if isinstance(exemplar, ReflectanceModel):
        values = exemplar.evaluate(light[None])[0, 0]
    elif isinstance(exemplar, SampleStack):
        view = int(np.argmax(exemplar.views[:, 2]))
        values = exemplar.image(view, int(np.argmax(exemplar.lights @ light)))
    else:
        from .features import appearance_features
        values = appearance_features(exemplar)[..., :3]
    values = np.asarray(values, np.float32)
    return np.repeat(values, 3, axis=2) if values.shape[2] == 1 else values[..., :3]


def tile_sheet(tiles, exemplar, light, columns: int = 0, gap: int = 0) -> np.ndarray:
    """``[rows, cols, 3]`` uint8: tiles in index order, each framed by bars in the colour of its four edges."""
    w = tiles.tile
    bar = max(2, w // 16)
    gap = gap or 2 * bar
    light = np.asarray(light, np.float64) / np.linalg.norm(light)
    image = relit_exemplar(exemplar, light)
    white = max(float(np.percentile(image, 99.5)), 1e-6)
    shown = linear_to_srgb8(tile_radiance(tiles, exemplar, light, image) / white)       # [T, w, w, 3]
    n = tiles.n_tiles
    columns = columns or int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / columns))
    cell = w + 2 * bar + gap
    out = np.full((rows * cell + gap, columns * cell + gap, 3), 255, np.uint8)

    def h_colour(c):
        return PALETTE[c % len(PALETTE)]

    def v_colour(c):
        return PALETTE[(tiles.colors_h + c) % len(PALETTE)]

    for t in range(n):
        y0, x0 = gap + (t // columns) * cell, gap + (t % columns) * cell
        north, east, south, west = tiles.tile_colors[t]
        out[y0:y0 + bar, x0 + bar:x0 + bar + w] = h_colour(north)
        out[y0 + bar + w:y0 + 2 * bar + w, x0 + bar:x0 + bar + w] = h_colour(south)
        out[y0 + bar:y0 + bar + w, x0:x0 + bar] = v_colour(west)
        out[y0 + bar:y0 + bar + w, x0 + bar + w:x0 + 2 * bar + w] = v_colour(east)
        out[y0 + bar:y0 + bar + w, x0 + bar:x0 + bar + w] = shown[t]
    return out


def tile_radiance(tiles, exemplar, light: np.ndarray, image: np.ndarray) -> np.ndarray:
    """``[T, w, w, 3]``: every tile's texels of ``image``, the exemplar relit at ``light``; where the set blends,
    each tile as ``synth.materialize`` replays it (its records mixed as radiance or as display values where they
    mix, else the heavier texel), relit at the same light."""
    if not tiles.blends:
        coords = tiles.tile_coords
        return image[coords[..., 0], coords[..., 1]]
    return np.stack([relit_exemplar(tiles.tile_map(t).apply(exemplar), light) for t in range(tiles.n_tiles)])
