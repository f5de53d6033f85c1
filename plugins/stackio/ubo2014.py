"""Reading the Bonn BTF database's UBO2014 ``.btf`` files: the DFMF format (a per-channel SVD of the BTF).

The layout, as the Bonn group's public readers (btflib, and the MIT-licensed "Free BTF Library") read it; every
number is little-endian, a ``float`` is 32 bits:

* **signature** ``!DFMF08FC``, then ``R`` when the file stores rotations of local frames (UBO2014 files do).
* **meta block**, whose first ``uint32`` is its own length in bytes: ``uint32 version``; three ``char[80]``
  (measurement setup, image sensor, light source); ``float`` pixels per mm; ``float[3]`` RGB scale; for
  version > 1 ``uint32`` cosine flag (the cosine of the light's polar angle is multiplied into the values); for
  version > 2 ``uint32`` length and the measurement's XML text; for version > 3 ``uint32`` channel count and per
  channel ``uint32`` length and name (otherwise R, G, B).
* **directions**: ``uint32`` view count; per view ``float`` theta, phi (radians, polar angle from the zenith and
  azimuth), ``uint32`` light count and that many ``float`` theta, phi pairs.  Every view has the same lights.
* ``uint32`` width, height; with ``R``, ``uint32`` rotation count and that many ``float[3][3]``.
* **DFMF**: ``uint32`` components, ``int32`` colour model, ``float[3]`` colour mean, ``float[3][3]`` colour
  transform (row-major).  Then per channel: ``uint8`` scalar size (2: IEEE half, 4: float, 8: double),
  ``uint32`` components K, ``uint32`` rows, ``uint32`` columns, K singular values, then the left matrix U
  (rows x K) and the right matrix S*V^T stored as columns x K, both row-major.  Rows are the light-view pairs
  (index ``view * lights + light``) and columns the texels (index ``y * width + x``, row 0 first in the file);
  a file may store the transpose (rows are texels), which is read as well - except when there are as many
  light-view pairs as texels, where the sizes cannot tell and U is taken as the pairs (as the Bonn readers do).

A channel's value at (light-view pair, texel) is the dot product of their K-vectors; the channels are then
turned back into RGB by the colour model (:func:`undecorrelate`).  The matrices are memory-mapped, so a band of
texels is decoded without reading the whole file.

Only DFMF is read.  The other Bonn signatures (FMF, PVF, BDIF) are refused with the reason, as are the colour
models that need more than a matrix (LAB, the spectral ones).
"""
from __future__ import annotations

import dataclasses
import os
import struct
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from btforge.errors import BtforgeInputError

DFMF_SIGNATURE = b"!DFMF08FC"
# Bonn signatures that are not DFMF, longest first, with what they are (refused with that reason).
OTHER_SIGNATURES = (
    (b"!BDIF06R2!", "BDI (raw bidirectional images in chunks, the UBO2014 'uncompressed' downloads)"),
    (b"!FMF12FCE", "FMF (one full-matrix SVD of all channels, with an extended header)"),
    (b"!FMF06FC", "FMF (one full-matrix SVD of all channels)"),
    (b"!PVF06FC", "PVF (a separate SVD per view)"),
)
SCALAR_TYPES = {2: np.dtype("<f2"), 4: np.dtype("<f4"), 8: np.dtype("<f8")}
LOG_EPSILON = 1e-5  # the offset the log colour models add before taking the logarithm
YUV_TO_RGB = np.array([[1.0, 0.0, 1.13983], [1.0, -0.39465, -0.5806], [1.0, 2.03211, 0.0]])
YCOCG_TO_RGB = np.array([[1.0, 1.0, -1.0], [1.0, 0.0, 1.0], [1.0, -1.0, -1.0]])
COLOUR_MODELS = {0: "RGB", 1: "YUV", 3: "PCA", 4: "YCoCg", 9: "log Y, U, V", 10: "log Y, log U, log V",
                 11: "log Y, U / Y, V / Y", 12: "log RGB"}
REFUSED_MODELS = {2: "LAB", 5: "spectral", 6: "linear spectral"}


def spherical_to_unit(angles: np.ndarray) -> np.ndarray:
    """``[N, 2]`` (polar angle from the zenith, azimuth) in radians -> unit vectors ``[N, 3]``."""
    theta, phi = angles[:, 0].astype(np.float64), angles[:, 1].astype(np.float64)
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)


@dataclasses.dataclass(frozen=True)
class Factor:
    """One channel's factorisation: where its matrices lie in the file and which side is which."""

    dtype: np.dtype
    components: int
    rows: int
    cols: int
    singular_offset: int
    left_offset: int
    right_offset: int

    @property
    def end(self) -> int:
        return self.right_offset + self.cols * self.components * self.dtype.itemsize


