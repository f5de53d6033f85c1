"""Stationary procedural materials of different kinds, for judging texture synthesis on what it was not tuned on.

Each pattern is a tileable height field with an albedo, returned as a :class:`ProceduralMaterial` that
:func:`~btforge.plugins.demo.procedural.render_lights` renders under any lights (shading and cast shadows):

* ``stones``: raised stones (periodic Voronoi cells) with sharp edges and dark grout between them, each stone
  its own colour and speckle;
* ``plaster``: a grainy plaster, a fine granular relief over gentle undulations, with pale mottled colour;
* ``fibres``: strands lying mostly along one direction, each a raised round ridge with its own shade;
* ``cobbles``: large flat-topped cells (about 36 texels across) in a few distinct colours, with narrow grooves;
* ``gravel``: small cells (about 10 texels across) in two pale colours;
* ``strands``: long strands (60-120 texels) within 8 degrees of one direction, on a dark ground;
* ``stucco``: a coarse plaster, lumps and undulations larger than the plaster's and stronger mottles;
* ``cracks``: dried mud, flat pale cells about 30 texels across parted by a network of dark cracks about 2 texels
  wide, each cell's rim curled up a little: a network of thin lines, which a cut ends wherever it crosses one.

``cobbles``, ``gravel``, ``strands`` and ``stucco`` are kinds no synthesizer default was chosen on; ``cracks`` came
after them.
"""
from __future__ import annotations

import math

import numpy as np

from btforge.errors import BtforgeInputError

from .procedural import ProceduralMaterial, normals_from_height

PATTERNS = ("bumps", "stones", "plaster", "fibres", "cobbles", "gravel", "strands", "stucco", "cracks")


def make_pattern(kind: str, height: int, width: int, *, seed: int = 0, relief: float = 4.0) -> ProceduralMaterial:
    """The ``kind`` of :data:`PATTERNS` (not ``bumps``, which is :func:`make_material`) at ``height x width``
    texels; ``relief`` scales its heights (texel widths)."""
    makers = {"stones": _stones, "plaster": _plaster, "fibres": _fibres, "cobbles": _cobbles, "gravel": _gravel,
              "strands": _strands, "stucco": _stucco, "cracks": _cracks}
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


def _cells(rng: np.random.Generator, h: int, w: int, across: float) -> tuple[np.ndarray, np.ndarray, int]:
    """Periodic Voronoi cells about ``across`` texels wide: each texel's distance to its cell border, its cell's
    index, and the number of cells."""
    n = max(4, round(h * w / across ** 2))
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
    return 0.5 * (second - first), owner, n


