"""Read and write HP Polynomial Texture Map files (``.ptm``, version ``PTM_1.2``).

A PTM stores, per pixel, the six coefficients of a biquadratic polynomial in the projected light direction.
This module reads ``PTM_FORMAT_LRGB``, ``PTM_FORMAT_RGB`` and ``PTM_FORMAT_JPEG_LRGB`` files and writes the two
raw formats.

Conventions
-----------
Coefficient order
    ``(lu^2, lv^2, lu*lv, lu, lv, 1)``, where ``(lu, lv)`` are the x and y components of the unit vector toward
    the light (z up, x to the right of the image, y toward the top of the image).  This is the order of the
    HP format document (Malzbender & Gelb, "Polynomial Texture Map (.ptm) File Format", HP Labs, 2001):
    ``C = a0 lu^2 + a1 lv^2 + a2 lu lv + a3 lu + a4 lv + a5``.
Unit scale
    Coefficients are held in *unit* scale: the relit display value of channel ``c`` is
    ``poly = sum_i coeffs[..., k, i] * term_i(lu, lv)``, then ``value_c = albedo_c * poly`` for ``lrgb``
    (``K = 1``, a luminance polynomial) and ``value_c = poly_c`` for ``rgb`` (``K = 3``).  Values are
    sRGB-encoded display values, nominally in ``[0, 1]``.
File scale
    A file stores bytes; the file's coefficient is ``a_i = (byte - bias_i) * scale_i``, in units of 8-bit
    display levels.  Viewers relight an LRGB pixel as ``rgb_byte * L / 255`` with ``L`` the polynomial of the
    ``a_i``, and an RGB pixel as the polynomial itself, in 0..255: checked in ptmlib's ``ptm_write_jpeg``
    (``L = POLY / 255``, output ``L * rgb``) and in relight/OpenLIME, which load PTM biases as ``bias / 255``
    and evaluate ``(texel - bias) * scale`` on [0, 1] textures, times a [0, 1] base colour for LRGB.  Dividing
    by 255 gives this module's unit scale: decoded coefficient ``(byte - bias_i) * scale_i / 255`` and lrgb
    albedo ``rgb_byte / 255``.  The real tablet in ``shared/data/ptm/tablet1`` relit from the top this way
    has over 99 % of its values inside ``[0, 1]``, as display values should.
Orientation
    Pixel rows are stored bottom-to-top in the file, raw and JPEG streams alike; arrays here have row 0 at
    the top of the image.  Checked on the real JPEG_LRGB tablet: with rows flipped, a light from ``+lv``
    brightens the upper rim of the tablet and a light from ``-lu`` its left rim, i.e. ``(lu, lv)`` is a
    right-handed frame with v toward the top of the image.
Raw layouts
    ``PTM_FORMAT_LRGB``: for every pixel its 6 coefficient bytes, then a second block with every pixel's RGB
    triplet.  ``PTM_FORMAT_RGB``: three blocks, red then green then blue, each with every pixel's 6
    coefficient bytes (the layout read by relight's ``legacy_rti`` and ptmlib).
JPEG_LRGB
    After the six scale/bias values the header has a quality line and seven lines of 9 integers: plane
    transforms, motion vectors x and y, decode order (``order[i]`` is the rank at which plane ``i`` is
    decoded), reference planes (-1: none), compressed sizes, side-information sizes.  The payload holds, for
    planes 0..8 in index order (6 luminance coefficients, then R, G, B), the grayscale JPEG stream followed
    by its side information.  A plane with a reference was stored as a difference:
    ``plane = ref' + stored - 128`` with ``ref' = 255 - ref`` when the plane's transform is 1 (plane
    inversion) and ``ref' = ref`` when it is 0.  Inverting the *reference* (as ptmlib and jpview do) is
    confirmed by the real tablet: it leaves every predicted value inside 0..255, while inverting the
    result overflows on 46 000 pixels.  Side information is a list of 5-byte records (big-endian pixel index
    in the stream's row order, then the exact byte) applied after prediction.  Predicted values are clamped
    to 0..255 (other readers wrap modulo 256, turning a small JPEG overshoot into a gross error).  Motion
    compensation (transform 2) is not supported.
"""
from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import io
import math
import os
import threading
from typing import Callable

import numpy as np

from btforge.atomic import atomic_write
from btforge.buffers import unit_directions
from btforge.errors import BtforgeInputError
from btforge.spill import finite_range, read_block

from .model import ptm_terms

__all__ = ["PtmFileContent", "read_ptm", "write_ptm", "describe_ptm", "relit_display_values"]

PTM_VERSION = "PTM_1.2"
FORMAT_LRGB = "PTM_FORMAT_LRGB"
FORMAT_RGB = "PTM_FORMAT_RGB"
FORMAT_JPEG_LRGB = "PTM_FORMAT_JPEG_LRGB"
FORMAT_JPEG_RGB = "PTM_FORMAT_JPEG_RGB"

N_COEFFS = 6
VARIANT_CHANNELS = {"lrgb": 1, "rgb": 3}
WRITE_FORMAT = {"lrgb": FORMAT_LRGB, "rgb": FORMAT_RGB}

READABLE_FORMATS = {FORMAT_LRGB: "lrgb", FORMAT_RGB: "rgb", FORMAT_JPEG_LRGB: "lrgb"}
# Number of JPEG streams of the compressed formats whose header layout is known (describe_ptm reads both).
JPEG_STREAMS = {FORMAT_JPEG_LRGB: 9, FORMAT_JPEG_RGB: 18}
KNOWN_UNSUPPORTED_FORMATS = {
    "PTM_FORMAT_LUM", "PTM_FORMAT_PTM_LUT", "PTM_FORMAT_PTM_C_LUT", FORMAT_JPEG_RGB,
    "PTM_FORMAT_JPEGLS_RGB", "PTM_FORMAT_JPEGLS_LRGB",
}

# A PTM header is a few hundred bytes; these bounds stop a binary file from being scanned as one huge "line".
MAX_HEADER_LINE = 4096
MAX_HEADER_BYTES = 1 << 16