class _Cursor:
    """Sequential little-endian reads that name the field and the byte offset when the file ends early."""

    def __init__(self, handle: BinaryIO, where: str):
        self.handle, self.where = handle, where

    @property
    def offset(self) -> int:
        return self.handle.tell()

    def bytes(self, count: int, field: str) -> bytes:
        at = self.offset
        data = self.handle.read(min(count, self.size - at))  # a damaged count asks for no more than the file has
        if len(data) != count:
            raise BtforgeInputError(f"{self.where}, byte {at}", f"expected {count} bytes of {field}, found "
                                    f"{len(data)} before the end of the file", "the file is truncated; download it again")
        return data

    def unpack(self, fmt: str, field: str) -> tuple:
        return struct.unpack("<" + fmt, self.bytes(struct.calcsize("<" + fmt), field))

    def one(self, fmt: str, field: str):
        return self.unpack(fmt, field)[0]

    def text(self, count: int, field: str) -> str:
        return self.bytes(count, field).split(b"\0", 1)[0].decode("latin-1")

    def skip(self, count: int, field: str) -> None:
        at = self.offset
        self.handle.seek(count, os.SEEK_CUR)
        if self.offset > self.size:
            raise BtforgeInputError(f"{self.where}, byte {at}", f"expected {count} bytes of {field}, found "
                                    f"{self.size - at} before the end of the file", "the file is truncated; download it again")

    @property
    def size(self) -> int:
        return os.fstat(self.handle.fileno()).st_size


def read_signature(path: str | os.PathLike) -> bytes:
    """The file's signature if it is DFMF; any other Bonn format, or none, is refused with what was found."""
    with open(path, "rb") as handle:
        head = handle.read(16)
    if head.startswith(DFMF_SIGNATURE):
        return DFMF_SIGNATURE + (b"R" if head[len(DFMF_SIGNATURE):].startswith(b"R") else b"")
    for signature, what in OTHER_SIGNATURES:
        if head.startswith(signature):
            raise BtforgeInputError(str(path), f"is a Bonn BTF in the {what} format (signature "
                                    f"{signature.decode()!r}); btforge reads the DFMF format (signature '!DFMF08FCR') "
                                    "of the UBO2014 downloads only", "use the database's DFMF (.btf) download of the "
                                    "material, or its images (UBO2003 zip layout)")
    raise BtforgeInputError(str(path), f"expected a Bonn UBO2014 BTF starting with '!DFMF08FC', found {head[:10]!r}",
                            "give a .btf file of the Bonn BTF database (DFMF format)")


