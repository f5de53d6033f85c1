"""Chunked sample stores: a capture converted once into a zarr v3 store of compressed texel blocks.

A store is a folder (conventionally ``NAME.zarr``) holding one zarr v3 array ``samples`` of shape
``[V, L, H, W, C]`` (uint8 sRGB codes or float32 linear radiance, as a :class:`~btforge.buffers.SampleStack`
holds them) whose chunks are ``[V, L, block_h, block_w, C]``: every chunk holds all samples of one block of
texels, since every per-texel fit needs all of them.  Chunks are Zstandard-compressed with byte shuffling.  The
array's attributes carry the rest of the stack and the layout's version::

    {"btforge": {"format": "btforge.samples", "format_version": 1, "lights": [[x, y, z], ...],
                 "views": [...], "channels": ["R", "G", "B"], "encoding": "srgb8", "names": [...]}}

:func:`create_store` makes an empty store that a caller fills block by block (so nothing is held whole),
:func:`open_store` checks one and :func:`read_samples` reads any block of texels.  The node cache keys a store
by the digest of its contents (``framework/cache.py``), as it keys files.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from .buffers import SampleStack, unit_directions, upper_hemisphere
from .errors import BtforgeInputError
from .spill import finite_range, read_block

FORMAT = "btforge.samples"
FORMAT_VERSION = 1
ARRAY = "samples"
DEFAULT_BLOCK = (64, 64)


def is_store(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a zarr store folder (it has a ``zarr.json``)."""
    return (Path(path) / "zarr.json").is_file()


def create_store(path: str | os.PathLike, shape: Sequence[int], dtype, *, lights, views, channels: Sequence[str],
                 encoding: str, names: Sequence[str] = (), block: Sequence[int] = DEFAULT_BLOCK):
    """An empty store for a stack of ``shape`` ``[V, L, H, W, C]``; returns its zarr array to fill by blocks.

    An existing store at ``path`` is replaced (a folder that is not a store is refused).
    """
    import zarr
    from zarr.codecs import BloscCodec, BloscShuffle

    path = Path(path)
    if path.exists() and not is_store(path):
        raise BtforgeInputError(str(path), "exists and is not a zarr store", "give a new path, e.g. capture.zarr")
    if path.exists():
        shutil.rmtree(path)
    n_view, n_light, height, width, n_channel = (int(v) for v in shape)
    chunks = (n_view, n_light, max(1, min(height, int(block[0]))), max(1, min(width, int(block[1]))), n_channel)
    group = zarr.open_group(str(path), mode="w", zarr_format=3)
    array = group.create_array(ARRAY, shape=(n_view, n_light, height, width, n_channel), chunks=chunks,
                               dtype=np.dtype(dtype),
                               compressors=[BloscCodec(cname="zstd", clevel=3, shuffle=BloscShuffle.shuffle)])
    array.attrs["btforge"] = {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "lights": np.asarray(lights, np.float64).tolist(), "views": np.asarray(views, np.float64).tolist(),
        "channels": list(channels), "encoding": encoding, "names": list(names)}
    return array


def open_store(path: str | os.PathLike):
    """The checked ``samples`` array of a store and its stack attributes ``(array, meta)``."""
    import zarr

    path = Path(path)
    if not is_store(path):
        raise BtforgeInputError(str(path), "is not a zarr store (no zarr.json)", "make one with stackio.import")
    try:
        array = zarr.open_group(str(path), mode="r", zarr_format=3)[ARRAY]
    except (KeyError, ValueError, TypeError, OSError, json.JSONDecodeError) as exc:  # zarr: TypeError for bad metadata
        raise BtforgeInputError(str(path), f"has no readable '{ARRAY}' array ({exc})",
                                "make the store with stackio.import") from None
    meta = dict(array.attrs.get("btforge") or {})
    if meta.get("format") != FORMAT:
        raise BtforgeInputError(str(path), f"expected a store of format '{FORMAT}', found {meta.get('format')!r}",
                                "make the store with stackio.import")
    if meta.get("format_version") != FORMAT_VERSION:
        raise BtforgeInputError(str(path), f"is a sample store of format version {meta.get('format_version')!r}; "
                                f"this btforge reads version {FORMAT_VERSION}", "import the capture again with "
                                "this btforge's stackio.import, or upgrade btforge")
    if array.ndim != 5 or len(meta.get("lights", ())) != array.shape[1] or len(meta.get("views", ())) != array.shape[0]:
        raise BtforgeInputError(str(path), f"its samples {array.shape} do not match its {len(meta.get('lights', ()))} "
                                f"lights and {len(meta.get('views', ()))} views", "the store is damaged; import it again")
    return array, meta


