"""relight's web layout, as OpenLIME reads it: ``info.json`` plus coefficient planes packed three to an image.

``info.json`` names the basis (``type``: ``ptm``, ``hsh`` or ``sh``), the ``colorspace`` (``rgb``: every
image holds one coefficient for R, G and B; ``lrgb``: image 0 the colour, the others three luminance
coefficients each), ``nplanes``, the image ``format`` (``jpg`` or ``png``) and, in ``materials[0]``, a
``scale`` and ``bias`` per plane: a coefficient is ``(byte / 255 - bias) * scale``.  Image ``plane_j`` holds
planes ``3j .. 3j + 2`` in its red, green and blue channels, row 0 at the top.

The relit value is the sum of coefficient x basis, shown as a display (sRGB) value.  Light-direction bases, in
OpenLIME's order:

- ``ptm``: ``1, lx, ly, lx^2, lx ly, ly^2``;
- ``sh``: real spherical harmonics of bands 0-2 (``Y00; x, z, y; xy, xz, 3z^2 - 1, yz, y^2 - x^2`` with their
  usual normalisations);
- ``hsh``: hemispherical harmonics (see :mod:`.hsh`);
- ``rbf`` and ``bilinear`` (colorspace ``mrgb`` / ``mycc``): a light table in ``basis``, laid out and read by the
  model class that declares them in ``web_types`` (``btforge.plugins.bases.weblayout``);
- ``neural``: latent codes and a decoder network, OpenLIME's neural layout (``btforge.plugins.neural.weblayout``):
  the model class writes and checks it itself (``write_web_layout``, ``web_info_problems``).

Each plane's scale and bias cover its whole range (relight's exporter clips at a quantile), so the export is
exact up to the 8-bit rounding.  A model of linear radiance (a fit in ``space: linear``, or ``auto`` choosing it)
gets ``"btforge": {"transfer": "linear"}``: our reader and viewer encode it to sRGB for display; viewers that
ignore the key show it as if it were display values (darker).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from btforge.atomic import atomic_write, atomic_write_text
from btforge.errors import BtforgeInputError, file_reader

from .hsh import HSHModel

PTM_ORDER = (5, 3, 4, 0, 2, 1)  # relight's (1, u, v, u^2, uv, v^2) from btforge's (u^2, v^2, uv, u, v, 1)
FORMATS = {"png": "PNG", "jpg": "JPEG"}


def sh_weights(lights: np.ndarray) -> np.ndarray:
    """OpenLIME's 9 ``sh`` basis functions at unit ``lights [L, 3]`` -> ``[L, 9]`` (exact pi)."""
    x, y, z = (np.asarray(lights, np.float64)[:, i] for i in range(3))
    a, b = 0.5 * math.sqrt(3 / math.pi), 0.5 * math.sqrt(15 / math.pi)
    return np.stack([np.full_like(x, 0.5 / math.sqrt(math.pi)), a * x, a * z, a * y, b * x * y, b * x * z,
                     0.5 * math.sqrt(5 / math.pi) * (3 * z * z - 1), b * y * z, 0.5 * b * (y * y - x * x)], axis=1)


def _sh_to_web_matrix() -> np.ndarray:
    """``M [9, 9]`` with ``sh_weights = real_sh(3) @ M`` (a signed permutation): web = inverse(M) @ ours."""
    from btforge.plugins.sh.model import real_sh
    rng = np.random.default_rng(0)
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    m = np.linalg.lstsq(real_sh(3, d), sh_weights(d), rcond=None)[0]
    return np.round(m, 9)


# ----------------------------------------------------------------------------------------------- writing


