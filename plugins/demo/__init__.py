"""Built-in demo data: procedural materials (bumps, stones, plaster, fibres, cobbles, gravel, strands, stucco)
rendered under many lights on OpenCL."""
from __future__ import annotations

import dataclasses

import numpy as np

from btforge import Fact, Param, SampleStack, declare_stage, hookimpl

from .patterns import PATTERNS

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


def pattern_material(pattern: str, size, *, bumps: int = 40, bump_height: float = 4.0, seed: int = 0):
    """The :class:`~.procedural.ProceduralMaterial` of a ``pattern`` at ``size = [H, W]``."""
    from .procedural import make_material
    if pattern == "bumps":
        return make_material(size[0], size[1], bumps=bumps, bump_height=bump_height, seed=seed)
    from .patterns import make_pattern
    return make_pattern(pattern, size[0], size[1], seed=seed, relief=bump_height)


@declare_stage(
    "demo.material",
    outputs={"stack": "SampleStack"},
    params=[
        Param("size", "ints", (128, 128), "image size [H, W] in texels", length=2, low=1, high=8192),
        Param("lights", "int", 36, "number of lights, spread over the hemisphere", low=1, high=4096),
        Param("min_elevation", "float", 15.0, "lowest light elevation in degrees", low=0.0, high=89.0),
        Param("bumps", "int", 40, "number of bumps in the (tileable) height field", low=0),
        Param("bump_height", "float", 4.0, "bump height in texel widths", low=0.0),
        Param("shadows", "bool", True, "cast shadows from the height field"),
        Param("seed", "int", 0, "random seed of the material"),
        Param("pattern", "choice", "bumps", "the kind of material: bumps (cosine-cap bumps with a fine weave on "
              "soft colour regions), stones (raised stones with sharp edges and dark grout), plaster (grainy relief, "
              "mottled colour), fibres (strands mostly along one direction), cobbles (large flat cells in a few "
              "colours, narrow grooves), gravel (small pale cells), strands (long, nearly parallel strands), stucco "
              "(coarse plaster) or cracks (dried mud: flat cells parted by a network of thin dark cracks); 'bumps' "
              "is the only one that reads the param 'bumps', 'bump_height' scales every pattern's relief",
              choices=PATTERNS),
    ],
)
def demo_material(ctx, *, size, lights, min_elevation, bumps, bump_height, shadows, seed, pattern):
    """Render a procedural material under a dome of lights, on OpenCL.

    Lambertian shading with cast shadows found by marching the height field toward each light.  The result
    is linear float32 radiance, so a graph can be tried with no capture at hand.  Every pattern tiles and is
    stationary (the same kind of texture everywhere), as texture synthesis expects of an exemplar.
    """
    from .procedural import hemisphere_lights, render_lights
    material = pattern_material(pattern, size, bumps=bumps, bump_height=bump_height, seed=seed)
    directions = hemisphere_lights(lights, min_elevation_deg=min_elevation)
    radiance = render_lights(material, directions, shadows=shadows)
    names = tuple(f"light_{i:03d}" for i in range(lights))
    return {"stack": SampleStack(radiance[None], directions, np.array([[0.0, 0.0, 1.0]]), names=names)}


def _views_precheck(params, paths):
    return [Fact("stack", "views", params["views"], "param 'views'")]


@declare_stage(
    "demo.btf",
    outputs={"stack": "SampleStack"},
    params=[
        Param("size", "ints", (64, 64), "image size [H, W] in texels", length=2, low=1, high=4096),
        Param("lights", "int", 25, "number of lights, spread over the hemisphere", low=1, high=1024),
        Param("views", "int", 9, "number of views, spread over the hemisphere above 30 degrees", low=1, high=256),
        Param("specular", "float", 0.6, "strength of the glossy lobe", low=0.0),
        Param("shininess", "float", 40.0, "Blinn-Phong exponent of the glossy lobe", low=1.0, high=10000.0),
        Param("bump_height", "float", 3.0, "bump height in texel widths", low=0.0),
        Param("seed", "int", 0, "random seed of the material"),
        Param("store", "outpath", "", "render chunk by chunk into this zarr store (8-bit sRGB, like a measured BTF) "
              "instead of memory; '' keeps the linear float32 stack in memory"),
        Param("block", "ints", (32, 32), "texels per chunk [rows, columns] of the store", length=2, low=1, high=4096),
    ],
    side_effects=True,  # with a store it writes one; without, rendering is as cheap as reading a cache entry
    precheck=_views_precheck,
)
def demo_btf(ctx, *, size, lights, views, specular, shininess, bump_height, seed, store, block):
    """Render a procedural glossy material under many lights and views: a synthetic BTF.

    Each texel reflects ``albedo + specular * max(0, n.h)^shininess`` times ``max(0, n.l)``, with h the half
    vector of light and view, and cast shadows from the height field (the OpenCL renderer of
    ``demo.material``).  Views share one light set, as in measured BTFs; parallax is not simulated.  With
    ``store``, the BTF is rendered one chunk (all views and lights of a block of texels) at a time into a zarr
    store and returned read lazily from it, so a BTF far larger than memory can be made (256 x 256 x 81 x 81 is
    1.29 GB as 8-bit).
    """
    from .procedural import hemisphere_lights, make_material, render_lights
    material = make_material(size[0], size[1], bump_height=bump_height, seed=seed)
    light_dirs = hemisphere_lights(lights, min_elevation_deg=15.0)
    view_dirs = hemisphere_lights(views, min_elevation_deg=30.0)
    white = dataclasses.replace(material, albedo=np.ones_like(material.albedo))
    lit = render_lights(white, light_dirs)[..., 0]                       # max(0, n.l) x visibility, [L, H, W]
    half = light_dirs[None, :, :] + view_dirs[:, None, :]
    half /= np.linalg.norm(half, axis=2, keepdims=True)                    # [V, L, 3]

    def radiance(rows: slice, cols: slice, views: slice = slice(None)) -> np.ndarray:   # [v, L, h, w, 3] float32
        n_dot_h = np.clip(np.einsum("hwc,vlc->vlhw", material.normals[rows, cols], half[views]), 0.0, 1.0)
        glossy = specular * n_dot_h ** shininess
        band = lit[None, :, rows, cols, None] * (material.albedo[None, None, rows, cols] + glossy[..., None])
        return band.astype(np.float32)

    if not store:
        return {"stack": SampleStack(radiance(slice(None), slice(None)), light_dirs, view_dirs)}
    from btforge.buffers import linear_to_srgb8
    from btforge.store import create_store, open_stored_stack
    target = ctx.paths.output(store)
    array = create_store(target, (views, lights, size[0], size[1], 3), np.uint8, lights=light_dirs, views=view_dirs,
                         channels=("R", "G", "B"), encoding="srgb8", block=block)
    step_r, step_c = array.chunks[2], array.chunks[3]
    for r0 in range(0, size[0], step_r):
        for c0 in range(0, size[1], step_c):
            rows, cols = slice(r0, r0 + step_r), slice(c0, c0 + step_c)
            chunk = np.empty((views, lights) + material.normals[rows, cols].shape, np.uint8)
            for v in range(views):  # one view at a time: the float working set stays a few MB
                chunk[v:v + 1] = linear_to_srgb8(radiance(rows, cols, slice(v, v + 1)))
            array[:, :, rows, cols] = chunk
    ctx.note("written", str(target))
    return {"stack": open_stored_stack(target)}


@hookimpl
def btforge_stages():
    return [demo_material, demo_btf]
