"""Built-in demo data: a procedural bumpy, textured material rendered under many lights on OpenCL."""
from __future__ import annotations

import dataclasses

import numpy as np

from btforge import Param, SampleStack, declare_stage, hookimpl

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


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
    ],
)
def demo_btf(ctx, *, size, lights, views, specular, shininess, bump_height, seed):
    """Render a procedural glossy material under many lights and views: a small synthetic BTF.

    Each texel reflects ``albedo + specular * max(0, n.h)^shininess`` times ``max(0, n.l)``, with h the half
    vector of light and view, and cast shadows from the height field (the OpenCL renderer of
    ``demo.material``).  Views share one light set, as in measured BTFs; parallax is not simulated.
    """
    from .procedural import hemisphere_lights, make_material, render_lights
    material = make_material(size[0], size[1], bump_height=bump_height, seed=seed)
    light_dirs = hemisphere_lights(lights, min_elevation_deg=15.0)
    view_dirs = hemisphere_lights(views, min_elevation_deg=30.0)
    white = dataclasses.replace(material, albedo=np.ones_like(material.albedo))
    lit = render_lights(white, light_dirs)[..., 0]                       # max(0, n.l) x visibility, [L, H, W]
    half = light_dirs[None, :, :] + view_dirs[:, None, :]
    half /= np.linalg.norm(half, axis=2, keepdims=True)                    # [V, L, 3]
    n_dot_h = np.clip(np.einsum("hwc,vlc->vlhw", material.normals, half), 0.0, 1.0)
    glossy = specular * n_dot_h ** shininess                               # [V, L, H, W]
    radiance = lit[None, :, :, :, None] * (material.albedo[None, None] + glossy[..., None])
    return {"stack": SampleStack(radiance.astype(np.float32), light_dirs, view_dirs)}


@hookimpl
def btforge_stages():
    return [demo_material, demo_btf]
