"""Images of a multi-light capture: decoding them into a :class:`~btforge.buffers.SampleStack` and writing one back.

Conventions (the ones RTI tools use in practice):

* 8-bit images (JPEG, PNG, TIFF) hold sRGB-encoded camera values.  :func:`load_stack` keeps them as uint8
  (``encoding='srgb8'``, a quarter of the memory of float32) and decodes to linear on access.
* 16-bit images hold linear values in ``[0, 65535]``; float images (OpenEXR, float TIFF) hold linear radiance.
* Alpha is dropped; an image has 1 (``'Y'``) or 3 (``'R', 'G', 'B'``) channels.

JPEG is decoded by simplejpeg when it is installed (the same pixels as Pillow, faster).  Pillow decodes everything
else except OpenEXR (official ``OpenEXR`` bindings) and the 16-bit colour layouts Pillow
would silently cut to 8 bits: 16-bit colour PNG is decoded losslessly through Pillow's own PNG decoder (see
:func:`_read_png16_colour`), other such files (16-bit or float colour TIFF) go to ``imageio`` when it is
installed, and otherwise stop with an error rather than lose precision.
"""
from __future__ import annotations

import concurrent.futures
import io
import os
import re
import struct
import threading
import zipfile
import zlib
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from btforge.atomic import atomic_output_path, atomic_write
from btforge.buffers import SRGB8_TO_LINEAR, SampleStack, linear_to_srgb8, srgb_to_linear
from btforge.errors import BtforgeInputError, reading_file

from .lightfile import LightFileEntry, image_path, is_btf_zip, read_capture_index, write_light_file

__all__ = ["read_image", "read_exr", "load_stack", "write_stack", "write_exr", "write_png"]

TRANSFERS = ("auto", "srgb", "linear")
HALF_MAX = 65504.0

# Pillow modes whose pixels end up as 8-bit colour after a conversion to RGB (alpha and padding dropped).
_PILLOW_COLOUR_MODES = {"RGB", "RGBA", "RGBX", "RGBa", "CMYK", "YCbCr", "LAB", "HSV", "P", "PA"}
_PILLOW_GREY_MODES = {"1", "L", "LA", "La"}


# ----------------------------------------------------------------------------------------------- reading


def _bit_depth(dtype: np.dtype) -> str:
    return {"u1": "8-bit", "u2": "16-bit"}.get(f"{dtype.kind}{dtype.itemsize}", "float")


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """Read an OpenEXR image as linear float32 ``[H, W, C]``.

    ``R``, ``G``, ``B`` channels give ``C = 3`` (alpha and any other channels are ignored), a lone ``Y``
    channel gives ``C = 1``.  Half and float channels are both returned as float32.  NaN/Inf values are returned
    as they are; :func:`load_stack` rejects them.
    """
    import OpenEXR

    path_text = str(path)
    if not Path(path).is_file():
        raise BtforgeInputError(path_text, "image not found")
    try:
        exr = OpenEXR.File(path_text, separate_channels=True)
        channels = exr.channels()
    except Exception as exc:  # the bindings raise bare RuntimeErrors with C-level text
        raise BtforgeInputError(path_text, f"cannot read the OpenEXR image: {exc}",
                                "check that the file is a complete, uncorrupted .exr") from None
    names = set(channels)
    if {"R", "G", "B"} <= names:
        wanted = ["R", "G", "B"]
    elif "Y" in names and not names & {"RY", "BY"}:
        wanted = ["Y"]
    elif "Y" in names:
        raise BtforgeInputError(path_text, "expected R, G, B or Y channels, found a luminance/chroma image "
                                "(Y, RY, BY)", "convert it to RGB, e.g. with oiiotool or exrmaketiled")
    else:
        raise BtforgeInputError(path_text, f"expected R, G, B or Y channels, found {sorted(names)}",
                                "write the radiance into channels named R, G, B (or Y for grey)")
    planes = [np.asarray(channels[name].pixels) for name in wanted]
    if any(p.ndim != 2 or p.shape != planes[0].shape for p in planes):
        raise BtforgeInputError(path_text, "expected full-resolution channels, found subsampled ones: "
                                + ", ".join(f"{n} {p.shape}" for n, p in zip(wanted, planes)))
    if any(p.dtype.kind != "f" for p in planes):
        raise BtforgeInputError(path_text, "expected half or float channels, found "
                                + ", ".join(f"{n} {p.dtype}" for n, p in zip(wanted, planes)))
    return np.stack(planes, axis=-1).astype(np.float32, copy=False)


