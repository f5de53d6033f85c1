"""Viewing/lighting settings: the distances of Liu, Yu & Shum (2001) eq. 6 and 7, the weights of eq. 8, and the
target grids of ``liu.synthesize``.

A direction is measured by its polar and azimuth angles (the paper's wording) as the point
``theta * (cos phi, sin phi)`` of the plane: the azimuthal equidistant map of the hemisphere.  Differences of
these points are differences of polar and azimuth angle for nearby directions, and, unlike raw ``(theta, phi)``
pairs, they do not jump where the azimuth wraps or change with the arbitrary azimuth of a direction at the pole.
Rotating a setting about the normal rotates both points, and mirroring it reflects both, so eq. 7's minimum over
rotations has a closed form: with complex points ``v = theta_v e^{i phi_v}``,

    min_r |v1 - e^{ir} v2|^2 + lam |l1 - e^{ir} l2|^2 = |v1|^2 + |v2|^2 + lam (|l1|^2 + |l2|^2) - 2 |conj(v1) v2 + lam conj(l1) l2|

reached at ``r = -arg(conj(v1) v2 + lam conj(l1) l2)``, and the mirror image ``C^`` conjugates both points.
"""
from __future__ import annotations

import math

import numpy as np

from btforge.errors import BtforgeInputError

LIGHT_WEIGHT = 1.0   # eq. 6's lambda
FURTHEST_RATIO = 100.0  # eq. 8: the nearest reference weighs this many times the furthest chosen one


def polar_points(directions: np.ndarray) -> np.ndarray:
    """Complex ``theta e^{i phi}`` of unit directions ``[..., 3]`` (z up)."""
    d = np.asarray(directions, np.float64)
    theta = np.arccos(np.clip(d[..., 2] / np.linalg.norm(d, axis=-1), -1, 1))
    phi = np.arctan2(d[..., 1], d[..., 0])
    return theta * np.exp(1j * phi)


def distance(view1, light1, view2, light2, lam: float = LIGHT_WEIGHT) -> np.ndarray:
    """Eq. 6 between settings (broadcast over leading axes)."""
    v1, l1, v2, l2 = (polar_points(x) for x in (view1, light1, view2, light2))
    return np.sqrt(np.abs(v1 - v2) ** 2 + lam * np.abs(l1 - l2) ** 2)


def isotropic_match(view1, light1, view2, light2, lam: float = LIGHT_WEIGHT):
    """Eq. 7: ``(distance, rotation, mirrored)``: the rotation ``r`` (radians, about the normal) of setting 2, and
    whether setting 1 is mirrored, that bring the two closest."""
    v1, l1, v2, l2 = (polar_points(x) for x in (view1, light1, view2, light2))
    base = np.abs(v1) ** 2 + np.abs(v2) ** 2 + lam * (np.abs(l1) ** 2 + np.abs(l2) ** 2)
    plain = np.conj(v1) * v2 + lam * np.conj(l1) * l2
    mirror = v1 * v2 + lam * l1 * l2            # conj(conj(v1)) v2: setting 1 reflected
    mirrored = np.abs(mirror) > np.abs(plain) + 1e-12
    best = np.where(mirrored, mirror, plain)
    d = np.sqrt(np.maximum(base - 2 * np.abs(best), 0.0))
    return d, -np.angle(best), mirrored


def blend_weights(distances: np.ndarray, sharpness: float | None = None) -> np.ndarray:
    """Eq. 8: ``exp(-sigma d_i) / sum_k exp(-sigma d_k)`` (computed stably).

    Without ``sharpness``, sigma is chosen per target so that the furthest of the given references weighs
    ``1 / FURTHEST_RATIO`` of the nearest - the paper's "close to 1 for the nearest, almost 0 for the furthest" -
    so a reference that leaves or joins the set as the target moves carries about 1 % of the weight, and the
    blend changes smoothly.  sigma depends only on the nearest and furthest distances, which move continuously.
    """
    d = np.asarray(distances, np.float64)
    if sharpness is None:
        spread = float(d.max() - d.min())
        sharpness = math.log(FURTHEST_RATIO) / spread if spread > 1e-12 else 0.0
    e = np.exp(-sharpness * (d - d.min()))
    return e / e.sum()


def direction(tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    t, a = math.radians(tilt_deg), math.radians(azimuth_deg)
    return np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)])


def parse_grid(grid, paths=None) -> tuple[np.ndarray, np.ndarray]:
    """The target ``(views [V, 3], lights [L, 3])`` of ``liu.synthesize``'s ``grid`` param.

    ``grid`` is a ``.lvp`` path (its distinct views x its distinct lights), ``{views: [...], lights: [...]}`` or
    ``{view_tilts, view_azimuths, light_tilts, light_azimuths}`` in degrees (every combination).
    """
    where = "liu.synthesize 'grid'"
    if isinstance(grid, str):
        from btforge.plugins.stackio.lightfile import read_light_file
        path = paths.input(grid) if paths is not None else grid
        entries = read_light_file(path, require_images=False)
        if not entries or entries[0].view is None:
            raise BtforgeInputError(where, f"expected a .lvp file with view directions, found '{grid}'",
                                    "give a .lvp file, or the views and lights as lists")
        views = _distinct([e.view for e in entries])
        lights = _distinct([e.light for e in entries])
    elif isinstance(grid, dict) and set(grid) == {"views", "lights"}:
        views, lights = (np.asarray(grid[k], np.float64) for k in ("views", "lights"))
    elif isinstance(grid, dict) and set(grid) == {"view_tilts", "view_azimuths", "light_tilts", "light_azimuths"}:
        views = np.array([direction(t, a) for t in grid["view_tilts"] for a in grid["view_azimuths"]])
        lights = np.array([direction(t, a) for t in grid["light_tilts"] for a in grid["light_azimuths"]])
    else:
        raise BtforgeInputError(where, f"expected a .lvp path, {{views, lights}} or {{view_tilts, view_azimuths, "
                                f"light_tilts, light_azimuths}}, found {str(grid)[:80]}",
                                "e.g. grid: {views: [[0, 0, 1]], lights: [[0.5, 0, 0.87]]}")
    problems = []
    for name, d in (("views", views), ("lights", lights)):
        if d.ndim != 2 or d.shape[1] != 3 or len(d) == 0 or not np.isfinite(d).all():
            problems.append(f"'{name}' must be a non-empty list of [x, y, z], found shape {d.shape}")
        elif (np.linalg.norm(d, axis=1) < 1e-9).any() or (d[:, 2] <= 0).any():
            problems.append(f"'{name}' must point above the surface (z > 0)")
    if problems:
        raise BtforgeInputError(where, "; ".join(problems), "tilts below 90 degrees, directions with z > 0")
    views = views / np.linalg.norm(views, axis=1, keepdims=True)
    lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    return views.astype(np.float32), lights.astype(np.float32)


def _distinct(rows) -> np.ndarray:
    out: list[np.ndarray] = []
    for r in rows:
        r = np.asarray(r, np.float64)
        if not any(np.allclose(r, o, atol=1e-6) for o in out):
            out.append(r)
    return np.array(out)