def _stones(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Periodic Voronoi cells about 20 texels across; the height rises steeply from the cell border."""
    border, owner, n = _cells(rng, h, w, 20.0)
    dome = np.clip(border / 2.5, 0.0, 1.0) ** 0.5  # a sharp rise over 2.5 texels, then a flat top
    height = dome * (1.0 + 0.15 * _grain(rng, h, w, 1.0)) * rng.uniform(0.7, 1.0, n)[owner]
    stone_colour = rng.uniform(0.35, 0.8, (n, 1)) * np.array([1.0, 0.9, 0.75]) * rng.uniform(0.93, 1.07, (n, 3))
    albedo = stone_colour[owner] * (1.0 + 0.12 * _grain(rng, h, w, 0.7))[..., None]
    grout = np.array([0.12, 0.11, 0.10])
    albedo = albedo * dome[..., None] + grout * (1.0 - dome[..., None])
    return height, albedo


#: The cobbles' colours (brick red, blue, cream, green, grey) and the gravel's (cream, grey).
COBBLE_COLOURS = np.array([[0.8, 0.3, 0.2], [0.3, 0.5, 0.8], [0.85, 0.8, 0.6], [0.4, 0.7, 0.35], [0.6, 0.6, 0.6]])
GRAVEL_COLOURS = COBBLE_COLOURS[[2, 4]]


def _flat_cells(rng, h: int, w: int, across: float, groove: float, colours: np.ndarray):
    """Flat-topped cells of ``across`` texels, each of one of ``colours`` (scaled by +-15 %), their tops falling to a
    grey groove over ``groove`` texels; a gentle undulation over all."""
    border, owner, n = _cells(rng, h, w, across)
    top = np.clip(border / groove, 0.0, 1.0)
    height = top * rng.uniform(0.5, 1.0, n)[owner] + 0.1 * _grain(rng, h, w, 2.0)
    colour = colours[rng.integers(0, len(colours), n)] * rng.uniform(0.85, 1.15, (n, 1))
    albedo = colour[owner] * top[..., None] + np.array([0.3, 0.28, 0.25]) * (1.0 - top[..., None])
    return height, albedo


def _cobbles(rng, h: int, w: int):
    """Cells about 36 texels across, so that a 192-texel exemplar holds only about 30 of them."""
    return _flat_cells(rng, h, w, 36.0, 3.0, COBBLE_COLOURS)


def _gravel(rng, h: int, w: int):
    """Cells about 10 texels across, in two pale colours."""
    return _flat_cells(rng, h, w, 10.0, 1.5, GRAVEL_COLOURS)


def _plaster(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Fine granular relief (1-texel grains and some 3-texel lumps) over gentle undulations, mottled colour."""
    height = 0.35 * _grain(rng, h, w, 0.8) + 0.25 * _grain(rng, h, w, 2.5) + 0.4 * _grain(rng, h, w, 10.0)
    pits = _grain(rng, h, w, 1.2) < -2.0           # a few deep pits
    height = height - 0.8 * pits
    mottle = 0.08 * _grain(rng, h, w, 6.0) + 0.05 * _grain(rng, h, w, 1.0)
    albedo = np.array([0.78, 0.74, 0.66]) * (1.0 + mottle)[..., None]
    return 0.5 * height, albedo


def _stucco(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """The plaster coarser: 1.5-texel grains, 5-texel lumps and 14-texel undulations, mottles of 9 texels."""
    height = 0.3 * _grain(rng, h, w, 1.5) + 0.4 * _grain(rng, h, w, 5.0) + 0.5 * _grain(rng, h, w, 14.0)
    mottle = 0.18 * _grain(rng, h, w, 9.0) + 0.06 * _grain(rng, h, w, 1.5)
    albedo = np.array([0.7, 0.62, 0.55]) * (1.0 + mottle)[..., None]
    return 0.6 * height, albedo


def _cracks(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Periodic cells about 30 texels across; a crack where the distance to the cell border is under about a
    texel, falling to a dark floor; the cells' rims, within 12 texels of a crack, raised by up to a third."""
    border, owner, n = _cells(rng, h, w, 30.0)
    flat = np.clip(border / 1.2, 0.0, 1.0)
    curl = 0.3 * np.clip(1.0 - border / 12.0, 0.0, 1.0)
    height = flat * (1.0 + curl) + 0.1 * _grain(rng, h, w, 2.0)
    mud = np.array([0.72, 0.6, 0.45]) * rng.uniform(0.9, 1.1, n)[owner][..., None]
    albedo = mud * (1.0 + 0.08 * _grain(rng, h, w, 1.5))[..., None]
    return height, albedo * flat[..., None] + 0.08 * (1.0 - flat[..., None])


def _fibres(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Strands 20-60 texels long, 1-2 texels thick, within 25 degrees of one direction, overlapping."""
    return _laid_strands(rng, h, w, area=90.0, half_length=(10, 30), spread=25, radius=(0.8, 1.8), ground=0.45,
                         tint=(1.0, 0.92, 0.7))


def _strands(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Strands 60-120 texels long, 2-5 texels thick, within 8 degrees of one direction, tan on a dark ground."""
    return _laid_strands(rng, h, w, area=60.0, half_length=(30, 60), spread=8, radius=(1.0, 2.5), ground=0.3,
                         tint=(0.8, 0.6, 0.35))


def _laid_strands(rng, h: int, w: int, *, area: float, half_length, spread: float, radius, ground: float, tint):
    """One strand per ``area`` texels, each a raised round ridge lying on what it crosses, within ``spread``
    degrees of one random direction, with its own shade (0.35-0.9) over a ``ground`` shade; ``tint``: RGB factors."""
    n = max(8, round(h * w / area))
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    height = np.zeros((h, w))
    shade = np.full((h, w), ground)
    base = rng.uniform(0, math.pi)
    for _ in range(n):
        angle = base + math.radians(rng.uniform(-spread, spread))
        ur, uc = math.sin(angle), math.cos(angle)
        cr, cc = rng.uniform(0, h), rng.uniform(0, w)
        half, thick = rng.uniform(*half_length), rng.uniform(*radius)
        dy = (rows - cr + h / 2) % h - h / 2
        dx = (cols - cc + w / 2) % w - w / 2
        along = dy * ur + dx * uc
        across = -dy * uc + dx * ur
        inside = (np.abs(along) < half) & (np.abs(across) < thick)
        ridge = np.where(inside, np.sqrt(np.maximum(0.0, 1.0 - (across / thick) ** 2)) * thick / 1.8, 0.0)
        top = np.where(inside, ridge + 0.5 * height, 0.0)  # lies on what it crosses
        higher = top > height
        height = np.where(higher, top, height)
        shade = np.where(higher, rng.uniform(0.35, 0.9), shade)
    albedo = shade[..., None] * np.asarray(tint) * (1 + 0.05 * _grain(rng, h, w, 0.7))[..., None]
    return 0.6 * height, albedo