@dataclasses.dataclass(frozen=True)
class DFMFFile:
    """A DFMF ``.btf`` file's header and the places of its matrices (see the module docs); :meth:`decode`
    gives radiance."""

    path: str
    version: int
    measurement_setup: str
    image_sensor: str
    light_source: str
    pixels_per_mm: float
    rgb_scale: tuple[float, float, float]
    cosine_flag: bool
    channels: tuple[str, ...]
    light_angles: np.ndarray      # [L, 2] radians (theta, phi)
    view_angles: np.ndarray       # [V, 2]
    width: int
    height: int
    rotations: int
    colour_model: int
    colour_mean: np.ndarray       # [3]
    colour_transform: np.ndarray  # [3, 3]
    factors: tuple[Factor, ...]

    @property
    def lights(self) -> np.ndarray:
        return spherical_to_unit(self.light_angles)

    @property
    def views(self) -> np.ndarray:
        return spherical_to_unit(self.view_angles)

    @property
    def n_light(self) -> int:
        return len(self.light_angles)

    @property
    def n_view(self) -> int:
        return len(self.view_angles)

    def _maps(self, factor: Factor) -> tuple[np.ndarray, np.ndarray]:
        left = np.memmap(self.path, factor.dtype, "r", factor.left_offset, (factor.rows, factor.components))
        right = np.memmap(self.path, factor.dtype, "r", factor.right_offset, (factor.cols, factor.components))
        return left, right

    def matrices(self, channel: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Channel ``channel``'s singular values ``[K]``, U ``[rows, K]`` and S*V^T ``[cols, K]`` as stored."""
        factor = self.factors[channel]
        singular = np.memmap(self.path, factor.dtype, "r", factor.singular_offset, (factor.components,))
        return (np.array(singular), *(np.array(m) for m in self._maps(factor)))

    def decode(self, rows: slice = slice(None), cols: slice = slice(None)) -> np.ndarray:
        """Linear radiance ``[V, L, h, w, C]`` float32 of a block of texels, decoded from the factors (only the
        block's rows of the texel matrices are read)."""
        ys, xs = np.arange(self.height)[rows], np.arange(self.width)[cols]
        texels = (ys[:, None] * self.width + xs[None, :]).ravel()
        n_pair = self.n_view * self.n_light
        values = np.empty((n_pair, len(texels), len(self.channels)), np.float32)
        for c, factor in enumerate(self.factors):
            left, right = self._maps(factor)
            if factor.rows == n_pair:     # U holds the light-view pairs, S*V^T the texels
                angular, spatial = left, right[texels]
            else:                         # stored transposed: U holds the texels
                angular, spatial = right, left[texels]
            values[:, :, c] = np.asarray(angular, np.float32) @ np.asarray(spatial, np.float32).T
        values = undecorrelate(values, self.colour_model, self.colour_mean, self.colour_transform, self.path)
        if self.cosine_flag:  # the values hold radiance times cos(theta_light): divide it out
            cosine = np.maximum(np.cos(self.light_angles[:, 0]), 1e-6).astype(np.float32)
            values /= np.tile(cosine, self.n_view)[:, None, None]
        return values.reshape(self.n_view, self.n_light, len(ys), len(xs), len(self.channels))

    def summary(self) -> dict[str, Any]:
        """What ``btforge info`` shows for the file."""
        first = self.factors[0]
        return {"kind": "Bonn UBO2014 BTF (DFMF)", "texels": [self.height, self.width], "views": self.n_view,
                "lights": self.n_light, "channels": list(self.channels),
                "colour_model": COLOUR_MODELS.get(self.colour_model, self.colour_model),
                "components": [f.components for f in self.factors], "scalar": str(first.dtype),
                "cosine_in_values": self.cosine_flag, "measurement_setup": self.measurement_setup,
                "image_sensor": self.image_sensor, "light_source": self.light_source}


def _meta_block(cur: _Cursor) -> dict[str, Any]:
    start = cur.offset
    size, version = cur.unpack("II", "the meta block's length and version")
    meta: dict[str, Any] = {"version": version}
    for name in ("measurement_setup", "image_sensor", "light_source"):
        meta[name] = cur.text(80, name.replace("_", " "))
    meta["pixels_per_mm"] = cur.one("f", "pixels per mm")
    meta["rgb_scale"] = cur.unpack("fff", "the RGB scale")
    meta["cosine_flag"] = bool(cur.one("I", "the cosine flag")) if version > 1 else False
    if version > 2:
        cur.skip(cur.one("I", "the XML length"), "the measurement XML")
    channels = ("R", "G", "B")
    if version > 3:
        count = cur.one("I", "the channel count")
        if not 1 <= count <= 64:
            raise BtforgeInputError(f"{cur.where}, byte {cur.offset - 4}", f"expected 1-64 channels, found {count}",
                                    "the file is damaged")
        channels = tuple(cur.text(cur.one("I", "a channel name's length"), "a channel name") or f"C{i}"
                         for i in range(count))
    meta["channels"] = channels
    if cur.offset - start != size:
        raise BtforgeInputError(f"{cur.where}, byte {start}", f"expected a meta block of {size} bytes (version "
                                f"{version}), read {cur.offset - start}", "the file is damaged or of a newer version")
    return meta


def _directions(cur: _Cursor) -> tuple[np.ndarray, np.ndarray]:
    n_view = cur.one("I", "the view count")
    views, lights = [], None
    for v in range(n_view):
        views.append(cur.unpack("ff", f"view {v}'s angles"))
        at = cur.offset
        n_light = cur.one("I", f"view {v}'s light count")
        angles = np.frombuffer(cur.bytes(8 * n_light, f"view {v}'s light angles"), "<f4").reshape(n_light, 2)
        if lights is None:
            lights = angles.astype(np.float64)
        elif n_light != len(lights):
            raise BtforgeInputError(f"{cur.where}, byte {at}", f"expected {len(lights)} lights for view {v} like "
                                    f"view 0, found {n_light}", "btforge reads BTFs whose views share one light set")
    if not n_view or lights is None or not len(lights):
        raise BtforgeInputError(cur.where, f"expected at least one view and one light, found {n_view} view(s)",
                                "the file is damaged")
    return lights, np.asarray(views, np.float64)


def _factor(cur: _Cursor, channel: str, n_pair: int, n_texel: int) -> Factor:
    at = cur.offset
    scalar = cur.one("B", f"channel {channel}'s scalar size")
    if scalar not in SCALAR_TYPES:
        raise BtforgeInputError(f"{cur.where}, byte {at}", f"expected a scalar size of 2, 4 or 8 bytes for channel "
                                f"{channel}, found {scalar}", "the file is damaged")
    components, rows, cols = cur.unpack("III", f"channel {channel}'s matrix sizes")
    if sorted((rows, cols)) != sorted((n_pair, n_texel)) or components < 1:
        raise BtforgeInputError(f"{cur.where}, byte {at + 1}", f"expected channel {channel}'s matrices to be "
                                f"{n_pair} light-view pairs by {n_texel} texels with at least one component, found "
                                f"{rows} x {cols} with {components}", "the file is damaged")
    dtype = SCALAR_TYPES[scalar]
    singular = cur.offset
    left = singular + components * scalar
    right = left + rows * components * scalar
    factor = Factor(dtype, components, rows, cols, singular, left, right)
    cur.skip(factor.end - singular, f"channel {channel}'s singular values and matrices")
    return factor


def read_dfmf(path: str | os.PathLike) -> DFMFFile:
    """Open a DFMF ``.btf`` file: its header is read and checked, its matrices are mapped, not read."""
    path = Path(path)
    signature = read_signature(path)
    where = str(path)
    with open(path, "rb") as handle:
        cur = _Cursor(handle, where)
        handle.seek(len(signature))
        meta = _meta_block(cur)
        lights, views = _directions(cur)
        width, height = cur.unpack("II", "the width and height")
        rotations = 0
        if signature.endswith(b"R"):
            rotations = cur.one("I", "the rotation count")
            cur.skip(36 * rotations, "the rotations")
        _, model = cur.unpack("Ii", "the component count and colour model")
        mean = np.array(cur.unpack("3f", "the colour mean"))
        transform = np.array(cur.unpack("9f", "the colour transform")).reshape(3, 3)
        check_colour_model(model, len(meta["channels"]), f"{where}, byte {cur.offset - 52}")
        n_pair, n_texel = len(lights) * len(views), width * height
        factors = tuple(_factor(cur, name, n_pair, n_texel) for name in meta["channels"])
        if cur.size != factors[-1].end:
            raise BtforgeInputError(where, f"expected the file to end at byte {factors[-1].end} after the last "
                                    f"channel, found {cur.size} bytes", "the file is damaged or not DFMF")
    return DFMFFile(where, meta["version"], meta["measurement_setup"], meta["image_sensor"], meta["light_source"],
                    meta["pixels_per_mm"], meta["rgb_scale"], meta["cosine_flag"], meta["channels"], lights, views,
                    width, height, rotations, model, mean, transform, factors)


def check_colour_model(model: int, n_channel: int, where: str) -> None:
    if model in REFUSED_MODELS:
        raise BtforgeInputError(where, f"uses the {REFUSED_MODELS[model]} colour model ({model}), which btforge does "
                                f"not decode (it reads {', '.join(COLOUR_MODELS.values())})",
                                "convert the file to RGB with the Bonn tools first")
    if model not in COLOUR_MODELS:
        raise BtforgeInputError(where, f"expected a colour model among {sorted(COLOUR_MODELS)}, found {model}",
                                "the file is damaged or of a newer version")
    if model != 0 and n_channel != 3:
        raise BtforgeInputError(where, f"expected 3 channels for the {COLOUR_MODELS[model]} colour model, found "
                                f"{n_channel}", "the file is damaged")


def undecorrelate(values: np.ndarray, model: int, mean: np.ndarray, transform: np.ndarray, where: str) -> np.ndarray:
    """Decorrelated channels ``[..., C]`` -> RGB (in place where it can), by the file's colour model."""
    check_colour_model(model, values.shape[-1], where)
    if model == 0:
        return values
    if model == 12:
        np.exp(values, out=values)
        values -= np.float32(LOG_EPSILON)
        return values
    if model == 3:
        return (values @ transform.astype(np.float32) + mean.astype(np.float32)).astype(np.float32)
    if model == 4:
        return (values @ YCOCG_TO_RGB.T.astype(np.float32)).astype(np.float32)
    if model in (9, 10, 11):
        luma = values[..., 0]
        np.exp(luma, out=luma)
        if model == 11:    # U and V were divided by Y (+ epsilon)
            values[..., 1:] *= luma[..., None]
        luma -= np.float32(LOG_EPSILON)
        if model == 10:    # signed log of the chroma, offset by log(epsilon)
            chroma = values[..., 1:]
            values[..., 1:] = np.sign(chroma) * np.exp(np.abs(chroma) + np.float32(np.log(LOG_EPSILON)))
    return (values @ YUV_TO_RGB.T.astype(np.float32)).astype(np.float32)