PLANE_INVERSION = 1
MOTION_COMPENSATION = 2
SIDE_INFO_RECORD = 5  # 4-byte big-endian pixel index, 1 byte value


# ----------------------------------------------------------------------------------------------- content


@dataclasses.dataclass(frozen=True, eq=False)
class PtmFileContent:
    """What a PTM file holds, decoded to unit scale (see the module docstring).

    Attributes
    ----------
    variant
        ``'lrgb'`` (a luminance polynomial times an RGB albedo) or ``'rgb'`` (one polynomial per channel).
    coeffs
        float32 ``[H, W, K, 6]``, ``K = 1`` for lrgb and 3 for rgb, row 0 at the top of the image.
    albedo
        float32 ``[H, W, 3]`` in ``[0, 1]`` for lrgb, ``None`` for rgb.
    file_format
        The format line of the file, e.g. ``'PTM_FORMAT_JPEG_LRGB'``.
    scale, bias
        The six per-coefficient scales and biases exactly as the header gives them.
    """

    variant: str
    coeffs: np.ndarray
    albedo: np.ndarray | None
    file_format: str
    scale: tuple[float, ...]
    bias: tuple[int, ...]

    def __post_init__(self):
        coeffs, albedo = _checked_model("PtmFileContent", self.variant, self.coeffs, self.albedo)
        # A read-only view freezes the content without touching the flags of the caller's array.
        coeffs = coeffs.astype(np.float32, copy=False).view()
        coeffs.flags.writeable = False
        object.__setattr__(self, "coeffs", coeffs)
        if albedo is not None:
            albedo = albedo.astype(np.float32, copy=False).view()
            albedo.flags.writeable = False
            object.__setattr__(self, "albedo", albedo)
        object.__setattr__(self, "scale", tuple(float(s) for s in self.scale))
        object.__setattr__(self, "bias", tuple(int(b) for b in self.bias))

    @property
    def height(self) -> int:
        return self.coeffs.shape[0]

    @property
    def width(self) -> int:
        return self.coeffs.shape[1]


# ----------------------------------------------------------------------------------------------- evaluation


def relit_display_values(coeffs: np.ndarray, albedo: np.ndarray | None, lights) -> np.ndarray:
    """Relight a PTM file's decoded content as the file defines it: display values ``[L, H, W, 3]`` float32.

    Unlike :meth:`PTMModel.evaluate <btforge.plugins.ptm.model.PTMModel.evaluate>` (linear radiance, clipped),
    this is the raw polynomial of the file's display values, for comparing files.

    Parameters
    ----------
    coeffs
        Unit-scale coefficients ``[H, W, K, 6]`` (``K = 1``: lrgb, needs ``albedo``; ``K = 3``: rgb).
    albedo
        ``[H, W, 3]`` for lrgb, ``None`` for rgb.
    lights
        ``[L, 3]`` directions toward the light (z up); normalised here.

    Returns
    -------
    numpy.ndarray
        sRGB-encoded display values, not clipped (callers clip to ``[0, 1]`` for display).
    """
    if not isinstance(coeffs, np.ndarray) or coeffs.ndim != 4 or coeffs.shape[-1] != N_COEFFS \
            or coeffs.shape[2] not in (1, 3):
        got = f"{coeffs.shape}" if isinstance(coeffs, np.ndarray) else type(coeffs).__name__
        raise BtforgeInputError("relit_display_values 'coeffs'", f"expected [H, W, K, 6] with K = 1 or 3, found {got}")
    variant = "lrgb" if coeffs.shape[2] == 1 else "rgb"
    coeffs, albedo = _checked_model("relit_display_values", variant, coeffs, albedo, check_values=False)
    terms = ptm_terms(unit_directions("lights", lights)).astype(np.float32)
    height, width, channels, _ = coeffs.shape
    # One matrix product over all texels keeps this a single BLAS call instead of a loop over lights.
    poly = coeffs.reshape(-1, N_COEFFS).astype(np.float32, copy=False) @ terms.T  # [H*W*K, L]
    poly = poly.T.reshape(len(terms), height, width, channels)
    if variant == "lrgb":
        return (poly * albedo.astype(np.float32, copy=False)[None]).astype(np.float32, copy=False)
    return poly


# ----------------------------------------------------------------------------------------------- validation


def _not_finite(owner: str, coeffs: np.ndarray):
    bad = np.argwhere(~np.isfinite(coeffs))[0]
    raise BtforgeInputError(f"{owner} 'coeffs'", f"expected finite values, found NaN/Inf at row {bad[0]}, column "
                            f"{bad[1]}", "repair the fit before saving it")


def _checked_model(owner: str, variant, coeffs, albedo, check_values: bool = True, coeffs_finite_later: bool = False):
    """Check a (variant, coeffs, albedo) triple; returns the arrays unchanged.  ``coeffs_finite_later``: the
    caller checks that the coefficients are finite on its own pass over them."""
    if variant not in VARIANT_CHANNELS:
        raise BtforgeInputError(f"{owner} 'variant'", f"expected 'lrgb' or 'rgb', found {variant!r}")
    channels = VARIANT_CHANNELS[variant]
    if not isinstance(coeffs, np.ndarray):
        raise BtforgeInputError(f"{owner} 'coeffs'", f"expected a numpy array, found {type(coeffs).__name__}",
                                "pass a float32 array [H, W, K, 6]")
    if coeffs.dtype.kind != "f" or coeffs.ndim != 4 or coeffs.shape[2:] != (channels, N_COEFFS) \
            or coeffs.shape[0] < 1 or coeffs.shape[1] < 1:
        raise BtforgeInputError(
            f"{owner} 'coeffs'",
            f"expected float [H, W, {channels}, 6] for variant '{variant}', found {coeffs.shape} {coeffs.dtype}",
            "lrgb models have one luminance polynomial per pixel (K = 1), rgb models one per channel (K = 3)")
    height, width = coeffs.shape[:2]
    # min and max see every NaN (they propagate it) and every infinity, without a mask the size of the model
    if check_values and not coeffs_finite_later and not finite_range(coeffs):  # page by page: a spilled model is not made resident
        _not_finite(owner, coeffs)
    if variant == "rgb":
        if albedo is not None:
            raise BtforgeInputError(f"{owner} 'albedo'", "expected None for an rgb PTM, found an array",
                                    "rgb PTMs carry colour in their per-channel polynomials; pass albedo=None")
        return coeffs, None
    if not isinstance(albedo, np.ndarray) or albedo.dtype.kind != "f" or albedo.shape != (height, width, 3):
        got = f"{albedo.shape} {albedo.dtype}" if isinstance(albedo, np.ndarray) else type(albedo).__name__
        raise BtforgeInputError(f"{owner} 'albedo'", f"expected float [{height}, {width}, 3], found {got}",
                                "an lrgb PTM needs one RGB albedo per pixel")
    if check_values:
        if not np.isfinite(albedo).all():
            raise BtforgeInputError(f"{owner} 'albedo'", "expected finite values, found NaN/Inf")
        low, high = float(albedo.min()), float(albedo.max())
        if low < 0.0 or high > 1.0:
            raise BtforgeInputError(f"{owner} 'albedo'", f"expected values in [0, 1], found [{low:g}, {high:g}]",
                                    "clip the albedo, or keep the brightness in the luminance polynomial")
    return coeffs, albedo


