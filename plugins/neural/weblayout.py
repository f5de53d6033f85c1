"""``NeuralModel`` in relight's web layout, in the form OpenLIME's neural layer (``LayerNeuralRTI`` with
``ShaderNeural``) reads.

``info.json`` (``"type": "neural"``, ``"colorspace": "rgb"``) holds

- ``planes``: the latent values per texel (K); ``samples``: the width of the hidden layers;
- ``min`` and ``max``: one ``[r, g, b]`` triple per code image; a code is ``byte / 255 * (max - min) + min``;
- ``weights`` and ``biases``: one flat list per layer.  Layer ``i``'s weights are output-major (all the inputs of
  output 0, then of output 1, ...), its input count padded with zeros to a multiple of 4 and, except for the
  output layer, its output count too, so a shader reads them as ``vec4`` rows; the biases are padded alike.

The codes are 8-bit images ``plane_1 .. plane_J`` (J = ceil(K / 3)), three codes to an image in its red, green
and blue channels, row 0 at the top: OpenLIME's neural layer reads ``plane_1 .. plane_3`` (``plane_0`` is the
name of its relit output).  Every code plane's ``min`` and ``max`` cover its whole range, so the codes are exact up
to half an 8-bit step (with PNG).

``"btforge": {"decoder", "light_order", "layer_sizes"}`` names the decoder (see :mod:`.model`); a layout without
it is read as NeuralRTI's: a ``light`` decoder of ``planes + 2`` inputs (the code, then the light's x and y), two
hidden layers of ``samples`` units and 3 outputs.  OpenLIME's layer evaluates exactly that network, so it opens
the exports of ``neural.fit`` with ``decoder: light``, ``light_order: 0``, ``latent: 9`` and ``layers: 2``
(:func:`openlime_compatible`) written as ``format: jpg`` (its ``image`` layout asks for ``plane_J.jpg``); every
other neural export (the harmonics decoder, other sizes) is for ``btforge view`` and ``web.read``.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from btforge.atomic import atomic_write_text
from btforge.errors import BtforgeInputError

from .lightinput import DECODERS, MAX_LIGHT_ORDER, n_light_features
from .network import pack_layers

FIRST_PLANE = 1       # OpenLIME's neural layer reads plane_1 .. plane_3
MAX_LATENT = 64       # neural.fit's largest code
MAX_UNITS = 4096      # a layer wider than this is not a decoder a viewer can evaluate per pixel
MAX_LAYERS = 8


def pad4(n: int) -> int:
    return -(-n // 4) * 4


def padded_shape(layer: int, sizes) -> tuple[int, int]:
    """(rows, columns) of layer ``layer``'s stored weights: its outputs (padded to 4 unless it is the output
    layer) by its inputs (padded to 4)."""
    n_out = sizes[layer + 1]
    return (n_out if layer == len(sizes) - 2 else pad4(n_out)), pad4(sizes[layer])


def pack_web_layers(layers, sizes) -> tuple[list[list[float]], list[list[float]]]:
    """The ``weights`` and ``biases`` lists of info.json (see the module docs) of ``[W [in, out], b]`` layers."""
    weights, biases = [], []
    for i, (w, b) in enumerate(layers):
        rows, cols = padded_shape(i, sizes)
        matrix = np.zeros((rows, cols), np.float32)
        matrix[:w.shape[1], :w.shape[0]] = w.T
        bias = np.zeros(rows, np.float32)
        bias[:len(b)] = b
        weights.append([float(v) for v in matrix.reshape(-1)])   # float32 -> float64 -> JSON: exact
        biases.append([float(v) for v in bias])
    return weights, biases


def unpack_web_layers(weights, biases, sizes) -> np.ndarray:
    """The model's flat float32 weights from checked info.json lists (:func:`web_info_problems`)."""
    layers = []
    for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
        rows, cols = padded_shape(i, sizes)
        matrix = np.asarray(weights[i], np.float32).reshape(rows, cols)
        layers.append([matrix[:n_out, :n_in].T, np.asarray(biases[i], np.float32)[:n_out]])
    return pack_layers(layers)


