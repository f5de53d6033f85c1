"""The light's part of ``neural.fit``'s decoders: the decoder kinds, the features a light decoder takes and the
harmonics a harmonics decoder's outputs weight (see :mod:`.model`)."""
from __future__ import annotations

import numpy as np

from btforge.numerics import real_sh

MAX_LIGHT_ORDER = 8
DECODERS = ("light", "harmonics")


def light_features(lights: np.ndarray, light_order: int) -> np.ndarray:
    """The decoder's light input ``[L, F]`` float32 for unit ``lights [L, 3]`` (see :mod:`.model`)."""
    lights = np.asarray(lights, np.float64).reshape(-1, 3)
    if light_order == 0:
        return lights[:, :2].astype(np.float32)
    return real_sh(light_order, lights)[:, 1:].astype(np.float32)  # the constant band adds nothing to a bias


def harmonics(lights: np.ndarray, light_order: int) -> np.ndarray:
    """Real spherical harmonics of bands 0 .. ``light_order`` - 1 at ``lights [L, 3]``, ``[L, N^2]`` float32,
    scaled by sqrt(4 pi) so that the constant one is 1 (a texel's first coefficient is then its mean value)."""
    return (real_sh(light_order, np.asarray(lights, np.float64).reshape(-1, 3)) * np.sqrt(4 * np.pi)).astype(np.float32)


def n_light_features(light_order: int) -> int:
    return 2 if light_order == 0 else light_order ** 2 - 1
