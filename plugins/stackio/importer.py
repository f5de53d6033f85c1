"""Converting a capture once into a chunked store (``stackio.import``), and reading a store back as a stack.

Every chunk of a store holds all samples of a block of texels, while a capture arrives one image at a time.
The import therefore decodes the images (in parallel, a batch at a time) into a temporary raw file beside the
store, then reads it back one band of block rows at a time - every image's rows of that band - and writes the
band's chunks.  Memory stays at one batch of images plus one band, whatever the capture's size.  A Bonn UBO2014
``.btf`` file (DFMF) already holds the BTF as factors any block of texels can be decoded from: it is decoded and
written one chunk at a time.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from btforge.buffers import SampleStack
from btforge.store import create_store, open_stored_stack

from .images import CaptureReader

BATCH_BYTES = 32 << 20
BAND_BYTES = 64 << 20


def import_capture(path: str | os.PathLike, store: str | os.PathLike, *, transfer: str = "auto",
                   block: tuple[int, int] = (32, 32), threads: int = 2):
    """Write the capture at ``path`` (a .lp/.lvp light file, a UBO folder or UBO2003 zip, a UBO2014 .btf) into a
    store at ``store``; return the store's zarr array."""
    from .lightfile import is_dfmf_path
    if is_dfmf_path(path):
        return import_dfmf(path, store, block=block)
    reader = CaptureReader(path, transfer=transfer)
    height, width, n_channel = reader.shape
    n_image = reader.n_view * reader.n_light
    image_bytes = height * width * n_channel * reader.dtype.itemsize
    array = create_store(store, (reader.n_view, reader.n_light, height, width, n_channel), reader.dtype,
                         lights=reader.lights, views=reader.views, channels=reader.channels,
                         encoding=reader.encoding, names=reader.names, block=block)
    slots = [(v, l) for v in range(reader.n_view) for l in range(reader.n_light)]
    fd, raw_name = tempfile.mkstemp(prefix=".import-", suffix=".raw", dir=Path(store).parent)
    try:
        with os.fdopen(fd, "w+b") as raw:
            per_batch = max(1, BATCH_BYTES // image_bytes)
            batch = np.empty((min(per_batch, n_image), height, width, n_channel), reader.dtype)
            for start in range(0, n_image, per_batch):
                part = batch[:min(per_batch, n_image - start)]
                reader.read_into(slots[start:start + len(part)], part, threads=threads)
                raw.write(memoryview(part).cast("B"))
            del batch, part
            row_bytes = width * n_channel * reader.dtype.itemsize
            band_rows = array.chunks[2] * max(1, BAND_BYTES // max(1, n_image * row_bytes * array.chunks[2]))
            for r0 in range(0, height, band_rows):
                rows = min(band_rows, height - r0)
                band = np.empty((n_image, rows, width, n_channel), reader.dtype)
                for image in range(n_image):
                    raw.seek(image * image_bytes + r0 * row_bytes)
                    raw.readinto(memoryview(band[image]).cast("B"))
                array[:, :, r0:r0 + rows] = band.reshape(reader.n_view, reader.n_light, rows, width, n_channel)
    finally:
        os.unlink(raw_name)
    return array


def import_dfmf(path: str | os.PathLike, store: str | os.PathLike, *, block: tuple[int, int] = (32, 32)):
    """Decode a UBO2014 ``.btf`` file (DFMF) into a store of linear float32 radiance, one chunk at a time."""
    from .ubo2014 import read_dfmf
    btf = read_dfmf(path)
    array = create_store(store, (btf.n_view, btf.n_light, btf.height, btf.width, len(btf.channels)), np.float32,
                         lights=btf.lights, views=btf.views, channels=btf.channels, encoding="linear", block=block)
    step_r, step_c = array.chunks[2], array.chunks[3]
    for r0 in range(0, btf.height, step_r):
        for c0 in range(0, btf.width, step_c):
            rows, cols = slice(r0, r0 + step_r), slice(c0, c0 + step_c)
            array[:, :, rows, cols] = btf.decode(rows, cols)
    return array


def load_dfmf_stack(path: str | os.PathLike) -> SampleStack:
    """A UBO2014 ``.btf`` file (DFMF) decoded whole into memory (``stackio.import`` streams it into a store)."""
    from .ubo2014 import read_dfmf
    btf = read_dfmf(path)
    return SampleStack(btf.decode(), btf.lights, btf.views, btf.channels, "linear")


def load_store_stack(path: str | os.PathLike) -> SampleStack:
    """The stack a store holds, read into memory one band of chunk rows at a time."""
    return open_stored_stack(path).in_memory()


__all__ = ["import_capture", "import_dfmf", "load_dfmf_stack", "load_store_stack"]