def _rawmode(image: Any) -> str:
    """The packing Pillow will decode from (e.g. ``'RGB;16B'``), or '' when it cannot be told."""
    tile = getattr(image, "tile", None)
    if not tile:
        return ""
    args = tile[0][3] if len(tile[0]) > 3 else None
    if isinstance(args, str):
        return args
    if isinstance(args, tuple) and args and isinstance(args[0], str):
        return args[0]
    return ""


def _read_png16_colour(path: str, rawmode: str) -> np.ndarray:
    """Decode a 16-bit colour PNG without losing the low byte.

    Pillow has no 16-bit colour mode, so its PNG decoder keeps only the high byte of each sample
    (``'RGB;16B'``).  Its unpacker for little-endian data (``'RGB;16L'``) keeps the *second* byte instead -
    which, on this big-endian data, is the low byte - while the PNG unfiltering, which depends only on the
    bytes per pixel, is identical.  Two decodes therefore give both halves.  Grey + alpha (``'LA;16B'``) is
    4 bytes a pixel, which the plain ``'RGBA'`` unpacker passes through whole in a single decode.
    """
    from PIL import Image

    def decode(new_rawmode: str) -> np.ndarray:
        if hasattr(path, "seek"):
            path.seek(0)
        with Image.open(path) as image:
            image.tile = [image.tile[0]._replace(args=new_rawmode)]
            image.load()
            return np.asarray(image)

    if rawmode == "LA;16B":
        bytes_la = decode("RGBA").astype(np.uint16)
        return (bytes_la[..., 0] << 8 | bytes_la[..., 1])[..., None]
    high = decode(rawmode).astype(np.uint16)
    low = decode(rawmode[:-1] + "L")
    return (high << 8 | low)[..., :3]


def _read_with_imageio(path: str, reason: str) -> np.ndarray:
    """Fallback for layouts Pillow cannot decode losslessly; refuses rather than returning degraded data."""
    try:
        import imageio.v3 as iio
    except ImportError:
        raise BtforgeInputError(path, f"cannot decode {reason} with Pillow without losing precision",
                                "install imageio (pip install imageio), or convert the image to 16-bit PNG or "
                                "OpenEXR") from None
    try:
        array = np.asarray(iio.imread(path))
    except Exception as exc:
        raise BtforgeInputError(path, f"cannot decode {reason}: imageio failed with {exc}",
                                "convert the image to 16-bit PNG or OpenEXR") from None
    if array.dtype == np.uint8:
        raise BtforgeInputError(path, f"cannot decode {reason}: the available decoders return only 8 bits",
                                "convert the image to 16-bit PNG or OpenEXR, or install tifffile")
    return array


def _normalised(array: np.ndarray, path: str) -> np.ndarray:
    """``[H, W, C]`` with ``C`` 1 or 3 in uint8, uint16 or float32 (native byte order)."""
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[2] not in (1, 2, 3, 4):
        raise BtforgeInputError(path, f"expected a grey or colour image, found an array of shape {array.shape}",
                                "multi-page and volume images are not supported")
    if array.shape[2] == 2:
        array = array[..., :1]
    elif array.shape[2] == 4:
        array = array[..., :3]
    kind = array.dtype.kind
    if kind == "u" and array.dtype.itemsize in (1, 2):
        array = array.astype(array.dtype.newbyteorder("="), copy=False)
    elif kind == "f":
        array = array.astype(np.float32, copy=False)
    elif kind in "iu" and array.size and array.min() >= 0 and array.max() <= 65535:
        # Pillow's 32-bit 'I' mode is how some readers hand over 16-bit grey data.
        array = array.astype(np.uint16)
    else:
        raise BtforgeInputError(path, f"expected 8-bit, 16-bit or float samples, found {array.dtype}",
                                "convert the image to 16-bit PNG or OpenEXR")
    return np.ascontiguousarray(array)


