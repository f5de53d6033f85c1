"""Environment lights: lat-long maps (EXR or a procedural sky), importance sampling into directional lights, and
spherical-harmonic projection with per-texel rotation.

Lat-long layout: row ``i`` of an ``h x w`` map is at polar angle ``theta = pi (i + 0.5) / h`` from the light's
``up`` axis (row 0 is the zenith), column ``j`` at azimuth ``phi = 2 pi (j + 0.5) / w + rotate`` measured from
``forward`` toward ``forward x up``: clockwise seen from above, so from inside the sphere, facing ``forward`` with
``up`` overhead, the panorama reads left to right as in any equirectangular viewer (Blender's convention, up to
where the seam sits).  With the defaults (up +z, forward +x) the map's left edge looks along +x and azimuth grows
toward -y; a positive ``rotate`` turns the map clockwise seen from above.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from btforge.errors import BtforgeInputError
from btforge.numerics import fibonacci_directions, real_sh

from .scene import LightSpec


def read_environment(path: str, where: str = "") -> np.ndarray:
    """Read a lat-long EXR environment as linear float32 ``[h, w, 3]``; checks values are finite and >= 0."""
    from btforge.plugins.stackio.images import read_exr

    where = where or path
    pixels = read_exr(path)
    if pixels.shape[2] == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    if pixels.shape[0] < 2 or pixels.shape[1] < 2:
        raise BtforgeInputError(where, f"expected a lat-long map of at least 2 x 2 pixels, found {pixels.shape[1]} x "
                                f"{pixels.shape[0]}")
    if not np.isfinite(pixels).all():
        raise BtforgeInputError(where, f"environment map has {int((~np.isfinite(pixels)).sum())} NaN/Inf values",
                                "repair the map (e.g. clamp it) before lighting with it")
    if pixels.min() < 0:
        raise BtforgeInputError(where, f"environment map has negative radiance (min {float(pixels.min()):g})",
                                "a light cannot take energy away; clamp the map at 0")
    return np.ascontiguousarray(pixels, np.float32)


def sky_map(sky: dict) -> np.ndarray:
    """A procedural lat-long sky (zenith-to-horizon gradient, dark ground, a disc sun) in the default layout."""
    w = int(sky["width"])
    h = w // 2
    theta = math.pi * (np.arange(h) + 0.5) / h
    elevation = (math.pi / 2 - theta)[:, None, None]
    zenith, horizon, ground = (np.asarray(sky[k], np.float64) for k in ("zenith", "horizon", "ground"))
    t = np.clip(np.sin(np.maximum(elevation, 0.0)), 0, 1) ** 0.5
    rows = np.where(elevation >= 0, horizon * (1 - t) + zenith * t, ground)
    pixels = np.broadcast_to(rows, (h, w, 3)).copy()
    dirs = pixel_directions(h, w, np.array([0.0, 0, 1]), np.array([1.0, 0, 0]), 0.0)
    sun = np.asarray(sky["sun"])
    cos_size = math.cos(math.radians(sky["sun_size"]) / 2)
    disc = dirs @ sun >= cos_size
    if not disc.any():  # a sun smaller than a pixel still lights: put it in the nearest pixel
        disc = np.zeros((h, w), bool)
        disc[np.unravel_index(np.argmax(dirs @ sun), (h, w))] = True
    pixels[disc] += sky["sun_intensity"]
    return pixels.astype(np.float32)


def environment_pixels(light: LightSpec, scene) -> np.ndarray:
    if light.sky is not None:
        return sky_map(dict(light.sky))
    return scene.file_arrays(light.file)["pixels"]


def _axes(up: np.ndarray, forward: np.ndarray):
    """``(forward, side, up)``: azimuth 0 along ``forward``, 90 degrees along ``side = forward x up``."""
    up = np.asarray(up, np.float64)
    forward = np.asarray(forward, np.float64)
    return forward, np.cross(forward, up), up


def pixel_directions(h: int, w: int, up, forward, rotate_deg: float) -> np.ndarray:
    """World directions ``[h, w, 3]`` of the map's pixel centres."""
    f, s, u = _axes(up, forward)
    theta = math.pi * (np.arange(h) + 0.5) / h
    phi = 2 * math.pi * (np.arange(w) + 0.5) / w + math.radians(rotate_deg)
    st, ct = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    sp, cp = np.sin(phi)[None, :, None], np.cos(phi)[None, :, None]
    return st * cp * f + st * sp * s + ct * u


def pixel_solid_angles(h: int, w: int) -> np.ndarray:
    theta = math.pi * (np.arange(h) + 0.5) / h
    return (2 * math.pi / w) * (math.pi / h) * np.sin(theta)  # per row


def lookup(pixels: np.ndarray, dirs: np.ndarray, light: LightSpec) -> np.ndarray:
    """Radiance ``[N, 3]`` of the map toward world ``dirs [N, 3]`` (nearest pixel), times the light's intensity."""
    h, w = pixels.shape[:2]
    f, s, u = _axes(light.up, light.forward)
    ct = np.clip(dirs @ u, -1, 1)
    phi = np.arctan2(dirs @ s, dirs @ f) - math.radians(light.rotate)
    row = np.clip((np.arccos(ct) / math.pi * h).astype(int), 0, h - 1)
    col = np.floor((phi / (2 * math.pi) % 1.0) * w).astype(int) % w
    return pixels[row, col] * np.asarray(light.intensity, np.float32)