def _model_planes(model) -> tuple[dict, np.ndarray]:
    """info.json fields and the coefficient planes ``[P, H, W]`` of a model, in the web layout's order."""
    kind = model.type_name
    if kind == "PTMModel":
        raw = model.with_basis("raw")
        coeffs = raw.coeffs[..., PTM_ORDER]                         # [H, W, K, 6] relight order
        info = {"type": "ptm", "colorspace": model.variant}
        if model.variant == "rgb":
            planes = coeffs.transpose(3, 2, 0, 1).reshape(-1, model.height, model.width)   # plane 3j + c
        else:
            lum = coeffs[:, :, 0].transpose(2, 0, 1)
            planes = np.concatenate([model.albedo.transpose(2, 0, 1), lum])
        linear = model.space == "linear"
    elif kind == "SHModel":
        if model.k_v != 1 or model.light_order > 3:
            raise BtforgeInputError("web.export 'model'", f"expected SH of light order <= 3 and view order 1 "
                                    f"(9 coefficients, as OpenLIME's sh basis), found light order "
                                    f"{model.light_order}, view order {model.view_order}",
                                    "fit with `light_order: 3` (and view_order 1) for the web")
        ours = np.zeros(model.coeffs.shape[:3] + (9,), np.float64)
        ours[..., :model.k_l] = model.dequantized()[:, :, :, 0, :] / math.sqrt(4 * math.pi)   # f(l) = sum c Y(l)
        web = ours @ np.linalg.inv(_sh_to_web_matrix()).T
        planes = web.transpose(3, 2, 0, 1).reshape(-1, model.height, model.width)
        info, linear = {"type": "sh", "colorspace": "rgb"}, model.space == "linear"
    elif kind == "HSHModel":
        planes = model.coeffs.transpose(3, 2, 0, 1).reshape(-1, model.height, model.width)
        info, linear = {"type": "hsh", "colorspace": "rgb"}, model.space == "linear"
    elif hasattr(model, "web_layout"):  # a plugin's model that lays itself out (hsh, rbf, bilinear fits)
        info, planes = model.web_layout()
        linear = getattr(model, "space", "srgb") == "linear"
    else:
        raise BtforgeInputError("web.export 'model'", f"expected a PTM, SH, HSH or light-table model, found "
                                f"{kind}", "fit ptm.fit, sh.fit (light_order 3), hsh.fit, rbf.fit or bilinear.fit")
    if len(model.channel_names) != 3:
        raise BtforgeInputError("web.export 'model'", f"expected 3 colour channels, found "
                                f"{len(model.channel_names)}")
    if linear:
        info["btforge"] = {"transfer": "linear"}
    return info, np.asarray(planes, np.float64)


def quantize_planes(planes: np.ndarray) -> tuple[np.ndarray, list[float], list[float]]:
    """Bytes ``[P, H, W]`` and per-plane scale and bias so that ``(byte / 255 - bias) * scale`` is within half a
    step (``scale / 510``) of each value: the whole range of every plane, nothing clipped."""
    low = planes.min(axis=(1, 2))
    span = planes.max(axis=(1, 2)) - low
    scale = np.where(span > 0, span, 1.0)
    bias = -low / scale
    levels = np.clip(np.rint((planes / scale[:, None, None] + bias[:, None, None]) * 255.0), 0, 255)
    return levels.astype(np.uint8), [float(s) for s in scale], [float(b) for b in bias]