def _read_pillow(path, label: str | None = None) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    source, path = path, label or str(path)  # messages name the file; an in-memory file is read from 'source'
    try:
        with Image.open(source) as image:
            mode, rawmode, fmt = image.mode, _rawmode(image), image.format
            high_depth_colour = bool(re.search(r";16", rawmode)) and mode in ("RGB", "RGBA", "LA")
            if not high_depth_colour:
                if mode in _PILLOW_COLOUR_MODES and mode != "RGB":
                    image = image.convert("RGB")
                elif mode in _PILLOW_GREY_MODES and mode != "L":
                    image = image.convert("L")
                else:
                    image.load()
                return np.asarray(image)
    except FileNotFoundError:
        raise BtforgeInputError(path, "image not found") from None
    except UnidentifiedImageError:
        if Path(path).suffix.lower() in (".tif", ".tiff"):
            # Pillow does not open float or 16-bit colour TIFF at all.
            return _read_with_imageio(path, "this TIFF layout")
        raise BtforgeInputError(path, "cannot identify the image format",
                                "use PNG, JPEG, TIFF or OpenEXR (.exr)") from None
    except OSError as exc:
        raise BtforgeInputError(path, f"cannot decode the image: {exc}",
                                "the file may be truncated or corrupted") from None

    if fmt == "PNG" and rawmode in ("RGB;16B", "RGBA;16B", "LA;16B"):
        try:
            return _read_png16_colour(source, rawmode)
        except (ValueError, OSError, AttributeError, IndexError):
            pass  # a Pillow without these unpackers: let imageio try
    return _read_with_imageio(path, f"16-bit colour {fmt or 'image'} ({rawmode})")


def _contents(source) -> bytes:
    """The bytes of an image file: a path, or an in-memory file (a member of a zip archive)."""
    if hasattr(source, "getvalue"):
        return source.getvalue()
    with open(source, "rb") as handle:
        return handle.read()


def _jpeg_turbo_into(path, out: np.ndarray) -> bool:
    """Decode a JPEG with simplejpeg straight into ``out`` (C-contiguous uint8 ``[H, W, C]``); False (and ``out``
    untouched) when the file is not such a JPEG of exactly that shape, so the caller decodes it the usual way."""
    try:
        import simplejpeg
    except ImportError:
        return False
    try:
        data = _contents(path)
        height, width, colourspace, _ = simplejpeg.decode_jpeg_header(data)
        channels = 1 if colourspace == "Gray" else 3
        if colourspace not in ("Gray", "YCbCr", "RGB") or (height, width, channels) != out.shape \
                or not out.flags.c_contiguous:
            return False
        simplejpeg.decode_jpeg(data, colorspace="GRAY" if channels == 1 else "RGB", buffer=out)
        return True
    except (OSError, ValueError):
        return False


def _read_jpeg_turbo(path) -> np.ndarray | None:
    """A grey or colour JPEG decoded by simplejpeg (libjpeg-turbo), or None to let Pillow decode the file.

    Same pixels as Pillow (both use libjpeg-turbo's accurate integer DCT and smooth upsampling), in 30-40 %
    less time on this machine (README, Benchmarks).  CMYK and YCCK files, damaged files and a missing simplejpeg
    are left to Pillow, which has the clearer messages.
    """
    try:
        import simplejpeg
    except ImportError:
        return None
    try:
        data = _contents(path)
        colourspace = simplejpeg.decode_jpeg_header(data)[2]
        if colourspace not in ("Gray", "YCbCr", "RGB"):
            return None
        return simplejpeg.decode_jpeg(data, colorspace="GRAY" if colourspace == "Gray" else "RGB")
    except (OSError, ValueError):
        return None


def read_image(path, name: str | None = None) -> tuple[np.ndarray, str]:
    """Read one image of a capture: a file, or an in-memory file (``io.BytesIO``) called ``name``.

    Returns
    -------
    array
        ``[H, W, C]`` with ``C`` 1 or 3 (alpha dropped): uint8 for 8-bit files, uint16 for 16-bit files,
        float32 for OpenEXR and float TIFF.
    transfer
        ``'srgb'`` for 8-bit data (camera-encoded), ``'linear'`` for 16-bit and float data.
    """
    path_text = name or str(path)
    # decoders raise many kinds of errors on damaged data (Pillow: SyntaxError for a broken PNG chunk)
    with reading_file(path_text, "an image", "the file may be truncated or corrupted; copy it again"):
        return _read_image(path, path_text)


def _read_image(path, path_text: str) -> tuple[np.ndarray, str]:
    in_memory = hasattr(path, "getvalue")
    suffix = Path(path_text).suffix.lower()
    if suffix == ".exr":
        if in_memory:
            raise BtforgeInputError(path_text, "OpenEXR images inside a zip archive cannot be read",
                                    "unpack the archive and read the folder")
        array = read_exr(path)
    else:
        array = (_read_jpeg_turbo(path) if suffix in (".jpg", ".jpeg") else None)
        if array is None:
            array = _read_pillow(path if in_memory else path_text, path_text)
    array = _normalised(array, path_text)
    return array, ("srgb" if array.dtype == np.uint8 else "linear")


