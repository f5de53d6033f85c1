"""``NeuralModel``: a latent code per texel and a small decoder network shared by every texel (NeuralRTI,
Dulecha et al. 2020).  Relighting runs on the OpenCL device (kernel ``neural_relight`` in ``neural.cl``, eight
texels to a work-item as the lanes of a vector; :mod:`.kernel`), or in NumPy with ``engine="numpy"`` (its twin).

A texel's display value (sRGB, in [0, 1]) under a light ``l`` comes from a multilayer perceptron with ELU
between its layers and a linear output layer (``decoder``):

* ``harmonics``: ``sum_p Y_p(l) D(code)[p]``, the decoder ``D`` mapping the texel's latent code to its real
  spherical-harmonic coefficients of bands 0 .. ``light_order`` - 1 (per channel; :func:`harmonics`, scaled so
  that the constant one is 1);
* ``light`` (NeuralRTI's): ``D([code, f(l)])``, with features ``f(l)`` of the light direction: the harmonics
  of bands 1 .. ``light_order`` - 1, or for ``light_order`` 0 the direction's x and y.

Evaluation clips the value to [0, 1] and decodes it to linear radiance.
"""
from __future__ import annotations

import dataclasses
from typing import ClassVar

import numpy as np

from btforge.buffers import ReflectanceModel, check_array, frozen, scattered_lookup, unit_directions
from btforge.errors import BtforgeInputError
from btforge.numerics import texel_chunks

from .lightinput import DECODERS, MAX_LIGHT_ORDER, harmonics, light_features, n_light_features
from .network import decoder_layers_forward, elu, unpack_layers

ENGINE = "opencl"   # NeuralModel.evaluate's default engine

__all__ = ["NeuralModel", "DECODERS", "MAX_LIGHT_ORDER", "harmonics", "light_features", "n_light_features"]


