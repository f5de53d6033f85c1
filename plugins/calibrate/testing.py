"""Rendered mirror-sphere captures with known lights: JPEG photographs of chrome balls on a textured background
with a bright matte card, lit by a small lamp (for tests and ``btforge bench calibrate --synthetic``)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image

from btforge.lazy import lazy_module

ndimage = lazy_module("scipy.ndimage")


def fibonacci_lights(n: int, min_elevation_deg: float = 20.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    k = np.arange(n) + 0.5
    z = np.sin(np.radians(min_elevation_deg)) + (1 - np.sin(np.radians(min_elevation_deg))) * k / n
    phi = k * math.pi * (3 - math.sqrt(5)) + rng.uniform(0, 2 * math.pi)
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def render_capture(folder: Path, lights: np.ndarray, spheres, size=(240, 320), focal=None, lamp_deg=1.5,
                   dark=(), seed=1, quality: int = 80, principal=None) -> list[Path]:
    """JPEG q80 photographs of mirror spheres ``(x, y, r)`` on a textured background with a bright matte card,
    lit by a small lamp in each of ``lights``; images listed in ``dark`` have the lamp off.  With ``focal`` the
    camera is a pinhole with its principal point at ``principal`` (column, row; default the image centre)."""
    h, w = size
    rng = np.random.default_rng(seed)
    texture = ndimage.gaussian_filter(rng.random((h, w)), 2.0)
    texture = 0.15 + 0.5 * (texture - texture.min()) / np.ptp(texture)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    paths = []
    for index, light in enumerate(lights):
        image = texture * (0.4 + 0.6 * light[2])
        card = (rows > h - 60) & (rows < h - 20) & (cols > 20) & (cols < 80)
        image = np.where(card, 0.95 * light[2], image)  # a white matte target, as bright as the highlights
        for (sx, sy, sr) in spheres:
            if focal is None:
                nx, ny = (cols - sx) / sr, -(rows - sy) / sr
                inside = nx * nx + ny * ny < 1
                nz = np.sqrt(np.clip(1 - nx * nx - ny * ny, 0, None))
                normal = np.stack([nx, ny, nz], -1)
                view = np.broadcast_to([0.0, 0.0, 1.0], normal.shape)
            else:
                px, py = principal if principal is not None else ((w - 1) / 2, (h - 1) / 2)
                d = np.stack([(cols - px) / focal, -(rows - py) / focal, -np.ones_like(cols)], -1)
                d /= np.linalg.norm(d, axis=-1, keepdims=True)
                axis = np.array([(sx - px) / focal, -(sy - py) / focal, -1.0])
                axis /= np.linalg.norm(axis)
                centre = axis / math.sin(math.atan2(sr, math.hypot(math.hypot(sx - px, sy - py), focal)))
                b = d @ centre
                disc = b * b - (centre @ centre - 1)
                inside = disc > 0
                t = b - np.sqrt(np.clip(disc, 0, None))
                normal = t[..., None] * d - centre
                normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
                view = -d
            refl = 2 * np.sum(normal * view, -1, keepdims=True) * normal - view
            angle = np.degrees(np.arccos(np.clip(refl @ light, -1, 1)))
            lamp = 0.0 if index in dark else 4.0 * np.exp(-(angle / lamp_deg) ** 2)
            env = 0.05 + 0.04 * np.sin(3 * refl[..., 0]) * np.cos(2 * refl[..., 1])  # a dim, smooth room
            image = np.where(inside, env + lamp, image)
        image = image + rng.normal(0, 0.01, image.shape)
        pixels = (np.clip(image, 0, 1) ** (1 / 2.2) * 255).round().astype(np.uint8)
        path = folder / f"shot_{index:02d}.jpg"
        Image.fromarray(np.repeat(pixels[..., None], 3, axis=2)).save(path, quality=quality)
        paths.append(path)
    return paths