# ----------------------------------------------------------------------------------------------- header


@dataclasses.dataclass(frozen=True)
class _JpegLayout:
    quality: int
    transforms: tuple[int, ...]
    motion_x: tuple[int, ...]
    motion_y: tuple[int, ...]
    order: tuple[int, ...]
    reference: tuple[int, ...]
    sizes: tuple[int, ...]
    side_sizes: tuple[int, ...]
    line_of: dict  # field name -> header line number, for error messages

    @property
    def payload_bytes(self) -> int:
        return sum(self.sizes) + sum(self.side_sizes)


@dataclasses.dataclass(frozen=True)
class _Header:
    version: str
    file_format: str
    width: int
    height: int
    scale: tuple[float, ...]
    bias: tuple[int, ...]
    header_bytes: int
    jpeg: _JpegLayout | None

    @property
    def payload_bytes(self) -> int:
        if self.jpeg is not None:
            return self.jpeg.payload_bytes
        per_pixel = 6 + 3 if self.file_format == FORMAT_LRGB else 3 * 6
        return self.width * self.height * per_pixel


class _HeaderCursor:
    """Reads the text header line by line, remembering line numbers for error messages."""

    def __init__(self, data: bytes, name: str, whole_file: bool):
        self.data = data
        self.name = name
        self.whole_file = whole_file
        self.pos = 0
        self.line_no = 0

    def error(self, problem: str, hint: str | None = None, line: int | None = None) -> BtforgeInputError:
        return BtforgeInputError(f"{self.name}, header line {line or self.line_no}", problem, hint)

    def next_line(self, expecting: str) -> str:
        self.line_no += 1
        if self.pos >= len(self.data):
            raise self.error(f"expected {expecting}, found the end of the file",
                             "the file is truncated; re-export it")
        end = self.data.find(b"\n", self.pos, self.pos + MAX_HEADER_LINE)
        if end < 0:
            if self.line_no == 1:
                raise self.error(f"expected {expecting} on a line of its own, found no line end",
                                 "this is not a PTM file")
            if len(self.data) - self.pos < MAX_HEADER_LINE and self.whole_file:
                raise self.error(f"expected {expecting} ending in a newline, found the end of the file",
                                 "the file is truncated; re-export it")
            raise self.error(f"expected {expecting}, found no line end within {MAX_HEADER_LINE} bytes",
                             "this is not a PTM header")
        raw = self.data[self.pos:end]
        self.pos = end + 1
        try:
            return raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise self.error(f"expected {expecting} as ASCII text, found binary data",
                             "this is not a PTM file" if self.line_no == 1 else "the header is corrupt") from None

    def values(self, count: int, what: str, parse: Callable[[str], object], multiline: bool = False) -> tuple:
        """``count`` values of one header field, on one line (or, with ``multiline``, spread over several)."""
        first = self.line_no + 1
        tokens: list[tuple[str, int]] = []
        while len(tokens) < count:
            tokens += [(token, self.line_no) for token in
                       self.next_line(f"{count} {what} value{'s' if count > 1 else ''}").split()]
            if not multiline:
                break
        if len(tokens) != count:
            lines = f"{first}" if first == self.line_no else f"{first}-{self.line_no}"
            found = " ".join(token for token, _ in tokens)
            raise BtforgeInputError(f"{self.name}, header line {lines}",
                                    f"expected {count} {what} values, found {len(tokens)}: {found[:80]!r}",
                                    "the header is malformed; re-export the PTM")
        out = []
        for token, line in tokens:
            try:
                out.append(parse(token))
            except ValueError as exc:
                raise BtforgeInputError(f"{self.name}, header line {line}",
                                        f"expected {what} values, found {token[:40]!r} ({exc})",
                                        "the header is malformed; re-export the PTM") from None
        return tuple(out)


def _parse_int(token: str) -> int:
    try:
        return int(token)
    except ValueError:
        pass
    # Some writers print integral fields as floats ("127.000000"); accept those, nothing fractional.
    try:
        value = float(token)
    except ValueError:
        raise ValueError("not a number") from None
    if not value.is_integer():
        raise ValueError("not an integer")
    return int(value)


def _parse_finite_float(token: str) -> float:
    try:
        value = float(token)
    except ValueError:
        raise ValueError("not a number") from None
    if not math.isfinite(value):
        raise ValueError("not a finite number")
    return value


