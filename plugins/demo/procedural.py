"""A procedural demo material - bumps on a coloured ground - and its rendering under a set of lights.

The material is a tileable height field (a sum of cosine-cap bumps placed with wrap-around) with a linear RGB
albedo and the normals of the height field.  :func:`render_lights` shades it with Lambert's law and casts
shadows by marching the height field toward each light, on OpenCL; :func:`render_lights_numpy` is the plain
NumPy reference that performs the same float32 arithmetic in the same order, so both give the same image up to
rare ties at shadow boundaries.  Together they give a demo graph a synthetic RTI capture that needs no files.

Frame convention
----------------
Texel ``[row, col]`` sits at ``x = col``, ``y = -row`` (x to the right, y up the image, as in RTI light-position
files), z out of the surface, all in texel widths.  A light ``(1, 0, z)`` therefore shines from the right of the
image and ``(0, 1, z)`` from its top.  Heights are in texel widths too: a bump of height 3 rises 3 texels.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from btforge.backend import get_backend
from btforge.buffers import check_array, freeze_fields, unit_directions
from btforge.errors import BtforgeInputError
from btforge.numerics import fibonacci_directions

__all__ = [
    "ProceduralMaterial",
    "make_material",
    "normals_from_height",
    "hemisphere_lights",
    "render_lights",
    "render_lights_numpy",
    "MARCH_STEP_TEXELS",
    "MAX_MARCH_LENGTH_FACTOR",
]

KERNEL_FILE = Path(__file__).with_name("procedural.cl")

#: Horizontal distance between two height samples of the shadow march (texel widths).
MARCH_STEP_TEXELS = 0.5
#: A march is never longer than this many times ``max(H, W)``: bounds grazing and horizon lights.
MAX_MARCH_LENGTH_FACTOR = 4
#: Lights whose horizontal component is below this are treated as at the zenith (no march).
_ZENITH_HORIZONTAL_EPS = 1e-6
#: Device memory allowed for one chunk of rendered lights.
_OUTPUT_CHUNK_BYTES = 128 << 20


# ----------------------------------------------------------------------------------------------- material


@dataclasses.dataclass(frozen=True, eq=False)
class ProceduralMaterial:
    """A height field with albedo and normals, all on the same ``H x W`` texel grid.

    Attributes
    ----------
    height
        ``float32 [H, W]``, in texel widths.
    albedo
        ``float32 [H, W, 3]``, linear RGB in ``(0, 1]``.
    normals
        ``float32 [H, W, 3]``, unit vectors with ``z > 0`` (frame in the module docstring).

    The arrays are validated and made read-only on construction.
    """

    height: np.ndarray
    albedo: np.ndarray
    normals: np.ndarray

    def __post_init__(self):
        owner = "ProceduralMaterial"
        height = check_array("height", self.height, ("H", "W"), np.float32, finite=True, owner=owner)
        h, w = height.shape
        albedo = check_array("albedo", self.albedo, (h, w, 3), np.float32, finite=True, owner=owner)
        normals = check_array("normals", self.normals, (h, w, 3), np.float32, finite=True, owner=owner)
        if h == 0 or w == 0:
            raise BtforgeInputError(f"{owner} 'height'", f"must have at least one texel, got shape {height.shape}")
        if albedo.min() <= 0.0 or albedo.max() > 1.0:
            raise BtforgeInputError(f"{owner} 'albedo'", f"must lie in (0, 1], found [{albedo.min()}, {albedo.max()}]")
        norms = np.linalg.norm(normals.astype(np.float64), axis=-1)
        if np.abs(norms - 1.0).max() > 1e-4 or normals[..., 2].min() <= 0.0:
            raise BtforgeInputError(f"{owner} 'normals'", "must be unit vectors with z > 0",
                                    "derive them with normals_from_height()")
        freeze_fields(self, height=height, albedo=albedo, normals=normals)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.height.shape  # type: ignore[return-value]


def normals_from_height(height: np.ndarray) -> np.ndarray:
    """Unit normals ``float32 [H, W, 3]`` of a periodic height field, from wrap-around central differences.

    Parameters
    ----------
    height
        ``[H, W]`` heights in texel widths.

    Returns
    -------
    numpy.ndarray
        ``(-dh/dx, -dh/dy, 1)`` normalised, with ``y`` up the image (so ``dh/dy`` differences the row above
        minus the row below).
    """
    h = np.asarray(height, dtype=np.float64)
    dh_dx = 0.5 * (np.roll(h, -1, axis=1) - np.roll(h, 1, axis=1))
    dh_dy = 0.5 * (np.roll(h, 1, axis=0) - np.roll(h, -1, axis=0))
    normals = np.stack([-dh_dx, -dh_dy, np.ones_like(h)], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    return normals.astype(np.float32)


def _wrapped_offsets(coords: np.ndarray, centre: float, period: int) -> np.ndarray:
    """Signed distance from ``centre`` to ``coords`` on a circle of length ``period`` (minimum image)."""
    return (coords - centre + 0.5 * period) % period - 0.5 * period


def _periodic_noise(rng: np.random.Generator, rows: np.ndarray, cols: np.ndarray, h: int, w: int,
                    n_modes: int, max_frequency: int) -> np.ndarray:
    """Smooth tileable noise in about ``[-1, 1]``: a few random plane waves of whole periods across the grid."""
    field = np.zeros((h, w))
    fy = rng.integers(-max_frequency, max_frequency + 1, size=n_modes)
    fx = rng.integers(0, max_frequency + 1, size=n_modes)
    fx[(fx == 0) & (fy == 0)] = 1  # a constant mode would carry no variation
    phases = rng.uniform(0.0, 2.0 * np.pi, size=n_modes)
    amplitudes = rng.uniform(0.5, 1.0, size=n_modes)
    for a, u, v, phase in zip(amplitudes, fx, fy, phases):
        field += a * np.cos(2.0 * np.pi * (u * cols[None, :] / w + v * rows[:, None] / h) + phase)
    return field / amplitudes.sum()


# A few ground colours (linear RGB) the albedo blends between: clay, moss, slate, ochre.
_PALETTE = np.array([
    [0.62, 0.30, 0.18],
    [0.25, 0.45, 0.16],
    [0.22, 0.30, 0.52],
    [0.75, 0.58, 0.20],
])


def make_material(height: int, width: int, *, bumps: int = 40, bump_height: float = 4.0,
                  seed: int = 0) -> ProceduralMaterial:
    """A tileable procedural material: cosine-cap bumps on a ground of smoothly blended colours.

    Parameters
    ----------
    height, width
        Texel grid size ``H x W`` (at least 1 each).
    bumps
        Number of bumps (0 gives a flat field).
    bump_height
        Peak height of the tallest single bump, in texel widths; each bump gets 60-100 % of it (overlapping
        bumps add up).  Negative values make dents.
    seed
        Seed of the random generator; the same arguments always give the same material.

    Returns
    -------
    ProceduralMaterial
        Periodic in both axes: every bump and every colour wave wraps around the edges, so the material tiles.
    """
    if int(height) != height or int(width) != width or height < 1 or width < 1:
        raise BtforgeInputError("make_material", f"expected a size of at least 1 x 1 texels, got {height} x {width}")
    if int(bumps) != bumps or bumps < 0:
        raise BtforgeInputError("make_material 'bumps'", f"expected a count >= 0, got {bumps}")
    if not math.isfinite(bump_height):
        raise BtforgeInputError("make_material 'bump_height'", f"expected a finite number, got {bump_height}")
    h, w, bumps = int(height), int(width), int(bumps)
    rng = np.random.default_rng(seed)
    rows = np.arange(h, dtype=np.float64)
    cols = np.arange(w, dtype=np.float64)

    # Bumps sized so that ``bumps`` of them cover about three quarters of the area; a radius at most half the shorter side keeps
    # the minimum-image distance exact, so a bump is round and smooth where it crosses an edge.
    typical_radius = math.sqrt(h * w / max(bumps, 1)) * 0.5
    max_radius = max(1.0, 0.5 * min(h, w))
    centres_row = rng.uniform(0.0, h, size=bumps)
    centres_col = rng.uniform(0.0, w, size=bumps)
    radii = np.clip(typical_radius * rng.uniform(0.6, 1.4, size=bumps), 1.0, max_radius)
    peaks = bump_height * rng.uniform(0.6, 1.0, size=bumps)
    relief = np.zeros((h, w))
    for cr, cc, radius, peak in zip(centres_row, centres_col, radii, peaks):
        dy = _wrapped_offsets(rows, cr, h)
        dx = _wrapped_offsets(cols, cc, w)
        distance = np.sqrt(dy[:, None] ** 2 + dx[None, :] ** 2)
        # Cosine cap: zero slope at the rim and at the top, so the normals stay continuous.
        relief += np.where(distance < radius, 0.5 * peak * (1.0 + np.cos(np.pi * np.minimum(distance / radius, 1.0))), 0.0)

    # Ground colour: soft regions, each palette colour weighted by its own smooth noise field.
    sharpness = 6.0
    weights = np.stack([np.exp(sharpness * _periodic_noise(rng, rows, cols, h, w, n_modes=3, max_frequency=3))
                        for _ in range(len(_PALETTE))], axis=-1)
    weights /= weights.sum(axis=-1, keepdims=True)
    albedo = weights @ _PALETTE

    # Bumps are darker and carry a fine weave so they read as a different material; the weave has a whole
    # number of periods across the grid to stay tileable.
    magnitude = np.abs(relief)
    bumpiness = magnitude / magnitude.max() if magnitude.max() > 0 else magnitude
    weave_col = max(1, round(w / 6))
    weave_row = max(1, round(h / 6))
    weave = 0.5 + 0.25 * (np.cos(2 * np.pi * weave_col * cols[None, :] / w) + np.cos(2 * np.pi * weave_row * rows[:, None] / h))
    albedo *= (1.0 - 0.5 * bumpiness * (0.6 + 0.4 * weave))[..., None]
    albedo = np.clip(albedo, 0.02, 1.0)

    return ProceduralMaterial(
        height=relief.astype(np.float32),
        albedo=albedo.astype(np.float32),
        normals=normals_from_height(relief),
    )


# ----------------------------------------------------------------------------------------------- lights


def hemisphere_lights(n: int, *, min_elevation_deg: float = 15.0, seed: int | None = None) -> np.ndarray:
    """``n`` light directions spread evenly over the hemisphere above ``min_elevation_deg``.

    Parameters
    ----------
    n
        Number of lights (0 gives an empty ``(0, 3)`` array).
    min_elevation_deg
        Lowest elevation above the surface plane, in ``[0, 90)`` degrees.
    seed
        ``None`` for the fixed spiral; otherwise the spiral is turned by a random azimuth drawn from this seed.

    Returns
    -------
    numpy.ndarray
        ``float32 (n, 3)`` unit vectors, z up: a spherical Fibonacci spiral, uniform in area over the cap.
    """
    if int(n) != n or n < 0:
        raise BtforgeInputError("hemisphere_lights 'n'", f"expected a count >= 0, got {n}")
    if not (0.0 <= min_elevation_deg < 90.0):
        raise BtforgeInputError("hemisphere_lights 'min_elevation_deg'",
                                f"expected degrees in [0, 90), got {min_elevation_deg}")
    azimuth = 0.0 if seed is None else np.random.default_rng(seed).uniform(0.0, 2.0 * np.pi)
    dirs = fibonacci_directions(int(n), math.sin(math.radians(min_elevation_deg)), turn=0.0, azimuth=azimuth)
    return dirs.astype(np.float32)


# ----------------------------------------------------------------------------------------------- rendering


def _check_render_inputs(material, lights, ambient) -> tuple[ProceduralMaterial, np.ndarray, np.float32]:
    if not isinstance(material, ProceduralMaterial):
        raise BtforgeInputError("render 'material'", f"expected a ProceduralMaterial, got {type(material).__name__}",
                                "build one with make_material()")
    lights = unit_directions("lights", lights, owner="render.image")
    if not math.isfinite(ambient) or ambient < 0:
        raise BtforgeInputError("render 'ambient'", f"expected a finite number >= 0, got {ambient}")
    return material, lights, np.float32(ambient)


def _march_plan(material: ProceduralMaterial, lights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-light march steps ``float32 (L, 4)`` = (column step, row step, rise, 0) and step bounds ``int32 (L,)``.

    The march moves ``MARCH_STEP_TEXELS`` horizontally per step toward the light.  Its length is what the ray
    needs to climb from the lowest to the highest point of the field, capped at ``MAX_MARCH_LENGTH_FACTOR *
    max(H, W)`` texels: the cap is what bounds grazing, horizon (z = 0) and below-horizon lights.
    """
    h, w = material.shape
    relief = float(material.height.max()) - float(material.height.min())
    cap = math.ceil(MAX_MARCH_LENGTH_FACTOR * max(h, w) / MARCH_STEP_TEXELS)
    steps = np.zeros((len(lights), 4), dtype=np.float32)
    max_steps = np.zeros(len(lights), dtype=np.int32)
    for i, (lx, ly, lz) in enumerate(lights.astype(np.float64)):
        horizontal = math.hypot(lx, ly)
        if horizontal < _ZENITH_HORIZONTAL_EPS or relief == 0.0:
            continue  # straight up, or nothing can rise above any point: no shadow possible
        rise_per_texel = lz / horizontal  # tan(elevation)
        if rise_per_texel > 0.0:
            needed = math.ceil(relief / (rise_per_texel * MARCH_STEP_TEXELS)) + 1
            max_steps[i] = min(cap, needed)
        else:
            max_steps[i] = cap
        steps[i, 0] = MARCH_STEP_TEXELS * lx / horizontal
        steps[i, 1] = -MARCH_STEP_TEXELS * ly / horizontal  # y is up the image, rows go down
        steps[i, 2] = MARCH_STEP_TEXELS * rise_per_texel
    return steps, max_steps


