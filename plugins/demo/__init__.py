"""Built-in demo data: a procedural bumpy, textured material rendered under many lights on OpenCL."""
from __future__ import annotations

import numpy as np

from btforge import Param, SampleStack, declare_stage, hookimpl


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
    ],
)
def demo_material(ctx, *, size, lights, min_elevation, bumps, bump_height, shadows, seed):
    """Render a procedural material (bumps on a coloured texture) under a dome of lights, on OpenCL.

    Lambertian shading with cast shadows found by marching the height field toward each light.  The result
    is linear float32 radiance, so a graph can be tried with no capture at hand.
    """
    from .procedural import hemisphere_lights, make_material, render_lights
    material = make_material(size[0], size[1], bumps=bumps, bump_height=bump_height, seed=seed)
    directions = hemisphere_lights(lights, min_elevation_deg=min_elevation)
    radiance = render_lights(material, directions, shadows=shadows)
    names = tuple(f"light_{i:03d}" for i in range(lights))
    return {"stack": SampleStack(radiance[None], directions, np.array([[0.0, 0.0, 1.0]]), names=names)}


@hookimpl
def btforge_stages():
    return [demo_material]