# ----------------------------------------------------------------------------------------------- stacks


_SRGB16_TO_LINEAR: np.ndarray | None = None


def _srgb16_lut() -> np.ndarray:
    global _SRGB16_TO_LINEAR
    if _SRGB16_TO_LINEAR is None:
        _SRGB16_TO_LINEAR = srgb_to_linear(np.arange(65536) / 65535.0).astype(np.float32)
    return _SRGB16_TO_LINEAR


def _converter(dtype: np.dtype, transfer: str) -> Callable[[np.ndarray, np.ndarray], None]:
    """A function that writes one decoded image into its slot of the stack, applying the transfer curve."""
    is_srgb = transfer == "srgb"
    if dtype == np.uint8:
        if transfer in ("auto", "srgb"):
            return lambda src, dst: np.copyto(dst, src)
        return lambda src, dst: np.multiply(src, np.float32(1 / 255), out=dst)
    if dtype == np.uint16:
        if is_srgb:
            lut = _srgb16_lut()
            return lambda src, dst: np.take(lut, src, out=dst)
        return lambda src, dst: np.multiply(src, np.float32(1 / 65535), out=dst)
    if is_srgb:
        return lambda src, dst: np.copyto(dst, srgb_to_linear(src), casting="same_kind")
    return lambda src, dst: np.copyto(dst, src)


def group_views(entries: Sequence[LightFileEntry], path_text: str) -> tuple[np.ndarray, list[list[int]]]:
    """Rows of a ``.lvp`` file as ``grid[view][light]`` of entry indices, views in order of first appearance."""
    tolerance = 1e-4  # directions are written with 4-9 digits; same view, different rounding
    views: list[np.ndarray] = []
    grid: list[list[int]] = []
    for index, entry in enumerate(entries):
        view = np.asarray(entry.view)
        for v, known in enumerate(views):
            if np.abs(known - view).max() <= tolerance:
                grid[v].append(index)
                break
        else:
            views.append(view)
            grid.append([index])
    first = grid[0]
    for v, rows in enumerate(grid[1:], start=1):
        if len(rows) != len(first):
            raise BtforgeInputError(
                f"{path_text}, line {entries[rows[0]].line}",
                f"expected {len(first)} lights for view {v} {tuple(round(c, 4) for c in views[v])} like view 0, "
                f"found {len(rows)}", "every view must be lit by the same lights, in the same order")
        for position, (a, b) in enumerate(zip(first, rows)):
            if np.abs(np.subtract(entries[a].light, entries[b].light)).max() > tolerance:
                raise BtforgeInputError(
                    f"{path_text}, line {entries[b].line}",
                    f"expected light {position} of view {v} to be {tuple(round(c, 4) for c in entries[a].light)} "
                    f"as on line {entries[a].line}, found {tuple(round(c, 4) for c in entries[b].light)}",
                    "every view must be lit by the same lights, in the same order")
    return np.asarray(views, dtype=np.float64), grid