def _parse_header(data: bytes, name: str, whole_file: bool) -> _Header:
    cursor = _HeaderCursor(data, name, whole_file)
    version = cursor.next_line(f"the version '{PTM_VERSION}'")
    if version != PTM_VERSION:
        if version.startswith("PTM_1."):
            raise cursor.error(f"expected version '{PTM_VERSION}', found {version[:40]!r}",
                               "only PTM_1.2 files are supported; re-export the PTM with a current tool")
        raise cursor.error(f"expected '{PTM_VERSION}' (a PTM file), found {version[:40]!r}",
                           "this is not a PTM file")
    file_format = cursor.next_line("the format name")
    if file_format not in READABLE_FORMATS and file_format not in JPEG_STREAMS:
        if file_format in KNOWN_UNSUPPORTED_FORMATS:
            raise cursor.error(f"format {file_format} is not supported (readable: {', '.join(READABLE_FORMATS)})",
                               "convert the PTM to PTM_FORMAT_LRGB or PTM_FORMAT_RGB with an RTI tool")
        raise cursor.error(f"expected a PTM format name such as {FORMAT_LRGB}, found {file_format[:60]!r}",
                           "the file is corrupt or not a PTM file")
    # The format document allows width and height on one line or on two.
    width, height = cursor.values(2, "width and height", _parse_int, multiline=True)
    if width < 1 or height < 1:
        raise cursor.error(f"expected a positive width and height, found {width} x {height}")
    scale = cursor.values(N_COEFFS, "scale", _parse_finite_float)
    bias = cursor.values(N_COEFFS, "bias", _parse_int)
    jpeg = None
    if file_format in JPEG_STREAMS:
        n = JPEG_STREAMS[file_format]
        line_of = {}
        fields = {}
        for field, what, count in (("quality", "compression quality", 1), ("transforms", "plane transform", n),
                                   ("motion_x", "motion vector x", n), ("motion_y", "motion vector y", n),
                                   ("order", "decode order", n), ("reference", "reference plane", n),
                                   ("sizes", "compressed size", n), ("side_sizes", "side information size", n)):
            fields[field] = cursor.values(count, what, _parse_int)
            line_of[field] = cursor.line_no
        for field in ("sizes", "side_sizes"):
            if min(fields[field]) < 0:
                raise cursor.error(f"expected sizes >= 0, found {fields[field]}", line=line_of[field])
        jpeg = _JpegLayout(quality=fields["quality"][0], line_of=line_of,
                           **{k: v for k, v in fields.items() if k != "quality"})
    return _Header(version, file_format, width, height, scale, bias, cursor.pos, jpeg)


# ----------------------------------------------------------------------------------------------- reading


def _display_name(path) -> str:
    return str(path)


def _read_bytes(path) -> bytes:
    try:
        with open(path, "rb") as handle:
            return handle.read()
    except FileNotFoundError:
        raise BtforgeInputError(_display_name(path), "expected a PTM file, found no such file",
                                "check the path") from None
    except IsADirectoryError:
        raise BtforgeInputError(_display_name(path), "expected a PTM file, found a directory") from None


def _check_payload_size(header: _Header, found: int, name: str) -> None:
    expected = header.payload_bytes
    if found == expected:
        return
    if header.jpeg is not None:
        sizes = f"the compressed sizes (line {header.jpeg.line_of['sizes']}) and side information sizes " \
                f"(line {header.jpeg.line_of['side_sizes']}) add up to {expected} bytes"
    else:
        sizes = f"{header.width} x {header.height} pixels of {header.file_format} take {expected} bytes"
    if found < expected:
        raise BtforgeInputError(name, f"truncated: {sizes} after the header, found only {found}",
                                "the file was cut short; copy or export it again")
    raise BtforgeInputError(name, f"size mismatch: {sizes} after the header, found {found}",
                            "the header does not match the data; the file is corrupt")


def _unit_coefficients(raw: np.ndarray, header: _Header) -> np.ndarray:
    """Bytes ``[..., 6]`` to unit-scale float32 coefficients ``(byte - bias) * scale / 255``."""
    scale = np.asarray(header.scale, dtype=np.float64) / 255.0
    bias = np.asarray(header.bias, dtype=np.float64)
    # A 256-entry table per coefficient turns the conversion into one gather instead of float arithmetic.
    table = ((np.arange(256, dtype=np.float64)[:, None] - bias[None, :]) * scale[None, :]).astype(np.float32)
    return table[raw, np.arange(N_COEFFS)]


def _decode_jpeg_stream(stream: bytes, index: int, header: _Header, name: str) -> np.ndarray:
    from PIL import Image

    what = f"{name}, JPEG stream {index}"
    try:
        with Image.open(io.BytesIO(stream)) as image:
            if image.format != "JPEG":
                raise BtforgeInputError(what, f"expected a JPEG stream, found {image.format or 'unknown data'}",
                                        "the compressed sizes in the header are wrong or the file is corrupt")
            if image.size != (header.width, header.height) or image.mode != "L":
                raise BtforgeInputError(
                    what, f"expected a {header.width} x {header.height} grayscale JPEG, "
                          f"found {image.size[0]} x {image.size[1]} {image.mode}",
                    "the file is corrupt or was written by an incompatible tool")
            image.load()
            return np.asarray(image, dtype=np.uint8)
    except BtforgeInputError:
        raise
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as exc:
        raise BtforgeInputError(what, f"expected a decodable JPEG stream, found undecodable data ({exc})",
                                "the file is corrupt or truncated") from None


def _apply_side_information(plane: np.ndarray, side: bytes, index: int, name: str) -> None:
    if len(side) % SIDE_INFO_RECORD:
        raise BtforgeInputError(f"{name}, side information of plane {index}",
                                f"expected a multiple of {SIDE_INFO_RECORD} bytes, found {len(side)}",
                                "the file is corrupt")
    records = np.frombuffer(side, dtype=np.uint8).reshape(-1, SIDE_INFO_RECORD)
    positions = records[:, :4].astype(np.int64) @ np.array([1 << 24, 1 << 16, 1 << 8, 1], dtype=np.int64)
    if positions.size and positions.max() >= plane.size:
        raise BtforgeInputError(f"{name}, side information of plane {index}",
                                f"expected pixel indices below {plane.size}, found {int(positions.max())}",
                                "the file is corrupt")
    plane.reshape(-1)[positions] = records[:, 4]