def _height_bilinear_wrapped(height: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """The kernel's ``height_bilinear_wrapped`` on float32 arrays of coordinates."""
    h, w = height.shape
    col0 = np.floor(col)
    row0 = np.floor(row)
    fx = col - col0
    fy = row - row0
    c0 = col0.astype(np.int64) % w
    r0 = row0.astype(np.int64) % h
    c1 = np.where(c0 + 1 == w, 0, c0 + 1)
    r1 = np.where(r0 + 1 == h, 0, r0 + 1)
    h00 = height[r0, c0]
    h01 = height[r0, c1]
    h10 = height[r1, c0]
    h11 = height[r1, c1]
    top = h00 + fx * (h01 - h00)
    bottom = h10 + fx * (h11 - h10)
    return top + fy * (bottom - top)


def render_lights_numpy(material: ProceduralMaterial, lights, *, shadows: bool = True,
                        ambient: float = 0.0) -> np.ndarray:
    """The NumPy reference of :func:`render_lights`: same float32 operations, same march, vectorised over texels.

    Parameters and result as for :func:`render_lights`.  Per light it marches only the texels still undecided
    (lit, not yet occluded, ray still below the highest point), so its working set shrinks as the march goes.
    """
    material, lights, ambient32 = _check_render_inputs(material, lights, ambient)
    h, w = material.shape
    height = material.height
    flat_height = height.reshape(-1)
    normals = material.normals.reshape(-1, 3)
    albedo = material.albedo.reshape(-1, 3)
    max_height = height.max()
    steps, max_steps = _march_plan(material, lights)
    texel_col = np.tile(np.arange(w, dtype=np.float32), h)
    texel_row = np.repeat(np.arange(h, dtype=np.float32), w)

    out = np.empty((len(lights), h, w, 3), dtype=np.float32)
    for i, light in enumerate(lights):
        lx, ly, lz = (np.float32(v) for v in light)
        n_dot_l = normals[:, 0] * lx + normals[:, 1] * ly + normals[:, 2] * lz
        lit = np.maximum(n_dot_l, np.float32(0.0))
        if shadows:
            col_step, row_step, rise = steps[i, 0], steps[i, 1], steps[i, 2]
            pending = np.flatnonzero(lit > 0)
            for k in range(1, int(max_steps[i]) + 1):
                if pending.size == 0:
                    break
                kf = np.float32(k)
                ray = kf * rise + flat_height[pending]
                below_top = ray < max_height
                pending, ray = pending[below_top], ray[below_top]
                terrain = _height_bilinear_wrapped(height, kf * col_step + texel_col[pending],
                                                   kf * row_step + texel_row[pending])
                occluded = terrain > ray
                lit[pending[occluded]] = np.float32(0.0)  # visibility 0: lit * 0 == 0 exactly as in the kernel
                pending = pending[~occluded]
        shade = ambient32 + lit
        np.multiply(albedo, shade[:, None], out=out[i].reshape(-1, 3))
    return out


def render_lights(material: ProceduralMaterial, lights, *, shadows: bool = True, ambient: float = 0.0,
                  use_opencl: bool = True) -> np.ndarray:
    """Render ``material`` under each light: Lambertian shading with cast shadows.

    Parameters
    ----------
    material
        The material to render.
    lights
        ``(L, 3)`` directions toward the light (normalised here), z up; see the module docstring for the frame.
        Lights at or below the horizon are allowed: their march is bounded and ``max(0, n . l)`` decides.
    shadows
        Cast shadows by marching the height field toward the light (0.5-texel steps, bilinear heights, wrapping
        around the edges, stopping once the ray is above the highest point).
    ambient
        Light added everywhere, unshadowed, as a fraction of the albedo.
    use_opencl
        Run the OpenCL kernel (default) or the NumPy reference.

    Returns
    -------
    numpy.ndarray
        ``float32 [L, H, W, 3]`` linear radiance ``albedo * (ambient + max(0, n . l) * visibility)``.
    """
    if not use_opencl:
        return render_lights_numpy(material, lights, shadows=shadows, ambient=ambient)
    material, lights, ambient32 = _check_render_inputs(material, lights, ambient)
    h, w = material.shape
    n_lights = len(lights)
    out = np.empty((n_lights, h, w, 3), dtype=np.float32)
    if n_lights == 0:
        return out

    backend = get_backend()
    cl = backend.cl
    # A fresh kernel object per call: its arguments are per-call state, so calls from several threads
    # must not share one (creating it is cheap next to the render; the program itself is memoised).
    kernel = cl.Kernel(backend.program(KERNEL_FILE), "render_procedural")
    steps, max_steps = _march_plan(material, lights)
    lights4 = np.zeros((n_lights, 4), dtype=np.float32)
    lights4[:, :3] = lights

    height_buf = backend.to_device(material.height)
    albedo_buf = backend.to_device(material.albedo)
    normals_buf = backend.to_device(material.normals)
    bytes_per_light = h * w * 3 * 4
    lights_per_chunk = max(1, min(n_lights, _OUTPUT_CHUNK_BYTES // bytes_per_light))
    out_buf = backend.empty(lights_per_chunk * bytes_per_light)
    for start in range(0, n_lights, lights_per_chunk):
        stop = min(n_lights, start + lights_per_chunk)
        chunk = slice(start, stop)
        kernel(backend.queue, (w, h, stop - start), None,
               height_buf, albedo_buf, normals_buf,
               backend.to_device(lights4[chunk]), backend.to_device(steps[chunk]),
               backend.to_device(max_steps[chunk]),
               np.int32(h), np.int32(w), np.float32(material.height.max()), ambient32,
               np.int32(1 if shadows else 0), out_buf)
        cl.enqueue_copy(backend.queue, out[chunk], out_buf)
    backend.queue.finish()
    return out
