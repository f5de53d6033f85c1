"""Texture synthesis of reflectance functions: every synthesizer outputs a coordinate map into the exemplar.

``synth.materialize`` replays a map on any per-texel buffer (a stack, a PTM, Lafortune or SH model), so one synthesis
serves every representation, and ``synth.write_coords`` saves a map (blends included) as an EXR image.
"""
from __future__ import annotations

import numpy as np

from btforge import REQUIRED, Param, declare_stage, hookimpl

from . import jumpmap, kcoherence, quilting, scoring

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


@declare_stage("synth.materialize", deprecated_names=("materialize",), inputs={"coords": "CoordMap", "source": "PerTexel"}, outputs={"output": "=source"})
def materialize(ctx, coords, source):
    """Apply a coordinate map to any per-texel buffer; the output has the type of ``source``.

    Each output texel copies the exemplar texel the map names; where the map blends two texels, linear
    representations (radiance, linear rgb PTM, SH) are blended with the map's weight (an 8-bit sRGB stack in
    linear radiance, then re-encoded) and the others (Lafortune, lrgb or sRGB-space PTM) take the texel with the
    larger weight.
    """
    out = coords.apply(source)
    ctx.note("size", [out.height, out.width])
    return {"output": out}


@declare_stage("synth.crop", deprecated_names=("crop",), inputs={"input": "PerTexel"}, outputs={"output": "=input"},
               params=[Param("origin", "ints", (0, 0), "top-left texel [row, column]", length=2, low=0),
                       Param("size", "ints", REQUIRED, "size [H, W] of the crop", length=2, low=1)])
def crop(ctx, input, *, origin, size):
    """Cut a rectangle out of any per-texel buffer (a stack or a model), e.g. a small exemplar for synthesis."""
    from btforge.errors import BtforgeInputError
    (r0, c0), (h, w) = origin, size
    if r0 + h > input.height or c0 + w > input.width:
        raise BtforgeInputError("synth.crop", f"expected the crop to fit in the {input.height} x {input.width} input, found "
                                f"rows {r0}..{r0 + h - 1}, columns {c0}..{c0 + w - 1}", "move 'origin' or shrink 'size'")
    rows, cols = np.meshgrid(np.arange(r0, r0 + h), np.arange(c0, c0 + w), indexing="ij")
    return {"output": input.remap(rows, cols)}


@declare_stage("synth.write_coords", deprecated_names=("coords.write",), inputs={"coords": "CoordMap"},
               params=[Param("path", "outpath", REQUIRED, "the .exr file to write (relative to --out)")],
               side_effects=True)
def coords_write(ctx, coords, *, path):
    """Write a coordinate map, losslessly, as a float32 EXR.

    Channels: R = exemplar row, G = exemplar column, B = blend weight, and the layer ``blend`` (``blend.R``,
    ``blend.G``) = the row and column of the texel blended in (the texel itself where nothing is blended).  Header
    attributes ``btforgeSourceSize`` (the exemplar's [H, W]), ``btforgeWrap`` (1 when the map tiles) and
    ``btforgeTile`` (the side of a tiling's tiles, 0 for other maps).  An
    RGB viewer or reader shows the map and ignores the rest; float32 holds the coordinates exactly.
    """
    import OpenEXR

    from btforge.atomic import atomic_output_path
    h, w = coords.coords.shape[:2]
    blended = bool(coords.blend_weight.size)
    weight = coords.blend_weight if blended else np.zeros((h, w), np.float32)
    partner = coords.blend_coords if blended else coords.coords
    planes = {"R": coords.coords[..., 0], "G": coords.coords[..., 1], "B": weight,
              "blend.R": partner[..., 0], "blend.G": partner[..., 1]}
    channels = {name: np.ascontiguousarray(plane, np.float32) for name, plane in planes.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage,
              "btforgeSourceSize": np.array(coords.source_size, np.int32), "btforgeWrap": int(coords.wrap),
              "btforgeTile": int(coords.tile)}
    with atomic_output_path(ctx.paths.output(path)) as temporary:
        OpenEXR.File(header, channels).write(str(temporary))
    return {}


@hookimpl
def btforge_stages():
    return [materialize, crop, coords_write, *quilting.STAGES, *kcoherence.STAGES, *jumpmap.STAGES, *scoring.STAGES]


@hookimpl
def btforge_bench_commands():
    from .bench import bench_synthesis
    from .bench_commands import COMMANDS
    return {**COMMANDS, "synthesis": bench_synthesis}