def openlime_compatible(model) -> bool:
    """Whether OpenLIME's neural layer evaluates this model's network: NeuralRTI's light decoder of the code and
    the light's (x, y), 9 code values, two hidden layers of equal width, RGB."""
    sizes = model.layer_sizes
    return (model.decoder == "light" and model.light_order == 0 and model.latent == 9 and len(sizes) == 4
            and sizes[1] == sizes[2] and sizes[3] == 3)


def write_neural_web(model, folder, image_format: str, quality: int) -> list[Path]:
    """Write ``info.json`` and the code images ``plane_1 ..`` of a NeuralModel; returns the files written."""
    from btforge.plugins.web.layout import quantize_planes, write_plane_images
    if len(model.channel_names) != 3:
        raise BtforgeInputError("web.export 'model'", f"expected 3 colour channels, found {len(model.channel_names)}")
    levels, scale, bias = quantize_planes(model.codes.transpose(2, 0, 1).astype(np.float64))
    low = [-b * s for b, s in zip(bias, scale)]
    high = [lo + s for lo, s in zip(low, scale)]
    pad = (-model.latent) % 3
    low, high = low + [0.0] * pad, high + [1.0] * pad
    written = write_plane_images(Path(folder), levels, image_format, quality, first=FIRST_PLANE)
    weights, biases = pack_web_layers(model.layers(), model.layer_sizes)
    content = {"width": model.width, "height": model.height, "format": image_format, "quality": quality,
               "type": "neural", "colorspace": "rgb", "planes": model.latent, "samples": model.layer_sizes[1],
               "min": [low[i:i + 3] for i in range(0, len(low), 3)],
               "max": [high[i:i + 3] for i in range(0, len(high), 3)],
               "weights": weights, "biases": biases,
               "btforge": {"decoder": model.decoder, "light_order": model.light_order,
                           "layer_sizes": list(model.layer_sizes), "openlime": openlime_compatible(model)}}
    atomic_write_text(Path(folder) / "info.json", json.dumps(content, separators=(",", ":")) + "\n")
    return written + [Path(folder) / "info.json"]


# ----------------------------------------------------------------------------------------------- reading


def _is_int(value, low: int, high: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and low <= value <= high


def _finite_list(values, length: int) -> bool:
    return (isinstance(values, list) and len(values) == length
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values))


def _what_list(values, length: int) -> str:
    """What a list that should hold ``length`` finite numbers holds instead."""
    if not isinstance(values, list):
        return type(values).__name__
    if len(values) != length:
        return f"{len(values)} values"
    bad = next(i for i, v in enumerate(values) if isinstance(v, bool) or not isinstance(v, (int, float))
               or not math.isfinite(v))
    return f"{values[bad]!r} at index {bad}"


def layer_sizes_of(info: dict) -> tuple[str, int, list]:
    """(decoder, light order, layer sizes) a neural info.json declares, NeuralRTI's network when it says none."""
    extra = info.get("btforge") if isinstance(info.get("btforge"), dict) else {}
    decoder, order = extra.get("decoder", "light"), extra.get("light_order", 0)
    default = [info.get("planes", 0) + 2, info.get("samples", 0), info.get("samples", 0), 3]
    return decoder, order, extra.get("layer_sizes", default)


def _size_problems(info: dict) -> list[str]:
    decoder, order, sizes = layer_sizes_of(info)
    if decoder not in DECODERS:
        return [f"btforge.decoder: expected one of {', '.join(DECODERS)}, found {decoder!r}"]
    if not _is_int(order, 0, MAX_LIGHT_ORDER) or order == 1 or (decoder == "harmonics" and order == 0):
        return [f"btforge.light_order: expected 0 (light decoder) or 2 .. {MAX_LIGHT_ORDER}, found {order!r}"]
    if not (isinstance(sizes, list) and 3 <= len(sizes) <= MAX_LAYERS + 1
            and all(_is_int(s, 1, MAX_UNITS) for s in sizes)):
        return [f"btforge.layer_sizes: expected 3 to {MAX_LAYERS + 1} unit counts of 1 .. {MAX_UNITS}, found "
                f"{sizes!r}"]
    light = decoder == "light"
    inputs = info["planes"] + (n_light_features(order) if light else 0)
    outputs = 3 if light else 3 * order ** 2
    if (sizes[0], sizes[-1]) != (inputs, outputs):
        return [f"btforge.layer_sizes: a {decoder} decoder of 'planes' = {info['planes']} codes (light order "
                f"{order}) runs from {inputs} inputs to {outputs} outputs, found {sizes[0]} to {sizes[-1]}"]
    return []