def _check_jpeg_layout(jpeg: _JpegLayout, name: str) -> None:
    n = len(jpeg.order)
    where = lambda field: f"{name}, header line {jpeg.line_of[field]}"  # noqa: E731
    if sorted(jpeg.order) != list(range(n)):
        raise BtforgeInputError(where("order"), f"expected the decode order to be a permutation of 0..{n - 1}, "
                                                f"found {list(jpeg.order)}", "the file is corrupt")
    for plane, transform in enumerate(jpeg.transforms):
        if transform & MOTION_COMPENSATION:
            raise BtforgeInputError(where("transforms"),
                                    f"plane {plane} uses motion compensation (transform {transform}), "
                                    "which is not supported", "convert the PTM to PTM_FORMAT_LRGB with an RTI tool")
        if transform not in (0, PLANE_INVERSION):
            raise BtforgeInputError(where("transforms"), f"expected transforms 0 or 1, found {transform} "
                                                         f"for plane {plane}", "the file is corrupt")
    for plane, ref in enumerate(jpeg.reference):
        if ref == -1:
            continue
        if not 0 <= ref < n or ref == plane:
            raise BtforgeInputError(where("reference"), f"expected reference planes -1 or 0..{n - 1} (not the "
                                                        f"plane itself), found {ref} for plane {plane}",
                                    "the file is corrupt")
        if jpeg.order[ref] > jpeg.order[plane]:
            raise BtforgeInputError(where("reference"), f"plane {plane} is predicted from plane {ref}, which "
                                                        "the decode order puts after it", "the file is corrupt")


def _decode_jpeg_planes(payload: memoryview, header: _Header, name: str) -> np.ndarray:
    """The 9 planes ``[9, H, W]`` uint8 of a JPEG_LRGB payload, rows in file order (bottom first)."""
    jpeg = header.jpeg
    _check_jpeg_layout(jpeg, name)
    streams, sides = [], []
    offset = 0
    for size, side_size in zip(jpeg.sizes, jpeg.side_sizes):
        streams.append(bytes(payload[offset:offset + size]))
        offset += size
        sides.append(bytes(payload[offset:offset + side_size]))
        offset += side_size
    planes = [None] * len(streams)
    for plane in np.argsort(jpeg.order):
        stored = _decode_jpeg_stream(streams[plane], int(plane), header, name)
        ref = jpeg.reference[plane]
        if ref >= 0:
            reference = planes[ref].astype(np.int16)
            if jpeg.transforms[plane] & PLANE_INVERSION:
                reference = 255 - reference
            stored = np.clip(reference + stored.astype(np.int16) - 128, 0, 255).astype(np.uint8)
        else:
            stored = stored.copy()  # Pillow's buffer may be read-only; side information writes into it
        _apply_side_information(stored, sides[plane], int(plane), name)
        planes[plane] = stored
    return np.stack(planes)


def read_ptm(path) -> PtmFileContent:
    """Read a PTM file (``PTM_FORMAT_LRGB``, ``PTM_FORMAT_RGB`` or ``PTM_FORMAT_JPEG_LRGB``).

    Parameters
    ----------
    path
        The ``.ptm`` file.

    Returns
    -------
    PtmFileContent
        Unit-scale coefficients (row 0 at the top) and, for LRGB formats, the albedo.

    Raises
    ------
    BtforgeInputError
        When the file is missing, truncated, not a PTM_1.2 file, of an unsupported format, has a malformed
        header, or its sizes do not match its payload.
    """
    name = _display_name(path)
    data = _read_bytes(path)
    header = _parse_header(data, name, whole_file=True)
    if header.file_format not in READABLE_FORMATS:
        raise BtforgeInputError(f"{name}, header line 2", f"format {header.file_format} is not supported "
                                                          f"(readable: {', '.join(READABLE_FORMATS)})",
                                "convert the PTM to PTM_FORMAT_LRGB or PTM_FORMAT_RGB with an RTI tool")
    payload = memoryview(data)[header.header_bytes:]
    _check_payload_size(header, len(payload), name)
    height, width = header.height, header.width
    pixels = width * height
    raw = np.frombuffer(payload, dtype=np.uint8)
    if header.file_format == FORMAT_LRGB:
        coeff_bytes = raw[:pixels * 6].reshape(height, width, 1, 6)
        rgb_bytes = raw[pixels * 6:].reshape(height, width, 3)
    elif header.file_format == FORMAT_RGB:
        coeff_bytes = raw.reshape(3, height, width, 6).transpose(1, 2, 0, 3)
        rgb_bytes = None
    else:
        planes = _decode_jpeg_planes(payload, header, name)
        coeff_bytes = planes[:6].transpose(1, 2, 0)[:, :, None, :]
        rgb_bytes = planes[6:].transpose(1, 2, 0)
    # Files store the bottom row first; flipping here gives row 0 = top everywhere else.
    coeffs = _unit_coefficients(coeff_bytes[::-1], header)
    albedo = None if rgb_bytes is None else (rgb_bytes[::-1].astype(np.float32) / np.float32(255.0))
    return PtmFileContent(READABLE_FORMATS[header.file_format], np.ascontiguousarray(coeffs),
                          None if albedo is None else np.ascontiguousarray(albedo),
                          header.file_format, header.scale, header.bias)