def write_plane_images(folder: Path, levels: np.ndarray, image_format: str, quality: int,
                       first: int = 0) -> list[Path]:
    """Bytes ``[P, H, W]`` as images ``plane_{first} ..``, three planes to an image (zeros fill the last)."""
    from PIL import Image
    n = len(levels)
    padded = np.concatenate([levels, np.zeros(((-n) % 3,) + levels.shape[1:], np.uint8)])
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for j in range(len(padded) // 3):
        target = folder / f"plane_{first + j}.{image_format}"
        image = Image.fromarray(np.ascontiguousarray(padded[3 * j:3 * j + 3].transpose(1, 2, 0)), "RGB")
        with atomic_write(target) as handle:
            if image_format == "jpg":
                image.save(handle, format="JPEG", quality=quality, subsampling=0)
            else:
                image.save(handle, format="PNG", compress_level=1)  # speed over size: PNG is for exactness
        written.append(target)
    return written


def write_web(model, folder, image_format: str = "png", quality: int = 95) -> list[Path]:
    """Write ``info.json`` and ``plane_0 .. plane_{n-1}`` images; returns the files written."""
    if image_format not in FORMATS:
        raise BtforgeInputError("web.export 'format'", f"expected png or jpg, found {image_format!r}")
    if hasattr(model, "write_web_layout"):  # a plugin's model with a layout of its own (neural)
        return model.write_web_layout(Path(folder), image_format, quality)
    info, planes = _model_planes(model)
    material = info.pop("material", {})
    levels, scale, bias = quantize_planes(planes)
    n = len(planes)
    folder = Path(folder)
    written = write_plane_images(folder, levels, image_format, quality)
    scale += [1.0] * (3 * len(written) - n)
    bias += [0.0] * (3 * len(written) - n)
    content = {"width": model.width, "height": model.height, "format": image_format, **info, "nplanes": n,
               "quality": quality, "materials": [{**material, "scale": scale, "bias": bias}]}
    atomic_write_text(folder / "info.json", json.dumps(content, indent=1) + "\n")
    return written + [folder / "info.json"]


# ----------------------------------------------------------------------------------------------- reading


MAX_SIDE = 1 << 17   # pixels per side of a plane image
MAX_PLANES = 64      # the largest layouts (HSH order 3, RGB) have 27


def read_info(path) -> dict:
    """The checked ``info.json`` of a web layout (a folder or the file itself)."""
    path = Path(path)
    if path.is_dir():
        path = path / "info.json"
    try:
        info = json.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise BtforgeInputError(str(path), f"cannot be read ({exc.strerror or exc})",
                                "give an exported folder or its info.json") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise BtforgeInputError(str(path), f"is not valid JSON ({exc})") from None
    if not isinstance(info, dict):
        raise BtforgeInputError(str(path), f"expected a JSON object, found {type(info).__name__}",
                                "export the model again (relight or web.export)")
    own = layout_class(info["type"]) if isinstance(info.get("type"), str) else None
    own = own if hasattr(own, "web_info_problems") else None
    problems = _size_problems(info) + (own.web_info_problems(info) if own else _plane_problems(info))
    if info.get("format", "jpg") not in FORMATS:
        problems.append(f"'format' {info.get('format')!r} is not jpg or png")
    if problems:
        raise BtforgeInputError(str(path), "; ".join(problems), "export the model again (relight or web.export)")
    info["_folder"] = str(path.parent)
    if own:
        count, low, span, first = own.web_plane_ranges(info)
    else:  # a coefficient is (byte / 255 - bias) * scale
        count, first = info["nplanes"], 0
        span = np.asarray(info["materials"][0]["scale"][:count], np.float64)
        low = -np.asarray(info["materials"][0]["bias"][:count], np.float64) * span
    info["_planes"] = {"count": count, "low": low, "span": span, "first": first}
    return info


def _type_problems(info: dict, fields) -> list[str]:
    """The fields (``(key, type)`` pairs) that ``info`` lacks or holds with another type."""
    return [f"'{key}' missing or not {kind.__name__}" for key, kind in fields if not isinstance(info.get(key), kind)]


def _size_problems(info: dict) -> list[str]:
    problems = _type_problems(info, (("width", int), ("height", int), ("type", str)))
    for key in ("width", "height"):
        if isinstance(info.get(key), int) and not 1 <= info[key] <= MAX_SIDE:
            problems.append(f"'{key}' must be 1 to {MAX_SIDE}, found {info[key]}")
    return problems


def _plane_problems(info: dict) -> list[str]:
    """What is wrong with the plane fields of a layout of coefficient planes (ptm, hsh, sh, rbf, bilinear)."""
    problems = _type_problems(info, (("nplanes", int), ("colorspace", str), ("materials", list)))
    if isinstance(info.get("nplanes"), int) and not 1 <= info["nplanes"] <= MAX_PLANES:
        problems.append(f"'nplanes' must be 1 to {MAX_PLANES}, found {info['nplanes']}")
    if not problems and isinstance(info.get("type"), str):
        plugin = layout_class(info["type"]) if info["type"] not in ("ptm", "hsh", "sh") else None
        if info["type"] not in ("ptm", "hsh", "sh") and plugin is None:
            problems.append(f"'type' {info['type']!r} is not ptm, hsh, sh, rbf, bilinear or neural")
        elif plugin is not None and info["colorspace"] not in plugin.web_colorspaces:
            problems.append(f"colorspace {info['colorspace']!r} with type {info['type']!r} is not supported "
                            f"({' or '.join(plugin.web_colorspaces)})")
        elif plugin is None and (info["colorspace"] not in ("rgb", "lrgb")
                                 or (info["colorspace"] == "lrgb" and info["type"] != "ptm")):
            problems.append(f"colorspace {info['colorspace']!r} with type {info['type']!r} is not supported "
                            "(rgb, or lrgb for ptm)")
        material = info["materials"][0] if info["materials"] else {}
        for key in ("scale", "bias"):
            values = material.get(key)
            if not isinstance(values, list) or len(values) < info["nplanes"] or not all(
                    isinstance(v, (int, float)) and math.isfinite(v) for v in values):
                problems.append(f"materials[0].{key} must list {info['nplanes']} finite numbers")
    return problems


def layout_class(kind: str):
    """The installed model class that reads web layouts of type ``kind`` (its ``web_types``, with the colour
    spaces it reads in ``web_colorspaces``), or None."""
    from btforge.registry import default_registry
    for cls in default_registry().types.values():
        if kind in getattr(cls, "web_types", ()) and hasattr(cls, "from_web"):
            return cls
    return None


def _read_planes(info: dict) -> np.ndarray:
    """The decoded planes ``[count, H, W]`` float32 of a checked layout (``info['_planes']``)."""
    from PIL import Image
    folder, fmt, spec = Path(info["_folder"]), info.get("format", "jpg"), info["_planes"]
    n, h, w = spec["count"], info["height"], info["width"]
    planes = None  # allocated once an image has the size info.json says (a damaged size must not allocate)
    lut = np.arange(256) / 255.0
    for j in range(-(-n // 3)):
        path = folder / f"plane_{spec['first'] + j}.{fmt}"
        try:
            with Image.open(path) as image:
                pixels = np.asarray(image.convert("RGB"))
        except (OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
            raise BtforgeInputError(str(path), f"cannot be read as an image ({exc})",
                                    "every plane_J image the info.json implies must be present") from None
        if pixels.shape[:2] != (h, w):
            raise BtforgeInputError(str(path), f"expected {w} x {h} pixels as info.json says, found "
                                    f"{pixels.shape[1]} x {pixels.shape[0]}",
                                    "export the model again: every plane image has the size info.json gives")
        if planes is None:
            planes = np.empty((n, h, w), np.float32)  # 8-bit steps are far above float32 rounding
        for c in range(3):
            p = 3 * j + c
            if p < n:
                planes[p] = (lut * spec["span"][p] + spec["low"][p]).astype(np.float32)[pixels[..., c]]
    return planes


@file_reader("a web layout", "export the model again (relight or web.export)")
def read_web(path):
    """The model a web layout holds: a PTMModel, SHModel or HSHModel (see the module docs)."""
    from btforge.plugins.ptm.model import PTMModel
    info = read_info(path)
    planes = _read_planes(info)
    h, w = info["height"], info["width"]
    linear = (info.get("btforge") or {}).get("transfer") == "linear"
    kind, space = info["type"], "linear" if linear else "srgb"
    if kind not in ("ptm", "hsh", "sh"):
        return layout_class(kind).from_web(info, planes)   # rbf, bilinear, neural: their plugin's class
    if kind == "ptm":
        inverse = np.argsort(PTM_ORDER)
        if info["colorspace"] == "rgb":
            _expect_planes(info, 18)
            coeffs = planes[:18].reshape(6, 3, h, w).transpose(2, 3, 1, 0)[..., inverse]
            return PTMModel(coeffs.astype(np.float32), np.zeros((h, w, 0), np.float32), "rgb", space)
        _expect_planes(info, 9)
        albedo = planes[:3].transpose(1, 2, 0)
        coeffs = planes[3:9].transpose(1, 2, 0)[:, :, None, :][..., inverse]
        return PTMModel(coeffs.astype(np.float32), albedo.astype(np.float32), "lrgb", space)
    terms = info["nplanes"] // 3
    coeffs = planes[:3 * terms].reshape(terms, 3, h, w).transpose(2, 3, 1, 0)
    if kind == "hsh":
        if terms not in (4, 9):
            raise BtforgeInputError(str(path), f"expected 12 or 27 planes for hsh, found {info['nplanes']}")
        return HSHModel(coeffs.astype(np.float32), space)
    from btforge.plugins.sh.model import SHModel
    _expect_planes(info, 27)
    ours = coeffs @ _sh_to_web_matrix().T * math.sqrt(4 * math.pi)
    return SHModel(ours[:, :, :, None, :].astype(np.float32), np.ones((1, 9), np.float32),
                   np.zeros((1, 9), np.float32), light_order=3, view_order=1, space=space)


def _expect_planes(info, n):
    if info["nplanes"] < n:
        raise BtforgeInputError(str(Path(info["_folder"]) / "info.json"),
                                f"expected {n} planes for {info['type']} {info['colorspace']}, found {info['nplanes']}")


def describe_web(path) -> dict:
    """Facts of a web layout for ``btforge info``."""
    info = read_info(path)
    return {"kind": "relight web layout", "type": info["type"], "colorspace": info.get("colorspace", "rgb"),
            "size": [info["width"], info["height"]], "planes": info["_planes"]["count"],
            "format": info.get("format", "jpg"),
            "transfer": (info.get("btforge") or {}).get("transfer", "srgb")}
