"""Texture synthesis of reflectance functions: every synthesizer outputs a coordinate map into the exemplar.

``materialize`` replays a map on any per-texel buffer (a stack, a PTM, Lafortune or SH model), so one synthesis
serves every representation, and ``coords.write`` saves a map as an EXR image.
"""
from __future__ import annotations

import numpy as np

from btforge import REQUIRED, Param, declare_stage, hookimpl

from . import jumpmap, kcoherence, quilting, scoring


@declare_stage("materialize", inputs={"coords": "CoordMap", "source": "PerTexel"}, outputs={"output": "=source"})
def materialize(ctx, coords, source):
    """Apply a coordinate map to any per-texel buffer; the output has the type of ``source``.

    Each output texel copies the exemplar texel the map names; where the map blends two texels, linear
    representations (radiance, PTM, SH) are blended with the map's weight and non-linear ones (Lafortune)
    take the texel with the larger weight.
    """
    out = coords.apply(source)
    ctx.note("size", [out.height, out.width])
    return {"output": out}


@declare_stage("crop", inputs={"input": "PerTexel"}, outputs={"output": "=input"},
               params=[Param("origin", "ints", (0, 0), "top-left texel [row, column]", length=2, low=0),
                       Param("size", "ints", REQUIRED, "size [H, W] of the crop", length=2, low=1)])
def crop(ctx, input, *, origin, size):
    """Cut a rectangle out of any per-texel buffer (a stack or a model), e.g. a small exemplar for synthesis."""
    from btforge.errors import BtforgeInputError
    (r0, c0), (h, w) = origin, size
    if r0 + h > input.height or c0 + w > input.width:
        raise BtforgeInputError("crop", f"expected the crop to fit in the {input.height} x {input.width} input, found "
                                f"rows {r0}..{r0 + h - 1}, columns {c0}..{c0 + w - 1}", "move 'origin' or shrink 'size'")
    rows, cols = np.meshgrid(np.arange(r0, r0 + h), np.arange(c0, c0 + w), indexing="ij")
    return {"output": input.remap(rows, cols)}


@declare_stage("coords.write", inputs={"coords": "CoordMap"},
               params=[Param("path", "outpath", REQUIRED, "the .exr file to write (relative to --out)")],
               side_effects=True)
def coords_write(ctx, coords, *, path):
    """Write a coordinate map as a float32 EXR: R = exemplar row, G = exemplar column, B = blend weight."""
    from btforge.plugins.stackio.images import write_exr
    weight = coords.blend_weight if coords.blend_weight.size else np.zeros(coords.coords.shape[:2], np.float32)
    image = np.dstack([coords.coords.astype(np.float32), weight])
    write_exr(ctx.paths.output(path), image)
    return {}


@hookimpl
def btforge_stages():
    return [materialize, crop, coords_write, *quilting.STAGES, *kcoherence.STAGES, *jumpmap.STAGES, *scoring.STAGES]