def describe_ptm(path) -> dict:
    """Header facts of a PTM file for ``btforge info``, reading only the header.

    Returns
    -------
    dict
        ``version``, ``format``, ``variant`` (``'lrgb'``/``'rgb'``), ``width``, ``height``, ``scale`` and
        ``bias`` (6-tuples), ``size_bytes`` (the file's size), ``header_bytes`` and ``expected_size_bytes``
        (header plus the payload the header announces; differs from ``size_bytes`` for a truncated or
        corrupt file).  JPEG formats add ``quality``, ``compressed_sizes``, ``side_info_sizes``,
        ``reference_planes`` and ``transforms``.
    """
    name = _display_name(path)
    try:
        size = os.stat(path).st_size
        with open(path, "rb") as handle:
            prefix = handle.read(MAX_HEADER_BYTES)
    except FileNotFoundError:
        raise BtforgeInputError(name, "expected a PTM file, found no such file", "check the path") from None
    except IsADirectoryError:
        raise BtforgeInputError(name, "expected a PTM file, found a directory") from None
    header = _parse_header(prefix, name, whole_file=len(prefix) >= size)
    facts = {
        "version": header.version,
        "format": header.file_format,
        "variant": "lrgb" if "LRGB" in header.file_format else "rgb",
        "width": header.width,
        "height": header.height,
        "scale": header.scale,
        "bias": header.bias,
        "size_bytes": size,
        "header_bytes": header.header_bytes,
        "expected_size_bytes": header.header_bytes + header.payload_bytes,
    }
    if header.jpeg is not None:
        facts.update(quality=header.jpeg.quality, compressed_sizes=header.jpeg.sizes,
                     side_info_sizes=header.jpeg.side_sizes, reference_planes=header.jpeg.reference,
                     transforms=header.jpeg.transforms)
    return facts


# ----------------------------------------------------------------------------------------------- writing

# Relative tolerance for "these values already lie on a byte grid" when no scale reproduces them bit for bit:
# float storage of (byte - bias) * step is off by at most ~255 * 6e-8 = 1.5e-5 steps, far below this; rounding
# to any other grid errs by up to half a step, far above it.
GRID_TOLERANCE = 1e-4
GRID_SAMPLE = 1 << 16


def _scale_text(scale: float) -> str:
    """The header spelling of a scale: the shortest decimal that reads back as exactly this float."""
    return repr(float(scale))


def _grid_scale(flat: np.ndarray, indices: np.ndarray, levels: np.ndarray, step: float) -> float | None:
    """The scale (``255 * step``) for values ``flat`` lying at integer ``indices`` of a grid, or None.

    Prefers the shortest decimal whose decoding, as :func:`read_ptm` does it, gives back every value's float32
    bit for bit, so a file read and written again keeps its header (``2.0`` stays ``2.0``) and its values.
    ``levels`` (distinct values, or a sample of them) narrow the candidates; the whole array confirms them.
    """
    level_indices = np.rint(levels / step)
    used = level_indices != 0
    nonzero_values, nonzero_indices = levels[used], level_indices[used]
    target = flat.astype(np.float32)
    with np.errstate(over="ignore", invalid="ignore"):
        # Every scale in [low, high] puts each level within half a float32 ulp of itself.
        half_ulp = np.spacing(np.abs(nonzero_values).astype(np.float32)).astype(np.float64) / 2
        one_end = (nonzero_values - half_ulp) * 255.0 / nonzero_indices
        other_end = (nonzero_values + half_ulp) * 255.0 / nonzero_indices
        low = float(np.minimum(one_end, other_end).max(initial=0.0))
        high = float(np.maximum(one_end, other_end).min(initial=np.inf))
    if 0 < low <= high and math.isfinite(high):
        middle = (low + high) / 2
        for digits in range(1, 18):
            scale = float(f"{middle:.{digits}g}")
            if low <= scale <= high and np.array_equal((indices * (scale / 255.0)).astype(np.float32), target):
                return scale
    scale = 255.0 * step
    if scale > 0 and np.abs(flat - indices * (scale / 255.0)).max() <= GRID_TOLERANCE * step:
        return scale
    return None


def _refined_step(values: np.ndarray, step: float) -> float:
    """``step`` re-measured across the widest spread of grid indices, where float noise matters least.

    A gap between two float32 levels is off by up to an ulp of the levels, i.e. up to ~1e-5 of a step; over
    255 steps that would misplace the outer levels, while the spread between the extreme levels is exact to
    ~1e-7.
    """
    indices = np.rint(values / step)
    low, high = indices.argmin(), indices.argmax()
    if indices[high] == indices[low]:
        return step
    refined = float(values[high] - values[low]) / float(indices[high] - indices[low])
    return refined if refined > 0 else step


