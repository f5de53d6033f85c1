"""The ``HeightField`` buffer: a surface's mesostructure as heights, albedo, normals and per-sample weights.

Frame (the one of ``demo.material`` and of RTI light files): texel ``[row, col]`` sits at ``x = col``,
``y = -row``, z out of the surface; heights are in texel widths.  ``normals_of`` differentiates a height field
with central differences in that frame, so a field and the normals it stores agree.
"""
from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from btforge.buffers import PerTexel, check_array, freeze_fields
from btforge.errors import BtforgeInputError


def slopes_of(height: np.ndarray, wrap: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``(dz/dx, dz/dy)`` float64 of ``[H, W]`` heights by central differences (one-sided at the borders unless
    ``wrap``); y points up the image, so dz/dy differences the row above minus the row below."""
    z = np.asarray(height, np.float64)
    if wrap:
        return (0.5 * (np.roll(z, -1, 1) - np.roll(z, 1, 1)), 0.5 * (np.roll(z, 1, 0) - np.roll(z, -1, 0)))
    p = np.gradient(z, axis=1) if z.shape[1] > 1 else np.zeros_like(z)
    q = -np.gradient(z, axis=0) if z.shape[0] > 1 else np.zeros_like(z)
    return p, q


def normals_of(height: np.ndarray, wrap: bool = False) -> np.ndarray:
    """Unit normals ``float32 [H, W, 3]`` ``(-dz/dx, -dz/dy, 1) / norm`` of a height field."""
    p, q = slopes_of(height, wrap)
    n = np.stack([-p, -q, np.ones_like(p)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class HeightField(PerTexel):
    """A height field with its albedo, unit normals and the robust weights of the samples it was recovered from.

    ``heights [H, W]`` float32 in texel widths (``height`` and ``width`` are the grid's size, as on every
    per-texel buffer); ``albedo [H, W, C]`` float32 linear, >= 0; ``normals [H, W, 3]``
    float32 unit with z > 0 (frame in the module docstring); ``weights [H, W, K]`` float32 in [0, 1], one per
    input sample (``K = views x lights`` of the stack it came from, 0 for a field that was not measured).
    Crop, ``synth.materialize`` and every synthesizer work on it as on any per-texel buffer; blending two texels
    averages heights and albedo and re-normalises the mean normal.
    """

    type_name: ClassVar[str] = "HeightField"
    texel_fields: ClassVar[tuple[str, ...]] = ("heights", "albedo", "normals", "weights")
    texel_axis: ClassVar[int] = 0

    heights: np.ndarray
    albedo: np.ndarray
    normals: np.ndarray
    weights: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0, 0), np.float32))
    channels: tuple[str, ...] = ("R", "G", "B")

    def __post_init__(self):
        owner = "HeightField"
        height = check_array("heights", self.heights, ("H", "W"), np.float32, finite=True, owner=owner)
        h, w = height.shape
        if h == 0 or w == 0:
            raise BtforgeInputError(f"{owner} 'heights'", f"must have at least one texel, got shape {height.shape}")
        albedo = check_array("albedo", self.albedo, (h, w, "C"), np.float32, finite=True, owner=owner)
        normals = check_array("normals", self.normals, (h, w, 3), np.float32, finite=True, owner=owner)
        weights = self.weights if self.weights.size else np.zeros((h, w, 0), np.float32)
        weights = check_array("weights", weights, (h, w, "K"), np.float32, finite=True, owner=owner)
        problems = []
        if albedo.size and albedo.min() < 0:
            problems.append(f"'albedo' must be >= 0, found {albedo.min():g}")
        norms = np.linalg.norm(normals.astype(np.float64), axis=-1)
        if np.abs(norms - 1).max() > 1e-3 or normals[..., 2].min() <= 0:
            problems.append("'normals' must be unit vectors with z > 0")
        if weights.size and (weights.min() < 0 or weights.max() > 1):
            problems.append(f"'weights' must lie in [0, 1], found {weights.min():g}..{weights.max():g}")
        if len(self.channels) != albedo.shape[2]:
            problems.append(f"'channels' must name {albedo.shape[2]} channels, got {tuple(self.channels)!r}")
        if problems:
            raise BtforgeInputError(owner, "; ".join(problems), "derive normals with normals_of(height)")
        freeze_fields(self, "channels", heights=height, albedo=albedo, normals=normals, weights=weights)

    @classmethod
    def from_height(cls, height: np.ndarray, albedo: np.ndarray | None = None, *, wrap: bool = False,
                    weights: np.ndarray | None = None, channels: tuple[str, ...] | None = None) -> "HeightField":
        """A field whose normals are those of ``height`` (grey albedo 1 when none is given)."""
        height = np.ascontiguousarray(height, np.float32)
        if albedo is None:
            albedo = np.ones(height.shape + (1,), np.float32)
        albedo = np.ascontiguousarray(albedo, np.float32)
        if channels is None:
            channels = ("R", "G", "B") if albedo.shape[-1] == 3 else tuple(f"C{i}" for i in range(albedo.shape[-1]))
        if weights is None:
            weights = np.zeros(height.shape + (0,), np.float32)
        return cls(height, albedo, normals_of(height, wrap), np.ascontiguousarray(weights, np.float32), channels)

    def slopes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(dz/dx, dz/dy)`` float32 ``[H, W]`` from the stored normals (exact for copied texels too)."""
        n = self.normals.astype(np.float64)
        return (-n[..., 0] / n[..., 2]).astype(np.float32), (-n[..., 1] / n[..., 2]).astype(np.float32)

    def appearance_features(self) -> np.ndarray:
        """``[H, W, 3]`` float32: height and its two slopes, each divided by its spread over the field.

        Height sets where shadows fall and slopes set the shading, so texels close in these three numbers look
        alike under every light; dividing by the spreads keeps either from swamping the other.
        """
        p, q = self.slopes()
        z = self.heights.astype(np.float64)
        z = (z - z.mean()) / (z.std() + 1e-12)
        slope_spread = np.sqrt(0.5 * (p.var() + q.var())) + 1e-12
        return np.stack([z, p / slope_spread, q / slope_spread], axis=-1).astype(np.float32)

    def blend_records(self, name, first, second, weight):
        mixed = super().blend_records(name, first, second, weight)
        if name == "normals":
            mixed = mixed / np.linalg.norm(mixed, axis=-1, keepdims=True)
        return mixed.astype(np.float32)