def read_samples(array, rows: slice = slice(None), cols: slice = slice(None)) -> np.ndarray:
    """Samples ``[V, L, h, w, C]`` of a block of texels, decompressing only the chunks it touches."""
    return np.asarray(array[:, :, rows, cols, :])


def store_summary(path: str | os.PathLike) -> dict[str, Any]:
    """What ``btforge info`` shows for a store."""
    array, meta = open_store(path)
    size = sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file())
    raw = int(np.prod(array.shape)) * array.dtype.itemsize
    return {"kind": "btforge sample store (zarr v3)", "format_version": meta["format_version"],
            "views": array.shape[0], "lights": array.shape[1], "texels": list(array.shape[2:4]),
            "channels": meta["channels"], "encoding": meta["encoding"], "chunk": list(array.chunks),
            "size_bytes": size, "compression_ratio": round(raw / max(size, 1), 2)}


# ----------------------------------------------------------------------------------------------- lazy stacks

@dataclasses.dataclass(frozen=True, eq=False)
class StoredSampleStack(SampleStack):
    """A :class:`~btforge.buffers.SampleStack` whose samples stay in a chunked store and are read on demand.

    ``samples`` is the store's zarr array: slicing it (``linear(rows)``, ``row_bands``, ``image``, ``take``)
    decompresses only the chunks a band touches, so stages that work band by band stream the capture.  Its
    content key is the store's content digest, so a cache entry refers to the store instead of copying it; a
    store that changed since is refused when such an entry is read back.
    """

    type_name: ClassVar[str] = "StoredSampleStack"
    chunked: ClassVar[bool] = True

    store: str = ""
    digest: str = ""

    def __post_init__(self):
        _check_lazy_stack(self, f"StoredSampleStack {self.store}", "the store is damaged; import it again")

    def payload(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        return ({"store": self.store, "digest": self.digest, "channels": list(self.channels),
                 "encoding": self.encoding, "names": list(self.names), "shape": list(self.samples.shape)},
                {"lights": self.lights, "views": self.views})

    @classmethod
    def from_payload(cls, meta: dict[str, Any], arrays: Mapping[str, np.ndarray]) -> "StoredSampleStack":
        stack = open_stored_stack(meta["store"])
        if stack.digest != meta["digest"]:
            raise BtforgeInputError(meta["store"], "changed since this result was cached",
                                    "run again: the nodes reading the store re-run when its contents change")
        return stack

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.samples.shape)) * self.samples.dtype.itemsize

    def take(self, views, lights, rows: slice = slice(None)) -> np.ndarray:
        return np.asarray(self.samples.oindex[np.asarray(views, int), np.asarray(lights, int), rows])

    def in_memory(self) -> SampleStack:
        samples = np.empty(self.samples.shape, self.samples.dtype)
        step = self.samples.chunks[2]
        for r0 in range(0, samples.shape[2], step):
            samples[:, :, r0:r0 + step] = read_samples(self.samples, slice(r0, r0 + step))
        return SampleStack(samples, self.lights, self.views, self.channels, self.encoding, self.names)

    def remap(self, *args, **kwargs):
        return self.in_memory().remap(*args, **kwargs)

    def row_bands(self, budget_bytes: int = 128 << 20):
        """Bands of rows within ``budget_bytes`` of linear samples: whole chunk rows where one fits, else a
        divisor of the chunk height (each chunk is then decompressed once per band that crosses it)."""
        step = self.samples.chunks[2]
        row_bytes = self.n_view * self.n_light * self.width * self.n_channel * 4
        fit = max(1, budget_bytes // max(row_bytes, 1))
        rows = (fit // step) * step if fit >= step else max(d for d in range(1, step + 1) if step % d == 0 and d <= fit)
        for start in range(0, self.height, rows):
            yield slice(start, min(self.height, start + rows))

    def texel_blocks(self, budget_bytes: int = 128 << 20):
        """Blocks ``(rows, cols)`` of whole chunks whose linear samples fit in ``budget_bytes`` (at least one
        chunk): whole chunk rows where they fit, else one chunk row cut into runs of chunks.  Every chunk is
        decompressed once, where row bands narrower than a chunk decompress it once per band."""
        step_r, step_c = self.samples.chunks[2:4]
        texel_bytes = self.n_view * self.n_light * self.n_channel * 4
        if budget_bytes >= texel_bytes * step_r * self.width:
            for rows in self.row_bands(budget_bytes):
                yield rows, slice(None)
            return
        cols = step_c * max(1, budget_bytes // (texel_bytes * step_r * step_c))
        for r0 in range(0, self.height, step_r):
            for c0 in range(0, self.width, cols):
                yield slice(r0, min(self.height, r0 + step_r)), slice(c0, min(self.width, c0 + cols))


def _check_lazy_stack(stack: SampleStack, owner: str, hint: str) -> None:
    """The checks of a :class:`~btforge.buffers.SampleStack` for one whose samples are not in memory: shapes,
    types and directions, never a pass over the samples that would page them in."""
    shape = tuple(stack.samples.shape)
    want = {"srgb8": np.uint8, "linear": np.float32}.get(stack.encoding)
    if want is None or np.dtype(stack.samples.dtype) != want:
        raise BtforgeInputError(owner, f"expected uint8 samples for encoding 'srgb8' or float32 for 'linear', "
                                f"found {stack.samples.dtype} with {stack.encoding!r}", hint)
    lights = upper_hemisphere("lights", unit_directions("lights", stack.lights, owner=owner), owner)
    views = upper_hemisphere("views", unit_directions("views", stack.views, owner=owner), owner)
    if len(shape) != 5 or lights.shape[0] != shape[1] or views.shape[0] != shape[0] \
            or len(stack.channels) != shape[4] or (stack.names and len(stack.names) != shape[1]):
        raise BtforgeInputError(owner, f"samples {shape} do not match {lights.shape[0]} lights, {views.shape[0]} "
                                f"views and channels {tuple(stack.channels)}", hint)
    for name, value in (("lights", lights), ("views", views)):
        value.flags.writeable = False
        object.__setattr__(stack, name, value)
    object.__setattr__(stack, "channels", tuple(stack.channels))
    object.__setattr__(stack, "names", tuple(stack.names))


@dataclasses.dataclass(frozen=True, eq=False)
class SpilledSampleStack(SampleStack):
    """A :class:`~btforge.buffers.SampleStack` whose samples were decoded into a spilled file
    (``framework/spill.py``): they live in the operating system's file cache, not in this process, and a stage
    reading a band of rows pages in only that band (the runner hands the band's pages back afterwards).

    What ``stackio.read`` gives when every node reading the stack runs per texel: the capture is decoded once,
    in parallel, and fitted band by band, so the process never holds it whole.  It is an ordinary stack
    otherwise (its ``samples`` is a memory map of the whole capture), with the type name ``SampleStack``.
    """

    chunked: ClassVar[bool] = True

    def __post_init__(self):
        _check_lazy_stack(self, "SampleStack", "a bug in the reader: decode the capture again")
        if self.encoding == "linear" and not finite_range(self.samples):
            raise BtforgeInputError("SampleStack", "expected finite radiance, found NaN/Inf samples",
                                    "repair or mask the images before fitting")
        self.samples.flags.writeable = False

    def in_memory(self) -> SampleStack:
        return SampleStack(self.samples, self.lights, self.views, self.channels, self.encoding, self.names)

    def keep_texel_grid(self, step: int, grid: np.ndarray) -> None:
        """Remember :meth:`texel_grid` ``(step)``, gathered by the reader while each image was in memory."""
        object.__setattr__(self, "_grids", {**self.__dict__.get("_grids", {}), step: grid})

    def texel_grid(self, step: int) -> np.ndarray:
        known = self.__dict__.get("_grids", {}).get(step)
        if known is not None:
            return known.copy()
        # row by row from the file: a strided read of the mapping would make the whole capture resident
        return np.concatenate([read_block(self.samples, 2, slice(row, row + 1))[:, :, :, ::step]
                               for row in range(0, self.height, step)], axis=2)


def open_stored_stack(path: str | os.PathLike) -> StoredSampleStack:
    """The stack of a store, read lazily (its content digest computed once, remembered by the node cache)."""
    from .locations import default_cache_root
    from .cache import file_digest
    array, meta = open_store(path)
    digest = file_digest(Path(path).resolve(), default_cache_root() / "nodes" / "files")
    return StoredSampleStack(array, np.asarray(meta["lights"]), np.asarray(meta["views"]), tuple(meta["channels"]),
                             meta["encoding"], tuple(meta.get("names") or ()), store=str(Path(path).resolve()),
                             digest=digest)
