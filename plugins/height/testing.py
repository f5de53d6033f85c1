"""Procedural captures with known geometry, for tests and benches: the demo material, matte or glossy, lit from
low lights so that it casts shadows, seen straight from above."""
from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class KnownCapture:
    images: np.ndarray     # [K, H, W, 3] linear radiance
    lights: np.ndarray     # [K, 3]
    heights: np.ndarray    # [H, W] the true height field
    normals: np.ndarray    # [H, W, 3] its normals
    shadowed: np.ndarray   # [K, H, W] bool: attached or cast shadow


def known_capture(size: int = 96, lights: int = 24, *, specular: float = 0.0, shininess: float = 40.0,
                  bump_height: float = 6.0, bumps: int = 30, min_elevation: float = 12.0, seed: int = 5) -> KnownCapture:
    """The demo material under ``lights`` (Lambert x cast shadows x (albedo + specular Blinn-Phong), view +z)."""
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights
    material = make_material(size, size, bumps=bumps, bump_height=bump_height, seed=seed)
    directions = hemisphere_lights(lights, min_elevation_deg=min_elevation)
    white = dataclasses.replace(material, albedo=np.ones_like(material.albedo))
    lit = render_lights(white, directions)[..., 0]
    half = directions + np.float32([0, 0, 1])
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    glossy = specular * np.clip(np.einsum("hwc,lc->lhw", material.normals, half), 0, 1) ** shininess
    images = lit[..., None] * (material.albedo[None] + glossy[..., None])
    return KnownCapture(images.astype(np.float32), directions, np.asarray(material.height),
                        np.asarray(material.normals), lit <= 0)


def angular_error_degrees(normals: np.ndarray, truth: np.ndarray, border: int = 2) -> np.ndarray:
    """Per-texel angle between two normal maps, in degrees, ``border`` texels left out on every side."""
    c = (slice(border, -border or None),) * 2
    cos = np.clip((normals[c].astype(np.float64) * truth[c]).sum(-1), -1, 1)
    return np.degrees(np.arccos(cos))
