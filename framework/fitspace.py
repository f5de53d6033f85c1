"""Which space a fit of an 8-bit capture works in: linear radiance or the display values the capture holds.

Shared by every representation with a ``space`` parameter (``auto``: whichever predicts held-out lights of a
sample of texels better); the representation supplies only how to fit and predict.
"""
from __future__ import annotations

import math

import numpy as np

from .buffers import SampleStack, linear_to_srgb


AUTO_TEXELS = 4096       # texels (a regular grid over the capture) on which `auto` compares the spaces
AUTO_HOLD_EVERY = 5      # ... holding out every fifth light
AUTO_MIN_LIGHTS = 10     # fewer lights than this: no held-out test, 8-bit captures are fitted in display space


def held_out_space(stack: SampleStack, predict) -> str:
    """``auto``'s choice for an 8-bit capture: the space whose fit predicts held-out lights better.

    ``predict(fit_stack, space, lights, views)`` fits ``fit_stack`` in ``space`` and returns linear radiance
    ``[V, L, h, w, C]`` at the held-out lights.  On a regular grid of at most ``AUTO_TEXELS`` texels, every
    ``AUTO_HOLD_EVERY``-th light is held out, both spaces are fitted to the rest, and the one with the lower
    mean squared error of the held-out display values (the bytes the capture holds) wins.  Neither space wins
    everywhere: real captures (camera tone curves, gloss) fit better as display values, a computer-generated matte relief
    (SynthRTI: radiance linear in n . l, then sRGB-encoded) as linear radiance.  A linear capture is fitted
    linearly; one with fewer than ``AUTO_MIN_LIGHTS`` lights in display space.
    """
    if stack.encoding != "srgb8":
        return "linear"
    if stack.n_light < AUTO_MIN_LIGHTS:
        return "srgb"
    step = auto_grid_step(stack.height, stack.width)
    return space_from_grid(stack.texel_grid(step), stack, predict)


def auto_grid_step(height: int, width: int) -> int:
    """The stride of the texel grid ``auto`` judges on: at most about ``AUTO_TEXELS`` texels."""
    return max(1, math.ceil(math.sqrt(height * width / AUTO_TEXELS)))


def space_from_grid(grid: np.ndarray, like: SampleStack, predict) -> str:
    """:func:`held_out_space` on 8-bit samples ``[V, L, h, w, C]`` of a texel grid (lights, views and channels
    those of ``like``): whoever read the grid - a whole stack, or a pass over a capture's images - gets the
    same answer."""
    held = np.arange(like.n_light) % AUTO_HOLD_EVERY == AUTO_HOLD_EVERY // 2
    fit = SampleStack(np.ascontiguousarray(grid[:, ~held]), like.lights[~held], like.views, like.channels, "srgb8")
    target = grid[:, held].astype(np.float64) / 255.0
    errors = {space: float(np.mean((linear_to_srgb(predict(fit, space, like.lights[held], like.views)) - target) ** 2))
              for space in ("srgb", "linear")}
    return min(errors, key=errors.get)


def resolve_space(stack: SampleStack, space: str, predict=None) -> str:
    """The space to fit: ``space`` itself, or for ``auto`` :func:`held_out_space` (display values for an 8-bit
    capture when no ``predict`` is given)."""
    if space != "auto":
        return space
    if predict is None:
        return "srgb" if stack.encoding == "srgb8" else "linear"
    return held_out_space(stack, predict)
