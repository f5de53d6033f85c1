"""The light-table models in relight's web layout (``info.json`` + coefficient planes), as OpenLIME reads them.

- ``hsh`` (colorspace ``rgb``): plane ``3k + c`` is term ``k`` of channel ``c``; a ``ycc`` HSH fit is written as
  the equivalent rgb coefficients (exactly: the colour transform is linear).
- ``rbf`` and ``bilinear`` (OpenLIME's ``bln``), colorspace ``mrgb`` or ``mycc``: ``nplanes`` coefficient planes,
  plus ``basis``, ``(nplanes + 1) x D x 3`` bytes in the order (plane, table direction, colour component):
  plane 0 the mean response (``byte / 255``), plane ``p + 1`` component ``p`` (``(byte - 127) / range[p]``, with
  ``materials[0].range[p] = 127 / max |component p|``).  ``rbf`` adds ``lights`` (``3 D`` numbers) and ``sigma``;
  ``bilinear`` adds ``resolution`` (``D = resolution^2``, node ``x + y * resolution``); ``mycc`` adds
  ``yccplanes`` (Y, Co, Cg plane counts; planes are (Y, Co, Cg) triplets while the chroma planes last, then Y).

Coefficients and the basis are display values (sRGB) in [0, 1] units, so the web layout is exact up to the
8-bit rounding of the planes and of the basis.
"""
from __future__ import annotations

import numpy as np

from btforge.errors import BtforgeInputError

from .lightfuncs import YCC_TO_RGB

EIGEN_ZERO = 127  # the byte of a zero basis value


def hsh_rgb_coeffs(model) -> np.ndarray:
    """``[H, W, 3 K]`` rgb HSH coefficients (plane ``3k + c``) of an hsh model in either colour space."""
    terms = model.table.shape[1]
    # table[p + 1, k, comp] selects plane p's (term, component); colour to RGB by YCC_TO_RGB when ycc.
    select = model.table[1:].astype(np.float64)                  # [P, K, 3]
    if model.colorspace == "ycc":
        select = select @ YCC_TO_RGB.T
    rgb = np.einsum("hwp,pkc->hwkc", model.coeffs.astype(np.float64), select)
    return rgb.reshape(model.height, model.width, 3 * terms)


def quantize_basis(table: np.ndarray) -> tuple[list[int], list[float]]:
    """Bytes of the basis (mean, then components) and ``range`` per component (see the module docs)."""
    mean = np.clip(np.rint(table[0] * 255.0), 0, 255)
    peak = np.abs(table[1:]).reshape(len(table) - 1, -1).max(axis=1)
    ranges = np.where(peak > 0, EIGEN_ZERO / np.where(peak > 0, peak, 1.0), 1.0)
    eigen = np.clip(np.rint(EIGEN_ZERO + table[1:] * ranges[:, None, None]), 0, 255)
    data = np.concatenate([mean[None], eigen]).astype(np.int64).reshape(-1)
    return [int(v) for v in data], [float(r) for r in ranges]


def dequantize_basis(data, ranges, n_plane: int, n_table: int, where: str) -> np.ndarray:
    """The table ``[n_plane + 1, n_table, 3]`` float32 a web layout's ``basis`` and ``range`` hold."""
    values = np.asarray(data, np.float64)
    if values.shape != ((n_plane + 1) * n_table * 3,) or not np.all((values >= 0) & (values <= 255)):
        raise BtforgeInputError(where, f"expected 'basis' to list {(n_plane + 1) * n_table * 3} bytes ((nplanes + 1) "
                                f"x {n_table} directions x 3), found {values.size} values",
                                "export the model again")
    ranges = np.asarray(ranges, np.float64)
    if ranges.shape != (n_plane,) or not np.all(ranges > 0):
        raise BtforgeInputError(where, f"expected materials[0].range to list {n_plane} positive numbers")
    table = values.reshape(n_plane + 1, n_table, 3)
    table[0] /= 255.0
    table[1:] = (table[1:] - EIGEN_ZERO) / ranges[:, None, None]
    return table.astype(np.float32)


def web_layout(model) -> tuple[dict, np.ndarray]:
    """``(info fields, planes [P, H, W])`` of a light-table model; ``info['material']`` goes into materials[0]."""
    if model.kind == "hsh":
        planes = hsh_rgb_coeffs(model).transpose(2, 0, 1)
        return {"type": "hsh", "colorspace": "rgb"}, planes
    basis, ranges = quantize_basis(model.table.astype(np.float64))
    info = {"type": model.kind, "colorspace": "mycc" if model.colorspace == "ycc" else "mrgb"}
    if model.kind == "rbf":
        info.update(sigma=model.sigma, lights=[float(v) for v in model.table_lights.reshape(-1)])
    else:
        info["resolution"] = model.resolution
    if model.colorspace == "ycc":
        info["yccplanes"] = list(model.yccplanes)
    info.update(basis=basis, material={"range": ranges})
    return info, model.coeffs.transpose(2, 0, 1).astype(np.float64)


def from_web(cls, info: dict, planes: np.ndarray):
    """The model an rbf / bilinear web layout holds (``planes [P, H, W]`` decoded coefficients)."""
    where = f"{info.get('_folder', '.')}/info.json"
    kind = "bilinear" if info["type"] in ("bilinear", "bln") else info["type"]
    if info["colorspace"] not in ("mrgb", "mycc"):
        raise BtforgeInputError(where, f"expected colorspace mrgb or mycc for {info['type']}, found "
                                f"{info['colorspace']!r}")
    n_plane = info["nplanes"]
    extra = {}
    if kind == "rbf":
        lights = np.asarray(info.get("lights", []), np.float64).reshape(-1, 3)
        lights /= np.maximum(np.linalg.norm(lights, axis=1, keepdims=True), 1e-12)
        extra.update(table_lights=lights.astype(np.float32), sigma=float(info.get("sigma", 0.125)))
        n_table = len(lights)
    else:
        extra["resolution"] = int(info.get("resolution", 0))
        n_table = extra["resolution"] ** 2
    colorspace = "ycc" if info["colorspace"] == "mycc" else "rgb"
    if colorspace == "ycc":
        extra["yccplanes"] = tuple(int(v) for v in info.get("yccplanes", (0, 0, 0)))
    table = dequantize_basis(info.get("basis", []), info["materials"][0].get("range", []), n_plane, n_table, where)
    coeffs = np.ascontiguousarray(planes[:n_plane].transpose(1, 2, 0), np.float32)
    space = "linear" if (info.get("btforge") or {}).get("transfer") == "linear" else "srgb"
    return cls(kind=kind, coeffs=coeffs, table=table, colorspace=colorspace, space=space, **extra)
