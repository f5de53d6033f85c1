"""Geometry-guided BTF synthesis after Liu, Yu & Shum (2001): ``liu.synthesize`` and ``liu.contact_sheet``.

A height field (recovered by ``height.from_shading`` or grown from one by a synthesizer) is rendered as
templates; real reference images are warped to every target setting and block-copied under the template's
guidance, so shadows and occlusion agree across lights and views.
"""
from __future__ import annotations

import numpy as np

from btforge import REQUIRED, Param, SampleStack, declare_stage, hookimpl
from btforge.errors import BtforgeInputError

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


def _grid_precheck(params, paths):
    from .settings import parse_grid
    grid = params.get("grid")
    parse_grid(grid, paths)
    return [paths.input(grid)] if isinstance(grid, str) else []


def _block_sizes(block_sizes):
    if not block_sizes or any(s < 3 or s % 2 == 0 for s in block_sizes):
        raise BtforgeInputError("liu.synthesize 'block_sizes'", f"expected odd sizes >= 3, found {list(block_sizes)}",
                                "e.g. [3, 5, 9]")
    return tuple(block_sizes)


@declare_stage(
    "liu.synthesize",
    inputs={"height": "HeightField", "references": "SampleStack"},
    outputs={"stack": "SampleStack", "templates": "SampleStack"},
    params=[
        Param("grid", "any", REQUIRED, "target settings: a .lvp path (its views x its lights), {views: [[x, y, z], "
              "...], lights: [...]} (every view with every light), or {view_tilts, view_azimuths, light_tilts, "
              "light_azimuths} in degrees"),
        Param("isotropic", "bool", True, "choose references by eq. 7 (rotations about the normal and the mirror "
              "image allowed) and rotate them to the target; false: eq. 6, no rotation"),
        Param("nearest", "int", 3, "M: the nearest reference images blended per target with eq. 8's weights "
              "(a count, not called 'references' because the input port has that name)", low=1, high=64),
        Param("block_sizes", "ints", (3, 5, 9), "odd block sides tried at each pixel (the best normalised SSD "
              "wins); holes are filled with 3 x 3 blocks"),
        Param("seed", "int", 0, "random seed (tie-breaks of the Harris order)"),
        Param("feather", "int", 2, "texels on each side of a block boundary blended with the neighbouring block's "
              "continuation, where it agrees with the template (0: hard block edges)", low=0, high=8),
        Param("relax", "int", 2, "sweeps of seam relaxation before feathering: each pixel may take the "
              "continuation of a neighbouring block where that lowers the colour jump across the block boundary, "
              "so boundaries move to where the blocks agree in colour (0: off)", low=0, high=64),
        Param("colour", "float", 1.0, "weight of colour agreement in the block matching: among the template's "
              "nearest blocks and the continuations of the neighbouring blocks, each block is chosen by its "
              "template SSD plus this times the mean squared colour difference between its continuation and the "
              "pixels already copied around it (0: the template alone, as in the paper)", low=0.0),
    ],
    precheck=_grid_precheck,
    version="3",
)
def liu_synthesize(ctx, height, references, *, grid, isotropic, nearest, block_sizes, seed, feather, relax, colour):
    """Synthesize a BTF of a height field on a grid of views x lights from real reference images.

    Liu, Yu & Shum (2001), sec. 6.  For every target setting: a template (grey shading of the height field with
    attached and cast shadows, occlusion and foreshortening, in the texture frame) is rendered on OpenCL; the
    ``nearest`` reference images by eq. 7 (or eq. 6) are rotated about the normal (and mirrored) to the target's
    light azimuth; each is block-copied under the template (histogram-matched template, Harris order, the best
    of ``block_sizes`` by normalised SSD, non-overlapping blocks, then holes filled with 3 x 3 blocks), each
    block chosen among the template's nearest blocks and its neighbours' continuations by its template SSD plus
    ``colour`` times its colour disagreement with the pixels already copied around it (the grey template
    cannot tell hues apart, so without it neighbouring blocks form colour islands); block boundaries are then
    moved texel by texel to where the blocks agree in colour (``relax`` sweeps), then
    blended over ``feather`` texels with the neighbouring block's continuation in the reference,
    as far as it agrees with the template, so no square block edges show; the copies are blended with eq. 8's
    weights.  References need not be registered to each other or to the height field.
    Images go one at a time into the output, so memory beyond the output stays flat.

    Outputs
    -------
    stack : SampleStack
        ``[V, L, H, W, C]`` on the grid, the height field's size, the references' channels.
    templates : SampleStack
        ``[V, L, H, W, 1]`` the templates (0 = shadow).
    """
    from .settings import parse_grid
    from .synthesis import synthesize
    views, lights = parse_grid(grid, ctx.paths)
    block_sizes = _block_sizes(block_sizes)
    stack, templates, stats = synthesize(height, references, views, lights, isotropic=isotropic, count=nearest,
                                         block_sizes=block_sizes, seed=seed, feather=feather, relax=relax,
                                         colour=colour)
    ctx.note("settings", int(len(views) * len(lights)))
    ctx.note("seconds", {k: round(v, 3) for k, v in stats["seconds"].items()})
    ctx.note("hole_fraction", round(stats["hole_pixels"] / max(stack.size // stack.shape[-1] * nearest, 1), 4))
    return {"stack": SampleStack(stack, lights, views, channels=references.channels),
            "templates": SampleStack(templates, lights, views, channels=("Y",))}


@declare_stage(
    "liu.contact_sheet",
    inputs={"stack": "SampleStack", "templates": "SampleStack", "references": "SampleStack"},
    params=[
        Param("path", "outpath", REQUIRED, "the PNG to write (relative to --out)"),
        Param("isotropic", "bool", True, "find the nearest reference by eq. 7 (as liu.synthesize did)"),
        Param("max_settings", "int", 12, "settings shown (evenly spaced over the grid)", low=1),
        Param("exposure", "float", 1.0, "multiplier applied to linear radiance before sRGB encoding", low=0.0),
    ],
    side_effects=True,
)
def liu_contact_sheet(ctx, stack, templates, references, *, path, isotropic, max_settings, exposure):
    """Write one PNG row per setting: template | synthesized image | nearest reference, warped to the setting.

    The template is scaled to the synthesized image's mean brightness; everything is sRGB-encoded.
    """
    from PIL import Image

    from btforge.atomic import atomic_write
    from btforge.buffers import linear_to_srgb8

    from .blockcopy import warp
    from .synthesis import choose_references, reference_table
    if templates.samples.shape[:4] != stack.samples.shape[:4]:
        raise BtforgeInputError("liu.contact_sheet 'templates'", f"expected the shape of 'stack' "
                                f"{stack.samples.shape[:4]}, found {templates.samples.shape[:4]}",
                                "wire both outputs of the same liu.synthesize node")
    ref_views, ref_lights, pairs = reference_table(references)
    n = stack.n_view * stack.n_light
    picks = np.unique(np.linspace(0, n - 1, min(max_settings, n)).round().astype(int))
    rows = []
    for i in picks:
        v, l = divmod(int(i), stack.n_light)
        image = stack.image(v, l)
        grey = np.repeat(templates.image(v, l)[..., :1], 3, 2)
        grey = grey * (image.mean() / max(float(grey.mean()), 1e-6))
        choice = choose_references(stack.views[v], stack.lights[l], ref_views, ref_lights, 1, isotropic)
        rv, rl = pairs[choice.indices[0]]
        ref, valid = warp(references.image(rv, rl), float(choice.rotations[0]), bool(choice.mirrored[0]), image.shape[:2])
        ref = ref * valid[..., None]  # black where the warped reference has no data
        tiles = [grey, image, ref]
        rows.append(np.concatenate([t if t.shape[2] == 3 else np.repeat(t[..., :1], 3, 2) for t in tiles], 1))
    sheet = linear_to_srgb8(np.concatenate(rows, 0) * exposure)
    with atomic_write(ctx.paths.output(path)) as handle:
        Image.fromarray(sheet).save(handle, format="PNG")
    ctx.note("settings_shown", int(len(picks)))
    return {}


@hookimpl
def btforge_stages():
    return [liu_synthesize, liu_contact_sheet]


@hookimpl
def btforge_bench_commands():
    from .bench import bench_liu
    return {"liu": bench_liu}