@dataclasses.dataclass(frozen=True, eq=False)
class NeuralModel(ReflectanceModel):
    """Latent codes ``codes [H, W, K]`` float32 and a decoder: ``weights`` (every layer's weight matrix then bias,
    flattened, float32) of the layers ``layer_sizes`` (``K + F, hidden..., C``), ``F`` light features of
    ``light_order`` (see the module docs)."""

    type_name: ClassVar[str] = "NeuralModel"
    texel_fields: ClassVar[tuple[str, ...]] = ("codes",)
    blendable: ClassVar[bool] = False  # a blend of two codes does not decode to the blend of their functions
    web_types: ClassVar[tuple[str, ...]] = ("neural",)   # web layouts web.read reads into this class
    web_colorspaces: ClassVar[tuple[str, ...]] = ("rgb",)

    codes: np.ndarray
    weights: np.ndarray
    layer_sizes: tuple[int, ...]
    light_order: int = 3
    decoder: str = "light"
    channel_names: tuple[str, ...] = ("R", "G", "B")

    def __post_init__(self):
        owner = "NeuralModel"
        check_array("codes", self.codes, ("H", "W", "K"), np.float32, finite=True, owner=owner)
        check_array("weights", self.weights, ("N",), np.float32, finite=True, owner=owner)
        sizes = tuple(int(s) for s in self.layer_sizes)
        object.__setattr__(self, "layer_sizes", sizes)
        object.__setattr__(self, "light_order", int(self.light_order))
        object.__setattr__(self, "channel_names", tuple(self.channel_names))
        if not 0 <= self.light_order <= MAX_LIGHT_ORDER or self.light_order == 1 or (
                self.decoder == "harmonics" and self.light_order == 0):
            raise BtforgeInputError(f"{owner} 'light_order'", f"must be 0 (light decoder only) or 2 .. "
                                    f"{MAX_LIGHT_ORDER}, got {self.light_order}")
        if self.decoder not in DECODERS:
            raise BtforgeInputError(f"{owner} 'decoder'", f"must be one of {DECODERS}, got {self.decoder!r}")
        light = self.decoder == "light"
        expected_in = self.codes.shape[2] + (n_light_features(self.light_order) if light else 0)
        expected_out = len(self.channel_names) * (1 if light else self.light_order ** 2)
        if len(sizes) < 2 or sizes[0] != expected_in or sizes[-1] != expected_out or min(sizes) < 1:
            raise BtforgeInputError(f"{owner} 'layer_sizes'", f"must run from {expected_in} inputs to "
                                    f"{expected_out} outputs (a {self.decoder} decoder), got {sizes}")
        n_weights = sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))
        if self.weights.size != n_weights:
            raise BtforgeInputError(f"{owner} 'weights'", f"layers {sizes} need {n_weights} weights, got "
                                    f"{self.weights.size}")
        for name in ("codes", "weights"):
            object.__setattr__(self, name, frozen(getattr(self, name)))

    @property
    def channels(self) -> tuple[str, ...]:
        return self.channel_names

    @property
    def latent(self) -> int:
        return self.codes.shape[2]

    def layers(self) -> list[list[np.ndarray]]:
        return unpack_layers(self.weights, self.layer_sizes)

    def evaluate(self, lights: np.ndarray, views: np.ndarray | None = None, *, engine: str = ENGINE) -> np.ndarray:
        """Linear radiance ``[1, L, H, W, C]``: the decoded display value clipped to [0, 1] and decoded.

        ``engine``: ``opencl`` runs kernel ``neural_relight`` (:mod:`.kernel`), ``numpy`` its twin here."""
        if engine not in ("opencl", "numpy"):
            raise BtforgeInputError("neural evaluation 'engine'", f"must be 'opencl' or 'numpy', got {engine!r}")
        lights = unit_directions("lights", lights, owner="neural evaluation")
        codes = self.codes.reshape(-1, self.latent)
        layers = self.layers()
        if engine == "opencl":
            from .kernel import relight_opencl
            out = relight_opencl(codes, lights, layers, self.decoder, self.light_order, len(self.channel_names))
        else:
            out = np.empty((len(lights), codes.shape[0], len(self.channel_names)), np.float32)
            for chunk in texel_chunks(codes.shape[0], 4 * 4 * max(max(self.layer_sizes), len(lights))):
                out[:, chunk] = decode_display(self.display_values(codes[chunk], lights, layers))
        return out.reshape(1, len(lights), self.height, self.width, len(self.channel_names))

    def display_values(self, codes: np.ndarray, lights: np.ndarray, layers=None) -> np.ndarray:
        """The decoder's display values ``[L, T, C]`` float32 of ``codes [T, K]`` at unit ``lights [L, 3]``,
        before clipping."""
        layers = layers or self.layers()
        if self.decoder == "light":
            return display_light_numpy(codes, light_features(lights, self.light_order), layers)
        return np.moveaxis(harmonics(lights, self.light_order) @ self.coefficients(codes, layers), 1, 0)

    def evaluate_texels(self, rows: np.ndarray, cols: np.ndarray, lights_local: np.ndarray,
                        views_local: np.ndarray | None = None) -> np.ndarray:
        """Linear radiance ``[N, C]`` of texels ``(rows[i], cols[i])``, each at its own light ``[N, 3]``."""
        rows, cols, lights, _ = scattered_lookup(self, rows, cols, lights_local, views_local)
        norm = np.linalg.norm(lights, axis=1, keepdims=True)
        features = light_features(lights / np.where(norm > 0, norm, 1.0), self.light_order) \
            if self.decoder == "light" else None
        layers, codes = self.layers(), self.codes[rows, cols]
        if self.decoder == "harmonics":
            coeffs = self.coefficients(codes, layers)
            basis = harmonics(lights / np.where(norm > 0, norm, 1.0), self.light_order)
            return decode_display(np.einsum("np,npc->nc", basis, coeffs))
        (w1, b1), k = layers[0], self.latent
        first = elu(codes @ w1[:k] + features @ w1[k:] + b1)
        return decode_display(decoder_layers_forward(layers[1:], first))

    def write_web_layout(self, folder, image_format: str, quality: int):
        """Write the model in relight's web layout (see :mod:`.weblayout`); returns the files written."""
        from .weblayout import write_neural_web
        return write_neural_web(self, folder, image_format, quality)

    @staticmethod
    def web_info_problems(info: dict) -> list[str]:
        from .weblayout import web_info_problems
        return web_info_problems(info)

    @staticmethod
    def web_plane_ranges(info: dict):
        """(planes, low, span, first image index) of a checked neural info.json: value = byte / 255 * span + low."""
        from .weblayout import FIRST_PLANE, plane_ranges
        return plane_ranges(info) + (FIRST_PLANE,)

    @classmethod
    def from_web(cls, info: dict, planes: np.ndarray) -> "NeuralModel":
        from .weblayout import model_from_web
        return model_from_web(cls, info, planes)

    def coefficients(self, codes: np.ndarray, layers=None) -> np.ndarray:
        """A harmonics decoder's spherical-harmonic coefficients ``[T, N^2, C]`` of ``codes [T, K]``."""
        layers = layers or self.layers()
        (w1, b1) = layers[0]
        return decoder_layers_forward(layers[1:], elu(codes @ w1 + b1)).reshape(len(codes), self.light_order ** 2, -1)


def decode_display(value: np.ndarray) -> np.ndarray:
    """Linear radiance of display values, clipped to [0, 1] first (fmin / fmax: a NaN becomes 0, as in
    neural.cl)."""
    from btforge.buffers import srgb_to_linear
    return srgb_to_linear(np.fmin(np.fmax(value, 0.0), 1.0)).astype(np.float32)


def display_light_numpy(codes: np.ndarray, features: np.ndarray, layers) -> np.ndarray:
    """Display values ``[L, T, C]`` (not clipped) of ``codes [T, K]`` at lights of ``features [L, F]``: the
    first layer's code part once per texel, its light part once per light."""
    (w1, b1), k = layers[0], codes.shape[1]
    code_part = codes @ w1[:k]
    light_part = features @ w1[k:] + b1
    out = np.empty((len(features), codes.shape[0], layers[-1][0].shape[1]), np.float32)
    for i in range(len(features)):
        out[i] = decoder_layers_forward(layers[1:], elu(code_part + light_part[i]))
    return out