class CaptureReader:
    """The images of a capture, decoded on demand into slots the caller provides.

    Opening reads the light file and decodes the first image, which fixes the size, the channels and the bit
    depth (every other image must match it).  :meth:`read_into` decodes any set of (view, light) images in
    parallel straight into an array, so a caller can hold the whole stack (:func:`load_stack`) or only a batch of
    images at a time (a fit that accumulates as it reads).  The attributes describe the stack: ``n_view``,
    ``n_light``, ``shape`` ``(H, W, C)``, ``dtype`` of the samples, ``encoding``, ``lights``, ``views``,
    ``channels`` and ``names`` as a :class:`~btforge.buffers.SampleStack` would hold them.
    """

    def __init__(self, light_file: str | os.PathLike, *, transfer: str = "auto"):
        if transfer not in TRANSFERS:
            raise BtforgeInputError("load_stack 'transfer'", f"expected one of {TRANSFERS}, found {transfer!r}")
        self.light_file, self.transfer, self.path_text = light_file, transfer, str(light_file)
        self.entries = read_capture_index(light_file, require_images=True)
        self._archive = zipfile.ZipFile(light_file) if is_btf_zip(light_file) else None  # UBO2003 download
        if self.entries[0].view is None:
            views, self.grid = np.array([[0.0, 0.0, 1.0]]), [list(range(len(self.entries)))]
        else:
            views, self.grid = group_views(self.entries, self.path_text)
        self.first_index = self.grid[0][0]
        self._first = self._decode(self.first_index)
        first = self._first
        self.shape = first.shape
        self.dtype = np.dtype(np.uint8 if first.dtype == np.uint8 and transfer != "linear" else np.float32)
        self._convert = _converter(first.dtype, transfer)
        # 8-bit JPEG kept as bytes: the decoder can write into the caller's slot (same pixels, checked shape).
        self._bytes_as_decoded = first.dtype == np.uint8 and self.dtype == np.uint8
        self.n_view, self.n_light = len(self.grid), len(self.grid[0])
        self.encoding = "srgb8" if self.dtype == np.uint8 else "linear"
        self.lights = np.asarray([self.entries[index].light for index in self.grid[0]], dtype=np.float32)
        self.views = views.astype(np.float32)
        self.channels = ("Y",) if first.shape[2] == 1 else ("R", "G", "B")
        self.names = tuple(self.entries[index].filename for index in self.grid[0])

    def _image(self, index: int):
        """The image file of entry ``index``: a path, or the member's bytes in a zip archive."""
        name = self.entries[index].filename
        if self._archive is not None:
            return io.BytesIO(self._archive.read(name))
        return image_path(self.light_file, name)

    def _decode(self, index: int) -> np.ndarray:
        entry = self.entries[index]
        where = f"{self.path_text}, line {entry.line}"
        try:
            array, _ = read_image(self._image(index), name=entry.filename if self._archive is not None else None)
        except BtforgeInputError as exc:
            # The light file line locates the image better than its full path; keep the name in the problem.
            raise BtforgeInputError(where, f"image {entry.filename!r}: {exc.problem}", exc.hint) from None
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            rows, cols, _ = np.nonzero(~np.isfinite(array))
            raise BtforgeInputError(
                where, f"expected finite radiance in {entry.filename!r}, found {rows.size} NaN/Inf values "
                f"(first at row {rows[0]}, column {cols[0]})", "repair or re-render the image")
        return array

    def _check(self, index: int, array: np.ndarray) -> None:
        entry, first, first_entry = self.entries[index], self._first, self.entries[self.first_index]
        where = f"{self.path_text}, line {entry.line}"
        like = f"like {first_entry.filename!r} on line {first_entry.line}"
        if array.shape[:2] != first.shape[:2]:
            raise BtforgeInputError(
                where, f"expected {first.shape[1]} x {first.shape[0]} pixels (width x height) {like}, found "
                f"{array.shape[1]} x {array.shape[0]} in {entry.filename!r}",
                "all images of a capture must have the same size; re-export or crop them consistently")
        if array.shape[2] != first.shape[2]:
            raise BtforgeInputError(
                where, f"expected {first.shape[2]} channel(s) {like}, found {array.shape[2]} in {entry.filename!r}",
                "save all images of a capture either in colour or in grey")
        if array.dtype != first.dtype:
            raise BtforgeInputError(
                where, f"expected {_bit_depth(first.dtype)} samples {like}, found {_bit_depth(array.dtype)} in "
                f"{entry.filename!r}", "export all images of a capture with the same bit depth")

    def read_into(self, slots: Sequence[tuple[int, int]], out: np.ndarray, *, threads: int = 2) -> None:
        """Decode the images of ``slots`` ((view, light) pairs) into ``out[i]`` (``[len(slots), H, W, C]`` of
        :attr:`dtype`), ``threads`` at once.  The error reported is always the one of the earliest line."""
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
            raise BtforgeInputError("load_stack 'threads'", f"expected a positive integer, found {threads!r}")
        failed = threading.Event()

        def load_one(i: int) -> None:
            if failed.is_set():  # another image already failed; do not spend time on the rest
                return
            view, light = slots[i]
            index = self.grid[view][light]
            if self._bytes_as_decoded and index != self.first_index and _jpeg_turbo_into(self._image(index), out[i]):
                return  # decoded in its slot: no image-sized buffer, no copy
            array = self._first if index == self.first_index else self._decode(index)
            self._check(index, array)
            self._convert(array, out[i])

        jobs = sorted(range(len(slots)), key=lambda i: self.entries[self.grid[slots[i][0]][slots[i][1]]].line)
        if threads == 1 or len(jobs) < 2:
            for i in jobs:
                load_one(i)
            return
        with concurrent.futures.ThreadPoolExecutor(max_workers=threads, thread_name_prefix="btforge-decode") as pool:
            futures = [pool.submit(load_one, i) for i in jobs]
            try:
                # In line order, so the error reported is always the one of the earliest line.
                for future in futures:
                    future.result()
            except BaseException:
                failed.set()
                for future in futures:
                    future.cancel()
                raise


