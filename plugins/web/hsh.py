"""Hemispherical harmonics (HSH) models as RTIBuilder's ``.rti`` files and relight's web layout hold them.

HSH (Gautron et al. 2004) are spherical harmonics remapped onto the upper hemisphere.  The basis here is the
one RTI viewers evaluate (4 terms for order 2, 9 for order 3), with the light's polar angle clamped 0.15 rad
above the horizon as OpenLIME does; the coefficients fit display values (sRGB), like a ``.ptm`` file's.
"""
from __future__ import annotations

import dataclasses
import math
import struct
from pathlib import Path
from typing import ClassVar

import numpy as np

from btforge.atomic import atomic_write
from btforge.buffers import ReflectanceModel, check_array, frozen, srgb_to_linear, unit_directions
from btforge.errors import BtforgeInputError

HSH_TERMS = (4, 9)
MIN_ELEVATION = 0.15  # radians above the horizon, as OpenLIME clamps grazing lights


def hsh_basis(lights: np.ndarray, terms: int) -> np.ndarray:
    """The first ``terms`` (4 or 9) HSH functions at unit ``lights [L, 3]`` -> ``[L, terms]`` float64."""
    d = np.asarray(lights, np.float64)
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * math.pi)
    theta = np.minimum(np.arccos(np.clip(d[:, 2], -1.0, 1.0)), math.pi / 2 - MIN_ELEVATION)
    ct = np.cos(theta)
    root = np.sqrt(np.maximum(ct - ct * ct, 0.0))
    pi = math.pi
    basis = [
        np.full_like(ct, 1.0 / math.sqrt(2 * pi)),
        math.sqrt(6 / pi) * np.cos(phi) * root,
        math.sqrt(3 / (2 * pi)) * (2 * ct - 1),
        math.sqrt(6 / pi) * np.sin(phi) * root,
        math.sqrt(30 / pi) * np.cos(2 * phi) * (ct * ct - ct),
        math.sqrt(30 / pi) * np.cos(phi) * (2 * ct - 1) * root,
        math.sqrt(5 / (2 * pi)) * (6 * ct * ct - 6 * ct + 1),
        math.sqrt(30 / pi) * np.sin(phi) * (2 * ct - 1) * root,
        math.sqrt(30 / pi) * np.sin(2 * phi) * (ct * ct - ct),
    ]
    return np.stack(basis[:terms], axis=1)


@dataclasses.dataclass(frozen=True, eq=False)
class HSHModel(ReflectanceModel):
    """Per-texel hemispherical harmonics: ``coeffs [H, W, C, K]`` float32 (K = 4 or 9) of display values
    (``space='srgb'``, as RTI files hold them) or of linear radiance (``space='linear'``)."""

    type_name: ClassVar[str] = "HSHModel"
    texel_fields: ClassVar[tuple[str, ...]] = ("coeffs",)

    coeffs: np.ndarray
    space: str = "srgb"
    channel_names: tuple[str, ...] = ("R", "G", "B")

    def __post_init__(self):
        if self.space not in ("srgb", "linear"):
            raise BtforgeInputError("HSHModel 'space'", f"must be 'srgb' or 'linear', got {self.space!r}")
        check_array("coeffs", self.coeffs, ("H", "W", len(self.channel_names), "K"), np.float32, finite=True,
                    owner="HSHModel")
        if self.coeffs.shape[3] not in HSH_TERMS:
            raise BtforgeInputError("HSHModel 'coeffs'", f"must have 4 or 9 terms per channel, got {self.coeffs.shape[3]}")
        object.__setattr__(self, "coeffs", frozen(self.coeffs))
        object.__setattr__(self, "channel_names", tuple(self.channel_names))

    @property
    def channels(self) -> tuple[str, ...]:
        return self.channel_names

    @property
    def blendable(self) -> bool:
        return self.space == "linear"

    @property
    def mixes_records(self) -> bool:
        return True  # linear in the evaluated values, before an srgb model's clip and decode

    def evaluate(self, lights: np.ndarray, views: np.ndarray | None = None) -> np.ndarray:
        """Linear radiance ``[1, L, H, W, C]``: the HSH sum, clipped to [0, 1] and decoded when it is sRGB."""
        lights = unit_directions("lights", lights, owner="HSH evaluation")
        basis = hsh_basis(lights, self.coeffs.shape[3]).astype(np.float32)
        value = np.einsum("hwck,lk->lhwc", self.coeffs, basis, dtype=np.float32)
        value = np.maximum(value, 0.0)
        if self.space == "srgb":
            value = srgb_to_linear(np.minimum(value, 1.0)).astype(np.float32)
        return value[None].astype(np.float32)