def _weight_problems(info: dict) -> list[str]:
    _, _, sizes = layer_sizes_of(info)
    problems = []
    for key in ("weights", "biases"):
        lists = info.get(key)
        if not isinstance(lists, list) or len(lists) != len(sizes) - 1:
            found = f"{len(lists)} lists" if isinstance(lists, list) else "none" if lists is None else type(lists).__name__
            problems.append(f"'{key}': expected {len(sizes) - 1} lists (one per layer of {sizes}), found {found}")
            continue
        for i, values in enumerate(lists):
            rows, cols = padded_shape(i, sizes)
            length = rows * cols if key == "weights" else rows
            if not _finite_list(values, length):
                found = _what_list(values, length)
                shape = f"{rows} outputs x {cols} inputs" if key == "weights" else f"{rows} outputs"
                problems.append(f"'{key}[{i}]': expected {length} finite numbers ({shape}: layer {i + 1}, "
                                f"{sizes[i]} -> {sizes[i + 1]} units, padded to multiples of 4), found {found}")
    return problems


def web_info_problems(info: dict) -> list[str]:
    """Everything wrong with a neural info.json (whose width, height and type were checked), at once."""
    problems = []
    if not _is_int(info.get("planes"), 1, MAX_LATENT):
        problems.append(f"'planes' (code values per texel): expected an integer 1 .. {MAX_LATENT}, found "
                        f"{info.get('planes')!r}")
    if not _is_int(info.get("samples"), 1, MAX_UNITS):
        problems.append(f"'samples' (hidden units): expected an integer 1 .. {MAX_UNITS}, found {info.get('samples')!r}")
    if info.get("colorspace", "rgb") != "rgb":
        problems.append(f"'colorspace': expected 'rgb' for a neural layout, found {info.get('colorspace')!r}")
    if not _is_int(info.get("planes"), 1, MAX_LATENT):
        return problems
    images = -(-info["planes"] // 3)
    for key in ("min", "max"):
        triples = info.get(key)
        if not (isinstance(triples, list) and len(triples) >= images and all(_finite_list(t, 3) for t in triples[:images])):
            problems.append(f"'{key}': expected {images} [r, g, b] triples of finite numbers (one per code image), "
                            f"found {json.dumps(triples)[:80] if triples is not None else 'none'}")
    if not problems:
        span = np.subtract(info["max"][:images], info["min"][:images], dtype=np.float64)
        if not np.all(np.isfinite(span) & (span >= 0)):
            problems.append("'max' - 'min': expected a finite range >= 0 for every code, found "
                            f"{json.dumps(span.reshape(-1).tolist())[:80]}")
    sizes_wrong = _size_problems(info)
    return problems + sizes_wrong + (_weight_problems(info) if not (sizes_wrong or problems) else [])


def plane_ranges(info: dict) -> tuple[int, np.ndarray, np.ndarray]:
    """(code count, low [K], span [K]) of a checked neural info.json: code = byte / 255 * span + low."""
    n = info["planes"]
    low = np.asarray(info["min"], np.float64).reshape(-1)[:n]
    return n, low, np.asarray(info["max"], np.float64).reshape(-1)[:n] - low


def model_from_web(cls, info: dict, planes: np.ndarray):
    """The NeuralModel a checked neural info.json and its decoded code planes ``[K, H, W]`` hold."""
    decoder, order, sizes = layer_sizes_of(info)
    codes = np.ascontiguousarray(planes.transpose(1, 2, 0), np.float32)
    weights = unpack_web_layers(info["weights"], info["biases"], sizes)
    return cls(codes, weights, tuple(sizes), order, decoder, ("R", "G", "B"))