def load_stack(light_file: str | os.PathLike, *, transfer: str = "auto", threads: int = 2) -> SampleStack:
    """Decode the images listed in a light file into one :class:`~btforge.buffers.SampleStack`.

    Parameters
    ----------
    light_file
        A ``.lp`` file (one view, ``(0, 0, 1)``), a ``.lvp`` file, whose rows are grouped by view direction
        into ``[V, L, ...]``, or a UBO-style BTF folder whose image names carry the angles.
    transfer
        ``'auto'``: 8-bit images are sRGB (kept as uint8, ``encoding='srgb8'``), 16-bit and float images are
        linear (float32).  ``'srgb'``: decode every image with the sRGB curve (8-bit stays ``srgb8``; 16-bit
        and float become linear float32).  ``'linear'``: take every value as linear radiance (float32).
    threads
        Images decoded at once.  Pillow and OpenEXR release the GIL while decoding, so threads scale.

    Returns
    -------
    SampleStack
        ``names`` are the file names (those of the first view for ``.lvp``), ``channels`` ``('R', 'G', 'B')``
        or ``('Y',)``.

    Raises
    ------
    BtforgeInputError
        Naming the light file line, for any problem of the light file, an unreadable image, an image whose size,
        channel count or bit depth differs from the first, or NaN/Inf pixels.
    """
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise BtforgeInputError("load_stack 'threads'", f"expected a positive integer, found {threads!r}")
    return _read_whole(CaptureReader(light_file, transfer=transfer), threads)


def _read_whole(reader: CaptureReader, threads: int) -> SampleStack:
    samples = np.empty((reader.n_view, reader.n_light) + reader.shape, dtype=reader.dtype)
    slots = [(v, l) for v in range(reader.n_view) for l in range(reader.n_light)]
    reader.read_into(slots, samples.reshape((-1,) + reader.shape), threads=threads)
    return SampleStack(samples=samples, lights=reader.lights, views=reader.views, channels=reader.channels,
                       encoding=reader.encoding, names=reader.names)


# A capture smaller than this is read into memory even where it could stream: writing it to a file and reading
# it back costs more than holding it (a 300 x 300, 38-light capture: 0.1 s of CPU for 10 MB).
STREAM_MIN_BYTES = 64 << 20


def load_stack_spilled(light_file: str | os.PathLike, *, transfer: str = "auto", threads: int = 2,
                       min_bytes: int | None = None) -> SampleStack:
    """:func:`load_stack` into a spilled file: a :class:`~btforge.store.SpilledSampleStack` whose samples stay
    in the operating system's file cache, to be read band by band of rows.  A capture of fewer than
    ``min_bytes`` (default :data:`STREAM_MIN_BYTES`) is read into memory instead, as :func:`load_stack` reads it.

    ``threads`` threads each decode one image at a time into their own buffer and write it to the file (plain
    writes: its pages are never mapped into the process), so the process holds ``threads`` images, never the
    capture, and decoding never waits for a batch to fill.  Same samples, lights and errors as
    :func:`load_stack` (the error reported is the one of the earliest line).
    """
    from btforge.fitspace import auto_grid_step
    from btforge.spill import spilled_empty, write_items
    from btforge.store import SpilledSampleStack
    reader = CaptureReader(light_file, transfer=transfer)
    nbytes = reader.n_view * reader.n_light * int(np.prod(reader.shape)) * reader.dtype.itemsize
    if nbytes < (STREAM_MIN_BYTES if min_bytes is None else min_bytes):
        return _read_whole(reader, threads)
    samples = spilled_empty((reader.n_view, reader.n_light) + reader.shape, reader.dtype)
    slots = [(v, l) for v in range(reader.n_view) for l in range(reader.n_light)]
    # the texel grid `auto` choices judge on, taken from each image while it is in memory (read from the file
    # afterwards, it would cost a read per grid row of every image)
    step = auto_grid_step(*reader.shape[:2])
    grid = np.empty((reader.n_view, reader.n_light) + samples[0, 0, ::step, ::step].shape, reader.dtype)
    own = threading.local()

    def decode(index: int) -> None:
        if not hasattr(own, "image"):
            own.image = np.empty((1,) + reader.shape, reader.dtype)
        reader.read_into([slots[index]], own.image, threads=1)
        grid[slots[index]] = own.image[0, ::step, ::step]
        write_items(samples, index, own.image)

    with concurrent.futures.ThreadPoolExecutor(max_workers=threads, thread_name_prefix="btforge-decode") as pool:
        futures = [pool.submit(decode, index) for index in range(len(slots))]
        try:
            for future in futures:  # in line order: the error reported is the earliest line's
                future.result()
        except BaseException:
            for future in futures:
                future.cancel()
            raise
    stack = SpilledSampleStack(samples=samples, lights=reader.lights, views=reader.views, channels=reader.channels,
                               encoding=reader.encoding, names=reader.names)
    stack.keep_texel_grid(step, grid)
    return stack