def _grid_quantization(values: np.ndarray) -> tuple[float, int, np.ndarray] | None:
    """Scale, bias and bytes that represent ``values`` exactly, if they already lie on a byte grid.

    Coefficients read from an 8-bit PTM are ``(byte - bias) * step``; re-encoding them on that same grid is
    lossless, while fitting a fresh grid to their (smaller) range would misalign the two grids and add up to
    half a step of error per coefficient.
    """
    flat = values.reshape(-1)
    levels = np.unique(flat[:: max(1, flat.size // GRID_SAMPLE)])
    gaps = np.diff(levels)
    gaps = gaps[gaps > 0]
    if gaps.size == 0:
        return None
    smallest_gap = float(gaps.min())
    span = max(float(flat.max()), 0.0) - min(float(flat.min()), 0.0)
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
        # The grid step divides the smallest gap between levels present; sparse data (few pixels, or levels
        # that skip values) needs a divisor > 1.  Steps finer than span / 255 cannot be stored anyway, so
        # dense float data leaves this loop at once (the slack covers a float32 gap off by ~1e-5 of a step).
        for divisor in range(1, int(255 * (1 + 1e-3) * smallest_gap / span) + 1 if span > 0 else 1):
            step = _refined_step(levels, smallest_gap / divisor)
            position = levels / step
            if np.abs(position - np.rint(position)).max() <= 1e-3:
                break
        else:
            return None
        indices = np.rint(flat / step)
        low, high = float(indices.min()), float(indices.max())
        if not (math.isfinite(low) and math.isfinite(high)) or max(high, 0.0) - min(low, 0.0) > 255:
            return None
    low, high = min(int(indices.min()), 0), max(int(indices.max()), 0)
    if high - low > 255:
        return None
    scale = _grid_scale(flat, indices, levels, step)
    if scale is None:
        return None
    bias = -low
    return scale, bias, (indices + bias).astype(np.uint8).reshape(values.shape)


def _range_plan(low: float, high: float) -> tuple[float, int, float]:
    """Scale, bias and step spreading the 256 levels over ``[min(lo, 0), max(hi, 0)]``.

    The integer bias in 0..255 puts zero on every representable grid, so the levels must span zero too.
    With ``step = span / 255`` and ``bias = round(-lo / step)`` every value maps into ``[-0.5, 255.5]``
    before rounding, so rounding to nearest never needs clamping beyond half a step.
    """
    low, high = min(low, 0.0), max(high, 0.0)
    span = high - low
    if span == 0.0:  # an all-zero coefficient: any positive scale decodes it exactly
        return 1.0, 0, 0.0
    scale = float(f"{span:.9g}")  # a short header number; the levels are computed with exactly this value
    step = scale / 255.0
    if not (math.isfinite(span) and step > 0):
        raise BtforgeInputError("write_ptm 'coeffs'",
                                f"expected a coefficient range a float can resolve, found [{low:g}, {high:g}]",
                                "rescale the model")
    return scale, int(min(255, max(0, round(-low / step)))), step


def _range_levels(values: np.ndarray, bias: int, step: float) -> np.ndarray:
    if step == 0.0:
        return np.zeros(values.shape, dtype=np.uint8)
    return np.clip(np.rint(values.astype(np.float64) / step + bias), 0, 255).astype(np.uint8)


GRID_PROBE = 1024  # values looked at first: any sample of a byte grid is spread at least as widely


def _grid_possible(sample: np.ndarray, low: float, high: float) -> bool:
    """Whether values with this sample, minimum and maximum might lie on a byte grid - the first test of
    :func:`_grid_quantization`, on the sample alone: dense float data answers no at once.  A part of the sample
    is tried first: its closest two distinct values are no closer than the whole sample's, so when they are too
    close for the grid, the sort of the whole sample is skipped."""
    span = max(high, 0.0) - min(low, 0.0)
    if not span > 0:
        return False
    probe_gap = _smallest_gap(sample[:GRID_PROBE])
    if probe_gap is not None and not _fits_a_byte_grid(probe_gap, span):
        return False
    gap = _smallest_gap(sample)
    return gap is not None and _fits_a_byte_grid(gap, span)


def _smallest_gap(values: np.ndarray) -> float | None:
    """The smallest distance between two distinct values, or None when all are equal."""
    gaps = np.diff(np.sort(values.astype(np.float64)))  # sorted, not np.unique: that imports numpy.ma (~20 ms)
    gaps = gaps[gaps > 0]
    return float(gaps.min()) if gaps.size else None


def _fits_a_byte_grid(gap: float, span: float) -> bool:
    return int(255 * (1 + 1e-3) * gap / span) >= 1


def _column_range(flat: np.ndarray, rows_per_block: int = 512) -> tuple[np.ndarray, np.ndarray]:
    """Per-column minimum and maximum of ``[N, K]``: reduced over blocks of rows laid side by side, since numpy
    reduces a narrow array down its long axis several times slower than a wide one."""
    n, k = flat.shape
    whole = n - n % rows_per_block
    wide = flat[:whole].reshape(-1, rows_per_block * k)
    lows = [wide.min(axis=0).reshape(rows_per_block, k).min(axis=0)] if whole else []
    highs = [wide.max(axis=0).reshape(rows_per_block, k).max(axis=0)] if whole else []
    if whole < n:
        lows.append(flat[whole:].min(axis=0))
        highs.append(flat[whole:].max(axis=0))
    return np.min(lows, axis=0), np.max(highs, axis=0)


def _spread_sample(flat: np.ndarray, runs: int = 64) -> np.ndarray:
    """About ``GRID_SAMPLE`` rows of ``[N, K]`` in ``runs`` contiguous runs spread over it: a strided sample would
    touch every page of the array (and a spilled model's are read from its file)."""
    step = max(1, flat.shape[0] // runs)
    length = max(1, GRID_SAMPLE // runs)
    return np.concatenate([read_block(flat, 0, slice(start, start + length))
                           for start in range(0, flat.shape[0], step)])


def _paged_column_range(flat: np.ndarray, rows: int = 1 << 16) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_column_range` a block of rows at a time, ``WRITE_THREADS`` blocks at once (a spilled model is read
    block by block from its file into one buffer per thread, never made resident)."""
    local = threading.local()

    def block_range(start: int) -> tuple[np.ndarray, np.ndarray]:
        if not hasattr(local, "buffer"):
            local.buffer = np.empty(min(rows, flat.shape[0]) * flat.shape[1], flat.dtype)
        return _column_range(read_block(flat, 0, slice(start, start + rows), local.buffer))

    parts = list(_in_order(block_range, list(range(0, flat.shape[0], rows)), WRITE_THREADS))
    return np.min([low for low, _ in parts], axis=0), np.max([high for _, high in parts], axis=0)


class _Quantizer:
    """Per-coefficient scale and bias over a whole model ``coeffs [H, W, K, 6]``, and the bytes of any band of it.

    Coefficients that may lie on a byte grid (a model read from an 8-bit PTM) are checked whole, as
    :func:`_grid_quantization` needs; dense float coefficients are encoded band by band, so writing a large
    model takes no copy of it.
    """

    def __init__(self, coeffs: np.ndarray, owner: str = "write_ptm"):
        self.coeffs = coeffs
        self._local = threading.local()  # working arrays, one set per thread: bands are encoded in parallel
        flat = coeffs.reshape(-1, N_COEFFS)
        sample = _spread_sample(flat)
        lows, highs = _paged_column_range(flat)
        if not (np.isfinite(lows).all() and np.isfinite(highs).all()):  # min and max see every NaN and Inf
            _not_finite(owner, coeffs)
        self.scales, self.biases, self.steps, self.whole = [], [], [], {}
        for i in range(N_COEFFS):
            low, high = float(lows[i]), float(highs[i])
            quantized = None
            if _grid_possible(sample[:, i], low, high):
                quantized = _grid_quantization(np.ascontiguousarray(coeffs[..., i], dtype=np.float64))
            if quantized is not None:
                scale, bias, self.whole[i] = quantized
                step = 0.0
            else:
                scale, bias, step = _range_plan(low, high)
            self.scales.append(scale)
            self.biases.append(bias)
            self.steps.append(step)
        # Each coefficient's step and bias repeated along a whole row of texels: against an operand of 6 values,
        # NumPy's inner loop over a band would be 6 elements long (3x slower for the same arithmetic).
        texel_row = coeffs.shape[1] * coeffs.shape[2]
        self._step_row = np.tile(np.array([step or 1.0 for step in self.steps]), texel_row)
        self._bias_row = np.tile(np.array(self.biases, np.float64), texel_row)

    def _buffer(self, name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
        """A flat working array of at least ``shape``'s size, kept for the next band."""
        size = math.prod(shape)
        buffers = self._local.__dict__.setdefault("buffers", {})
        found = buffers.get(name)
        if found is None or found.size < size or found.dtype != dtype:
            found = buffers[name] = np.empty(size, dtype)
        return found

    def levels(self, rows: slice) -> np.ndarray:
        """Bytes ``[rows, W, K, 6]`` of every channel's coefficients of a band of rows."""
        # All coefficients in one pass (the arithmetic of _range_levels, column by column), then the
        # coefficients stored on their own grid, or constant zero, put in place.
        shape = self.coeffs[rows].shape
        # Both working arrays are reused from band to band, so their pages are faulted in once.
        part = read_block(self.coeffs, 0, rows, self._buffer("part", shape, self.coeffs.dtype))
        band = self._buffer("band", shape, np.float64).reshape(-1)[:part.size].reshape(shape)
        part_rows, band_rows = part.reshape(len(part), -1), band.reshape(len(band), -1)
        # float32 read as float64: the same operations as _range_levels
        np.divide(part_rows, self._step_row, out=band_rows)
        np.add(band_rows, self._bias_row, out=band_rows)
        np.rint(band, out=band)
        out = np.clip(band, 0, 255, out=band).astype(np.uint8)
        for i in range(N_COEFFS):
            if i in self.whole:
                out[..., i] = self.whole[i][rows]
            elif self.steps[i] == 0.0:
                out[..., i] = 0
        return out


WRITE_BAND_BYTES = 2 << 20  # float64 working set of one band of rows while writing (one band per thread)
WRITE_THREADS = 2  # bands encoded at once (NumPy's arithmetic runs without the GIL)


def _in_order(function: Callable, items: list, threads: int):
    """``function(item)`` for each of ``items``, in order, computed ``threads`` at a time a little ahead of the
    caller (at most ``2 * threads`` results wait)."""
    if threads < 2 or len(items) < 2:
        yield from map(function, items)
        return
    with concurrent.futures.ThreadPoolExecutor(threads, thread_name_prefix="btforge-write") as pool:
        pending = collections.deque()
        try:
            for item in items:
                pending.append(pool.submit(function, item))
                if len(pending) >= 2 * threads:
                    yield pending.popleft().result()
            while pending:
                yield pending.popleft().result()
        finally:
            for future in pending:
                future.cancel()


def write_ptm(path, variant: str, coeffs: np.ndarray, albedo: np.ndarray | None) -> None:
    """Write a model as a raw ``PTM_FORMAT_LRGB`` (variant ``'lrgb'``) or ``PTM_FORMAT_RGB`` (``'rgb'``) file.

    Each coefficient gets its own scale and integer bias covering its whole range over the image (and zero,
    which every byte grid with a bias in 0..255 contains); values are rounded to the nearest level, so each
    decoded coefficient is within half a level of the input.  Coefficients that already lie on a byte grid
    (a model read from an 8-bit PTM) are stored on that grid, losslessly.  The file appears atomically.

    Parameters
    ----------
    path
        Destination ``.ptm`` file (parent folders are created).
    variant
        ``'lrgb'`` or ``'rgb'``.
    coeffs
        Unit-scale coefficients, float ``[H, W, K, 6]``, ``K = 1`` for lrgb and 3 for rgb, row 0 at the top.
    albedo
        Float ``[H, W, 3]`` in ``[0, 1]`` for lrgb; ``None`` for rgb.
    """
    # the coefficients are checked finite by the quantizer's pass over them
    coeffs, albedo = _checked_model("write_ptm", variant, coeffs, albedo, coeffs_finite_later=True)
    height, width = coeffs.shape[:2]
    quantizer = _Quantizer(coeffs)
    header = "\n".join([
        PTM_VERSION,
        WRITE_FORMAT[variant],
        str(width),
        str(height),  # width and height on separate lines: some readers insist on it
        " ".join(_scale_text(s) for s in quantizer.scales),
        " ".join(str(b) for b in quantizer.biases),
    ]) + "\n"
    rows_per_band = max(1, WRITE_BAND_BYTES // (width * coeffs.shape[2] * N_COEFFS * 8))
    plane = height * width * N_COEFFS  # bytes of one channel's coefficients
    with atomic_write(path, "wb") as handle:
        start = handle.write(header.encode("ascii"))
        # Files store the bottom row first; an rgb file holds each channel's plane in turn, then lrgb its colours.
        # Each band of rows is read once and its bytes placed in every channel's plane.
        bands = [slice(max(0, stop - rows_per_band), stop) for stop in range(height, 0, -rows_per_band)]

        def planes(rows: slice) -> list[np.ndarray]:  # each channel's bytes of the band, bottom row first
            # a texel's 6 bytes as one item: copied item by item rather than byte by byte
            texels = quantizer.levels(rows).view(f"V{N_COEFFS}")[..., 0]
            return [np.ascontiguousarray(texels[::-1, :, channel]).view(np.uint8)
                    for channel in range(coeffs.shape[2])]

        for stop, parts in zip((rows.stop for rows in bands), _in_order(planes, bands, WRITE_THREADS)):
            for channel, part in enumerate(parts):
                handle.seek(start + channel * plane + (height - stop) * width * N_COEFFS)
                handle.write(memoryview(part).cast("B"))
        handle.seek(start + coeffs.shape[2] * plane)
        if variant == "lrgb":
            for stop in range(height, 0, -rows_per_band):
                rows = albedo[max(0, stop - rows_per_band):stop][::-1]
                rgb = np.clip(np.rint(rows.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)
                handle.write(memoryview(np.ascontiguousarray(rgb)).cast("B"))