# ----------------------------------------------------------------------------------------------- sampling


@dataclasses.dataclass(frozen=True)
class DirectionalSet:
    """An environment as directional lights: unit ``directions [N, 3]`` toward the light and RGB ``intensities``."""

    directions: np.ndarray
    intensities: np.ndarray


def _r2(n: int) -> np.ndarray:
    """``n`` points of the R2 low-discrepancy sequence in [0, 1)^2 (deterministic, well spread for any n)."""
    g = 1.32471795724474602596
    a = np.array([1 / g, 1 / (g * g)])
    return (0.5 + np.outer(np.arange(1, n + 1), a)) % 1.0


def importance_sample(pixels: np.ndarray, light: LightSpec, n: int) -> DirectionalSet:
    """Importance-sample the map into at most ``n`` directional lights (fewer when samples coincide).

    Pixels are drawn with probability proportional to luminance x solid angle, at the points of a low-discrepancy
    sequence pushed through the inverse CDF (rows by their marginal, then columns), so the set is deterministic and
    evenly spread.  A pixel drawn ``k`` times becomes one light carrying ``k`` samples; each sample carries
    ``L(pixel) * solid_angle(pixel) / (n * P(pixel))``, the unbiased estimate of the map's irradiance integral.
    """
    h, w = pixels.shape[:2]
    omega = pixel_solid_angles(h, w)
    lum = pixels.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    weight = np.maximum(lum, 0) * omega[:, None]
    total = weight.sum()
    if total <= 0:
        return DirectionalSet(np.zeros((0, 3), np.float64), np.zeros((0, 3), np.float64))
    row_w = weight.sum(axis=1)
    row_cdf = np.cumsum(row_w) / total
    xi = _r2(n)
    rows = np.minimum(np.searchsorted(row_cdf, xi[:, 0], side="right"), h - 1)
    cols = np.empty(n, dtype=np.int64)
    for r in np.unique(rows):
        sel = rows == r
        cdf = np.cumsum(weight[r]) / row_w[r]
        cols[sel] = np.minimum(np.searchsorted(cdf, xi[sel, 1], side="right"), w - 1)
    flat, counts = np.unique(rows * w + cols, return_counts=True)
    r, c = flat // w, flat % w
    prob = weight[r, c] / total
    intensities = pixels[r, c].astype(np.float64) * (omega[r] * counts / (n * prob))[:, None]
    intensities *= np.asarray(light.intensity)
    dirs = pixel_directions(h, w, light.up, light.forward, light.rotate)[r, c]
    return DirectionalSet(dirs, intensities)


# ----------------------------------------------------------------------------------------------- spherical harmonics


def project_sh(pixels: np.ndarray, light: LightSpec, order: int) -> np.ndarray:
    """SH coefficients ``[order^2, 3]`` of the map in world coordinates (times the light's intensity)."""
    h, w = pixels.shape[:2]
    dirs = pixel_directions(h, w, light.up, light.forward, light.rotate)
    weights = pixel_solid_angles(h, w)[:, None, None] * pixels.astype(np.float64)      # [h, w, 3]
    coeffs = np.einsum("hwk,hwc->kc", real_sh(order, dirs), weights)
    return coeffs * np.asarray(light.intensity)


def hemisphere_quadrature(q: int) -> tuple[np.ndarray, float]:
    """``q`` directions on the upper hemisphere (z > 0), each with weight ``2 pi / q`` (equal areas)."""
    return fibonacci_directions(q, 0.0), 2 * math.pi / q


class SHRotator:
    """Rotates band-limited SH coefficients into per-point frames.

    For a frame ``F`` (rows T, B, N: world -> local) the local coefficients of a function with world coefficients
    ``c`` are ``Y(D)^+ [Y(F^T d_k) c]_k`` for a fixed set of directions ``D`` of full rank: a band-limited function
    is determined by its values there, and SH bands are closed under rotation (and reflection), so this is the
    exact rotation for any orthogonal frame.
    """

    def __init__(self, order: int):
        self.order = order
        self.points = fibonacci_directions(2 * order * order + 8)
        self.solve = np.linalg.pinv(real_sh(order, self.points))           # [n^2, K]

    def local_values(self, frames_t, frames_b, frames_n, coeffs: np.ndarray) -> np.ndarray:
        """Local coefficients ``[N, n^2, 3]`` of world ``coeffs [n^2, 3]`` in the frames ``(T, B, N)`` ``[N, 3]`` each."""
        d = self.points
        world = (d[None, :, 0:1] * frames_t[:, None] + d[None, :, 1:2] * frames_b[:, None]
                 + d[None, :, 2:3] * frames_n[:, None])                   # [N, K, 3]
        values = real_sh(self.order, world) @ coeffs                       # [N, K, 3]
        return np.einsum("jk,nkc->njc", self.solve, values)