# ----------------------------------------------------------------------------------------------- writing


def _image_planes(array: Any, path_text: str, what: str) -> np.ndarray:
    """Validate an image to write: ``[H, W]`` or ``[H, W, C]`` with ``C`` 1 or 3, finite; returned as 3-D."""
    array = np.asarray(array)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[2] not in (1, 3) or 0 in array.shape:
        raise BtforgeInputError(path_text, f"expected {what} of shape (H, W, 3) or (H, W, 1), found {array.shape}")
    if array.dtype.kind == "f" and not np.isfinite(array).all():
        raise BtforgeInputError(path_text, f"expected finite values, found {int((~np.isfinite(array)).sum())} "
                                "NaN/Inf", "repair the image before writing it")
    return array


def write_exr(path: str | os.PathLike, rgb_float32: Any, *, half: bool = False) -> None:
    """Write linear radiance as an OpenEXR file (ZIP-compressed), atomically.

    Parameters
    ----------
    path
        Destination ``.exr`` file.
    rgb_float32
        ``[H, W, 3]`` (channels R, G, B) or ``[H, W]`` / ``[H, W, 1]`` (channel Y), finite.
    half
        Store 16-bit half floats (half the size, about 3 significant digits; values above 65504 are refused).
    """
    import OpenEXR

    path_text = str(path)
    array = _image_planes(rgb_float32, path_text, "an image")
    if array.dtype.kind not in "fiu":
        raise BtforgeInputError(path_text, f"expected float radiance, found {array.dtype}")
    array = array.astype(np.float32, copy=False)
    if half:
        if np.abs(array).max() > HALF_MAX:
            raise BtforgeInputError(path_text, f"expected values within the half range (|x| <= {HALF_MAX:g}), found "
                                    f"{float(np.abs(array).max()):g}", "write float32 (half=False) or rescale")
        array = array.astype(np.float16)
    names = ["Y"] if array.shape[2] == 1 else ["R", "G", "B"]
    channels = {name: np.ascontiguousarray(array[..., c]) for c, name in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_output_path(path) as temporary:
        OpenEXR.File(header, channels).write(str(temporary))


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def _encode_png16(array: np.ndarray) -> bytes:
    """A 16-bit grey or RGB PNG, which Pillow cannot write; tagged gamma 1.0 because the values are linear."""
    height, width, n_channel = array.shape
    rows = array.astype(">u2").reshape(height, width * n_channel).view(np.uint8)
    # Filter type 0 (none) on every row: simplest, and zlib still finds the redundancy in smooth images.
    scanlines = np.concatenate([np.zeros((height, 1), np.uint8), rows], axis=1)
    colour_type = 0 if n_channel == 1 else 2
    return (b"\x89PNG\r\n\x1a\n"
            + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 16, colour_type, 0, 0, 0))
            + _png_chunk(b"gAMA", struct.pack(">I", 100000))
            + _png_chunk(b"IDAT", zlib.compress(scanlines.tobytes(), 6))
            + _png_chunk(b"IEND", b""))


def _write_png_uint8(path: str | os.PathLike, encoded: np.ndarray) -> None:
    from PIL import Image

    image = Image.fromarray(encoded[..., 0] if encoded.shape[2] == 1 else encoded)
    with atomic_write(path, "wb") as handle:
        image.save(handle, format="PNG")