# ----------------------------------------------------------------------------------------------- .rti files


def read_rti(path) -> HSHModel:
    """Read an RTIBuilder HSH ``.rti`` file (type 3: comment lines, ``3``, ``width height bands``,
    ``terms basis element_size``, then float32 scales and biases and one byte per term, band and pixel,
    bottom row first)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise BtforgeInputError(str(path), f"cannot be read ({exc.strerror or exc})") from None
    pos, line_no, lines = 0, 0, []
    while len(lines) < 3:
        end = data.find(b"\n", pos)
        if end < 0:
            raise BtforgeInputError(f"{path}, line {line_no + 1}", "the header ends before the file type, size "
                                    "and basis lines", "the file is truncated or not an HSH .rti file")
        text = data[pos:end].decode("latin-1").strip()
        pos, line_no = end + 1, line_no + 1
        if text.startswith("#") or not text:
            continue
        lines.append((line_no, text))
    try:
        kind = int(lines[0][1])
        width, height, bands = (int(t) for t in lines[1][1].split()[:3])
        terms, _basis, element = (int(t) for t in lines[2][1].split()[:3])
    except ValueError:
        raise BtforgeInputError(f"{path}, line {lines[0][0]}", "expected integers in the header lines "
                                "(type; width height bands; terms basis element-size)") from None
    if kind != 3:
        raise BtforgeInputError(f"{path}, line {lines[0][0]}", f"expected RTI type 3 (HSH), found {kind}",
                                "only hemispherical-harmonics .rti files are read")
    if terms not in HSH_TERMS or element != 1 or bands not in (1, 3):
        raise BtforgeInputError(f"{path}, line {lines[2][0]}", f"expected 4 or 9 terms of 1 byte and 1 or 3 bands, "
                                f"found {terms} terms of {element} bytes, {bands} bands")
    need = pos + 8 * terms + width * height * bands * terms
    if len(data) < need:
        raise BtforgeInputError(str(path), f"expected {need} bytes for {width} x {height} x {bands} x {terms}, "
                                f"found {len(data)}", "the file is truncated; export it again")
    scale = np.frombuffer(data, "<f4", terms, pos).astype(np.float64)
    bias = np.frombuffer(data, "<f4", terms, pos + 4 * terms).astype(np.float64)
    raw = np.frombuffer(data, np.uint8, width * height * bands * terms, pos + 8 * terms)
    coeffs = raw.reshape(height, width, bands, terms)[::-1] / 255.0 * scale + bias
    names = ("R", "G", "B") if bands == 3 else ("Y",)
    return HSHModel(np.ascontiguousarray(coeffs, dtype=np.float32), "srgb", names)


def write_rti(path, model: HSHModel) -> None:
    """Write an HSH model as an RTIBuilder ``.rti`` file (8 bits per coefficient, scale and bias per term)."""
    coeffs = model.coeffs.astype(np.float64)
    terms = coeffs.shape[3]
    low = coeffs.min(axis=(0, 1, 2))
    span = np.maximum(coeffs.max(axis=(0, 1, 2)) - low, 1e-12)
    levels = np.clip(np.rint((coeffs - low) / span * 255.0), 0, 255).astype(np.uint8)[::-1]
    header = (f"#HSH1.2\n3\n{model.width} {model.height} {coeffs.shape[2]}\n{terms} 2 1\n").encode()
    body = struct.pack(f"<{terms}f", *span.astype(np.float32)) + struct.pack(f"<{terms}f", *low.astype(np.float32))
    with atomic_write(path) as handle:
        handle.write(header + body + np.ascontiguousarray(levels).tobytes())
