"""Stationary procedural materials of different kinds, for judging texture synthesis on what it was not tuned on.

Each pattern is a tileable height field with an albedo, returned as a :class:`ProceduralMaterial` that
:func:`~btforge.plugins.demo.procedural.render_lights` renders under any lights (shading and cast shadows):

* ``stones``: raised stones (periodic Voronoi cells) with sharp edges and dark grout between them, each stone
  its own colour and speckle;
* ``plaster``: a grainy plaster, a fine granular relief over gentle undulations, with pale mottled colour;
* ``fibres``: strands lying mostly along one direction, each a raised round ridge with its own shade.
"""
from __future__ import annotations

import math

import numpy as np

from btforge.errors import BtforgeInputError

from .procedural import ProceduralMaterial, normals_from_height

PATTERNS = ("bumps", "stones", "plaster", "fibres")


def make_pattern(kind: str, height: int, width: int, *, seed: int = 0, relief: float = 4.0) -> ProceduralMaterial:
    """The ``kind`` of :data:`PATTERNS` (not ``bumps``, which is :func:`make_material`) at ``height x width``
    texels; ``relief`` scales its heights (texel widths)."""
    makers = {"stones": _stones, "plaster": _plaster, "fibres": _fibres}
    if kind not in makers:
        raise BtforgeInputError("demo pattern", f"expected one of {', '.join(makers)}, found {kind!r}",
                                "pick a pattern by name, or make_material() for bumps")
    if height < 8 or width < 8:
        raise BtforgeInputError("demo pattern", f"expected at least 8 x 8 texels, found {height} x {width}",
                                "make a larger material")
    rng = np.random.default_rng(seed)
    relief_map, albedo = makers[kind](rng, int(height), int(width))
    relief_map = relief * relief_map
    return ProceduralMaterial(height=relief_map.astype(np.float32), albedo=np.clip(albedo, 0.02, 1.0).astype(np.float32),
                              normals=normals_from_height(relief_map))


def _grain(rng: np.random.Generator, h: int, w: int, sigma: float) -> np.ndarray:
    """Tileable noise of about unit standard deviation with features of about ``sigma`` texels."""
    from scipy.ndimage import gaussian_filter
    field = gaussian_filter(rng.standard_normal((h, w)), sigma, mode="wrap")
    return field / max(field.std(), 1e-9)


def _stones(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Periodic Voronoi cells about 20 texels across; the height rises steeply from the cell border."""
    n = max(4, round(h * w / 20.0 ** 2))
    centres = rng.uniform(0, 1, (n, 2)) * (h, w)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    first = np.full((h, w), np.inf)
    second = np.full((h, w), np.inf)
    owner = np.zeros((h, w), np.int64)
    for i, (cr, cc) in enumerate(centres):
        dy = (rows - cr + h / 2) % h - h / 2
        dx = (cols - cc + w / 2) % w - w / 2
        d = np.hypot(dy, dx)
        closer = d < first
        second = np.where(closer, first, np.minimum(second, d))
        owner = np.where(closer, i, owner)
        first = np.where(closer, d, first)
    border = 0.5 * (second - first)               # distance to the cell border
    dome = np.clip(border / 2.5, 0.0, 1.0) ** 0.5  # a sharp rise over 2.5 texels, then a flat top
    height = dome * (1.0 + 0.15 * _grain(rng, h, w, 1.0)) * rng.uniform(0.7, 1.0, n)[owner]
    stone_colour = rng.uniform(0.35, 0.8, (n, 1)) * np.array([1.0, 0.9, 0.75]) * rng.uniform(0.93, 1.07, (n, 3))
    albedo = stone_colour[owner] * (1.0 + 0.12 * _grain(rng, h, w, 0.7))[..., None]
    grout = np.array([0.12, 0.11, 0.10])
    albedo = albedo * dome[..., None] + grout * (1.0 - dome[..., None])
    return height, albedo


def _plaster(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Fine granular relief (1-texel grains and some 3-texel lumps) over gentle undulations, mottled colour."""
    height = 0.35 * _grain(rng, h, w, 0.8) + 0.25 * _grain(rng, h, w, 2.5) + 0.4 * _grain(rng, h, w, 10.0)
    pits = _grain(rng, h, w, 1.2) < -2.0           # a few deep pits
    height = height - 0.8 * pits
    mottle = 0.08 * _grain(rng, h, w, 6.0) + 0.05 * _grain(rng, h, w, 1.0)
    albedo = np.array([0.78, 0.74, 0.66]) * (1.0 + mottle)[..., None]
    return 0.5 * height, albedo


def _fibres(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Strands 20-60 texels long, 1-2 texels thick, within 25 degrees of one direction, overlapping."""
    n = max(8, round(h * w / 90.0))
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    height = np.zeros((h, w))
    shade = np.full((h, w), 0.45)
    base = rng.uniform(0, math.pi)
    for _ in range(n):
        angle = base + math.radians(rng.uniform(-25, 25))
        ur, uc = math.sin(angle), math.cos(angle)
        cr, cc = rng.uniform(0, h), rng.uniform(0, w)
        half, radius = rng.uniform(10, 30), rng.uniform(0.8, 1.8)
        dy = (rows - cr + h / 2) % h - h / 2
        dx = (cols - cc + w / 2) % w - w / 2
        along = dy * ur + dx * uc
        across = -dy * uc + dx * ur
        inside = (np.abs(along) < half) & (np.abs(across) < radius)
        ridge = np.where(inside, np.sqrt(np.maximum(0.0, 1.0 - (across / radius) ** 2)) * radius / 1.8, 0.0)
        top = np.where(inside, ridge + 0.5 * height, 0.0)  # lies on what it crosses
        higher = top > height
        height = np.where(higher, top, height)
        shade = np.where(higher, rng.uniform(0.35, 0.9), shade)
    albedo = np.stack([shade, 0.92 * shade, 0.7 * shade], axis=-1) * (1 + 0.05 * _grain(rng, h, w, 0.7))[..., None]
    return 0.6 * height, albedo