def write_png(path: str | os.PathLike, linear_float: Any, bits: int = 8) -> None:
    """Write linear radiance as a PNG, atomically.

    Parameters
    ----------
    path
        Destination ``.png`` file.
    linear_float
        ``[H, W, 3]`` or ``[H, W]`` / ``[H, W, 1]`` linear values, nominally in ``[0, 1]`` (clipped).
    bits
        8: sRGB-encoded (``linear_to_srgb``, rounded), what :func:`read_image` reads back as ``'srgb'``.
        16: linear values times 65535, what :func:`read_image` reads back as ``'linear'``.
    """
    path_text = str(path)
    if bits not in (8, 16):
        raise BtforgeInputError(path_text, f"expected bits 8 or 16, found {bits!r}")
    array = _image_planes(linear_float, path_text, "an image")
    if bits == 8:
        encoded = linear_to_srgb8(array)
        _write_png_uint8(path, encoded)
        return
    encoded = np.rint(np.clip(array.astype(np.float64), 0.0, 1.0) * 65535.0).astype(np.uint16)
    with atomic_write(path, "wb") as handle:
        handle.write(_encode_png16(encoded))


def write_stack(stack: SampleStack, directory: str | os.PathLike, *, fmt: str = "exr", half: bool = False,
                stem: str = "light", threads: int = 2) -> list[Path]:
    """Write a stack as one image per light plus a light file listing them in light order.

    Parameters
    ----------
    stack
        The samples; channels must be ``('R', 'G', 'B')`` or ``('Y',)``.
    directory
        Destination folder (created if needed).  Existing files of the same names are replaced.
    fmt
        ``'exr'``: linear float32 (or half) OpenEXR.  ``'png'``: 8-bit sRGB-encoded PNG (an ``srgb8`` stack is
        written as is, without a round trip through float).
    half
        Half-float EXR.
    stem
        File names are ``{stem}_{light:03d}.{ext}``, or ``{stem}_v{view:03d}_l{light:03d}.{ext}`` for more than
        one view.
    threads
        Images encoded at once.

    Returns
    -------
    list of Path
        The images in view-major, light order, then the light file (``lights.lp``, or ``lights.lvp`` for
        several views).  The light file is written last, so its presence means every image it lists is complete.
    """
    if fmt not in ("exr", "png"):
        raise BtforgeInputError("write_stack 'fmt'", f"expected 'exr' or 'png', found {fmt!r}")
    if half and fmt != "exr":
        raise BtforgeInputError("write_stack 'half'", "half floats only exist in EXR", "use fmt='exr' or half=False")
    if tuple(stack.channels) not in (("R", "G", "B"), ("Y",)):
        raise BtforgeInputError("write_stack 'stack'", f"expected channels ('R', 'G', 'B') or ('Y',), found "
                                f"{tuple(stack.channels)}", "image files hold grey or RGB; split other channels")
    if not stem or any(c in stem for c in "/\\") or stem != stem.strip():
        raise BtforgeInputError("write_stack 'stem'", f"expected a plain file-name prefix, found {stem!r}")
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise BtforgeInputError("write_stack 'threads'", f"expected a positive integer, found {threads!r}")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    multi_view = stack.n_view > 1

    jobs: list[tuple[int, int, Path]] = []
    for v in range(stack.n_view):
        for l in range(stack.n_light):
            name = f"{stem}_v{v:03d}_l{l:03d}" if multi_view else f"{stem}_{l:03d}"
            jobs.append((v, l, directory / f"{name}.{fmt}"))

    def write_one(job: tuple[int, int, Path]) -> None:
        v, l, target = job
        if fmt == "png" and stack.encoding == "srgb8":
            _write_png_uint8(target, stack.samples[v, l])
        elif fmt == "png":
            write_png(target, stack.samples[v, l])
        else:
            radiance = stack.samples[v, l]
            if stack.encoding == "srgb8":
                radiance = SRGB8_TO_LINEAR[radiance]
            write_exr(target, radiance, half=half)

    if threads == 1:
        for job in jobs:
            write_one(job)
    else:
        with concurrent.futures.ThreadPoolExecutor(max_workers=threads, thread_name_prefix="btforge-encode") as pool:
            for _ in pool.map(write_one, jobs):
                pass

    light_file = directory / ("lights.lvp" if multi_view else "lights.lp")
    filenames = [target.name for _, _, target in jobs]
    lights = np.asarray([stack.lights[l] for _, l, _ in jobs])
    views = np.asarray([stack.views[v] for v, _, _ in jobs]) if multi_view else None
    write_light_file(light_file, filenames, lights, views)
    return [target for _, _, target in jobs] + [light_file]
