"""Typed, immutable, validated buffers: the only things that cross a stage boundary.

Every buffer is a frozen dataclass whose ``__post_init__`` validates shapes, dtypes and ranges and freezes its
arrays (``writeable=False``).  A buffer has a content key (BLAKE2 over its type, metadata and array bytes) that
the executor uses for caching, and it serialises itself generically: array fields go into an ``.npz`` file,
everything else into JSON metadata.

Adding a type is a local change: subclass :class:`Buffer` (or :class:`ReflectanceModel`, :class:`PerTexel`),
give it a ``type_name``, validate in ``__post_init__``, and return the class from the plugin's
``btforge_buffer_types`` hook.  Port declarations name types by ``type_name``; a port accepts any subclass.
"""
from __future__ import annotations

import abc
import contextlib
import contextvars
import dataclasses
import hashlib
import io
import json
import zipfile
from typing import Any, ClassVar, Iterator, Mapping, Sequence

import numpy as np

from .errors import BtforgeInputError
from .spill import finite_range, pages, write_npy

# ----------------------------------------------------------------------------------------------- validation


def _shape_text(shape: Sequence[Any]) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ")"


_VALUES_CHECKED = contextvars.ContextVar("btforge_values_checked", default=False)


@contextlib.contextmanager
def values_already_checked():
    """Within it, buffers are built without the checks of their values (:func:`check_array`'s ``finite``): for
    arrays joined from parts that were each checked as a buffer of the same type (the bands of a streamed
    fit), whose second check would read every value again.  Shapes and types are still checked."""
    token = _VALUES_CHECKED.set(True)
    try:
        yield
    finally:
        _VALUES_CHECKED.reset(token)


def check_array(
    name: str,
    value: Any,
    shape: Sequence[str | int],
    dtype: Any | Sequence[Any],
    *,
    finite: bool = False,
    owner: str = "",
) -> np.ndarray:
    """Check that ``value`` is an ndarray of ``shape`` (ints fixed, strings free) and one of ``dtype``.

    The message reads like ``'radiance' must be (V, L, H, W, C) float32, got (H, W, 9) float64``.
    """
    dtypes = tuple(np.dtype(d) for d in (dtype if isinstance(dtype, (list, tuple)) else (dtype,)))
    want = f"{_shape_text(shape)} {' or '.join(str(d) for d in dtypes)}"
    what = owner or "array"
    if not isinstance(value, np.ndarray):
        raise BtforgeInputError(what, f"'{name}' must be {want}, got {type(value).__name__}",
                                "pass a numpy array")
    got = f"{_shape_text(value.shape)} {value.dtype}"
    ok = value.ndim == len(shape) and value.dtype in dtypes
    bound: dict[str, int] = {}
    if ok:
        for want_dim, have in zip(shape, value.shape):
            if isinstance(want_dim, int) and want_dim != have:
                ok = False
            elif isinstance(want_dim, str):
                if bound.setdefault(want_dim, have) != have:
                    ok = False
    if not ok:
        raise BtforgeInputError(what, f"'{name}' must be {want}, got {got}")
    # min and max see every NaN (they propagate it) and every infinity, without a mask the size of the array
    if finite and value.dtype.kind == "f" and value.size and not _VALUES_CHECKED.get() and not finite_range(value):
        bad = int((~np.isfinite(value)).sum())
        raise BtforgeInputError(what, f"'{name}' must be finite, found {bad} NaN/Inf values",
                                "mask or repair the bad samples before building the buffer")
    return value


def frozen(array: np.ndarray) -> np.ndarray:
    """``array`` as a C-contiguous array nobody can write, copied only when that cannot be had otherwise.

    An array that owns its memory is frozen in place (no copy; the caller's reference turns read-only too), and
    so is the owner of a view that spans all of it (a reshape, ``a[None]``), so a large stack or model is never
    held twice.  A view of part of an array is copied unless every array it looks into is read-only already: the
    rest of its base could still be written through another reference.
    """
    out = np.ascontiguousarray(array)
    if out is array and _written_elsewhere(array):
        chain = _view_chain(array)
        if chain and chain[-1].base is None and chain[-1].nbytes == array.nbytes \
                and chain[-1].ctypes.data == array.ctypes.data:
            for view in chain:
                view.flags.writeable = False
        else:
            out = array.copy()
    out.flags.writeable = False
    return out


def settled(value: Any) -> Any:
    """A field value as a buffer keeps it: arrays read-only (:func:`frozen`), lists and tuples as tuples, mappings
    with their values settled, anything else as given."""
    if isinstance(value, np.ndarray):
        return frozen(value)
    if isinstance(value, (list, tuple)):
        return tuple(value)
    if isinstance(value, Mapping):
        return {key: settled(item) for key, item in value.items()}
    return value


def freeze_fields(buffer: "Buffer", *names: str, **values: Any) -> None:
    """Store a frozen buffer's fields in their kept form (see :func:`settled`), from ``__post_init__``: the fields
    ``names`` as they are, and ``values`` (checked or converted copies) in place of theirs.  Dataclasses frozen
    with ``frozen=True`` refuse plain assignment, so this is the one place that sets fields after validation."""
    for name in names:
        object.__setattr__(buffer, name, settled(getattr(buffer, name)))
    for name, value in values.items():
        object.__setattr__(buffer, name, settled(value))


def _view_chain(array: np.ndarray) -> list[np.ndarray]:
    """The arrays ``array`` looks into, nearest first (empty for an array that owns its memory)."""
    chain, base = [], array.base
    while isinstance(base, np.ndarray):
        chain.append(base)
        base = base.base
    return chain


def _written_elsewhere(array: np.ndarray) -> bool:
    base = array.base
    while isinstance(base, np.ndarray):
        if base.flags.writeable:
            return True
        base = base.base
    if base is None or isinstance(base, bytes):
        return False
    try:
        return not memoryview(base).readonly
    except TypeError:  # an exporter we cannot inspect: assume the worst
        return True


def unit_directions(name: str, dirs: Any, owner: str = "") -> np.ndarray:
    """Validate an ``(N, 3)`` array of directions and return them normalised as float32."""
    arr = np.asarray(dirs, dtype=np.float64)
    check_array(name, arr, ("N", 3), np.float64, finite=True, owner=owner)
    norms = np.linalg.norm(arr, axis=1)
    if arr.shape[0] and norms.min() < 1e-9:
        i = int(np.argmin(norms))
        raise BtforgeInputError(f"{owner} '{name}'".strip(), f"direction {i} is zero", "give a non-zero vector")
    unit = (arr / norms[:, None]).astype(np.float32)
    # Keep float32 rows that are already unit as they are, so normalising is idempotent: a stack rebuilt from
    # another stack's lights (a store read into memory, a dask band) sees bit-identical lights.
    if np.asarray(dirs).dtype == np.float32:
        already = np.abs(norms - 1.0) <= 4 * np.finfo(np.float32).eps
        unit[already] = np.asarray(dirs)[already]
    return unit


def upper_hemisphere(name: str, dirs: np.ndarray, owner: str = "SampleStack") -> np.ndarray:
    """Refuse directions below the surface (z < 0): a measured sample cannot be lit or seen from below."""
    below = np.flatnonzero(dirs[:, 2] < -1e-6)
    if below.size:
        i = int(below[0])
        raise BtforgeInputError(owner, f"'{name}' must lie on the upper hemisphere (z >= 0), found {below.size} below it, "
                                f"first row {i}: {dirs[i].round(4).tolist()}",
                                "directions point from the surface toward the light or camera, with z up")
    return dirs


# ----------------------------------------------------------------------------------------------- base types


@dataclasses.dataclass(frozen=True, eq=False)
class Buffer:
    """Base of all buffers.  Subclasses are frozen dataclasses that validate in ``__post_init__``."""

    type_name: ClassVar[str] = "Buffer"

    # -- content addressing ------------------------------------------------------------------------------
    def payload(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """Split the fields into JSON metadata and arrays; override when fields are not plain."""
        meta: dict[str, Any] = {}
        arrays: dict[str, np.ndarray] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                arrays[f.name] = value
            else:
                meta[f.name] = list(value) if isinstance(value, tuple) else value
        return meta, arrays

    @classmethod
    def from_payload(cls, meta: dict[str, Any], arrays: Mapping[str, np.ndarray]) -> "Buffer":
        kwargs = dict(meta)
        for f in dataclasses.fields(cls):
            if f.name in kwargs and isinstance(kwargs[f.name], list):
                kwargs[f.name] = tuple(kwargs[f.name])
        kwargs.update(arrays)
        return cls(**kwargs)

    @property
    def content_key(self) -> str:
        cached = self.__dict__.get("_content_key")
        if cached is None:
            h = hashlib.blake2b(digest_size=20)
            meta, arrays = self.payload()
            h.update(self.type_name.encode())
            h.update(json.dumps(meta, sort_keys=True, default=str).encode())
            for name in sorted(arrays):
                a = np.ascontiguousarray(arrays[name])
                h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
                for part in pages(a) if a.size else ():  # a spilled array is hashed without becoming resident
                    h.update(part.reshape(-1).view(np.uint8))
            cached = h.hexdigest()
            object.__setattr__(self, "_content_key", cached)
        return cached

    # -- serialisation (cache entries, `btforge info`) ---------------------------------------------------
    def to_bytes(self) -> bytes:
        bio = io.BytesIO()
        self.write_npz(bio)
        return bio.getvalue()

    def write_npz(self, handle) -> None:
        """Write the buffer as ``.npz`` to a binary file object (which need not be seekable)."""
        meta, arrays = self.payload()
        header = json.dumps({"type": self.type_name, "meta": meta}, default=str)
        # what np.savez writes, with each array written page by page (a spilled one never becomes resident)
        with zipfile.ZipFile(handle, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
            for name, array in {"__header__": np.frombuffer(header.encode(), dtype=np.uint8), **arrays}.items():
                with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                    write_npy(member, np.asanyarray(array))

    @staticmethod
    def from_file(path, types: Mapping[str, type["Buffer"]]) -> "Buffer":
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(bytes(z["__header__"]).decode())
            arrays = {k: z[k] for k in z.files if k != "__header__"}
        cls = types.get(header["type"])
        if cls is None:
            raise BtforgeInputError(str(path), f"holds a buffer of unknown type '{header['type']}'",
                                    "install the plugin that defines it")
        return cls.from_payload(header["meta"], arrays)

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in self.payload()[1].values()))

    # -- capabilities: a class declares one by defining the method; the base says clearly that it has none ----
    def appearance_features(self) -> np.ndarray:
        """``(H, W, D)`` float32 vectors whose Euclidean distances approximate L2 distances between the texels'
        reflectance functions: what synthesizers compare.  Per-texel buffers have them."""
        raise BtforgeInputError(f"buffer type '{self.type_name}'", "has no appearance features: it is not a "
                                "per-texel buffer", "synthesize from a per-texel buffer (a stack or a fitted model), "
                                "or define appearance_features on the class")


def capability(buffer: Buffer, name: str, what: str, hint: str):
    """The bound method ``name`` of an optional capability that only some plugins' buffer types define (a tile
    set's ``seam_scores(exemplar, coords) -> dict``): stages call it through here without importing the plugin
    that defines the type, and a buffer without it is a clear error naming its type."""
    if not callable(getattr(type(buffer), name, None)):
        raise BtforgeInputError(f"buffer type '{buffer.type_name}'", f"has no {what} (no method {name})", hint)
    return getattr(buffer, name)


# ----------------------------------------------------------------------------------------------- samples

SRGB_LUT_SIZE = 256


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """The sRGB electro-optical transfer function, on values in [0, 1]."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * np.power(x, 1 / 2.4) - 0.055)


_ENCODE_STEPS = 1 << 16
_LINEAR_TO_SRGB8 = np.round(linear_to_srgb(np.arange(_ENCODE_STEPS) / (_ENCODE_STEPS - 1)) * 255).astype(np.uint8)


def linear_to_srgb8(x: np.ndarray) -> np.ndarray:
    """Linear radiance -> 8-bit sRGB through a 65536-entry table: ~20x faster than the power law; a value
    differs from exact rounding by one level only near a rounding boundary (about 0.4% of random values)."""
    index = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0) * np.float32(_ENCODE_STEPS - 1)
    return _LINEAR_TO_SRGB8[(index + np.float32(0.5)).astype(np.int32)]


SRGB8_TO_LINEAR = srgb_to_linear(np.arange(256) / 255.0).astype(np.float32)
SRGB8_TO_LINEAR.flags.writeable = False


@dataclasses.dataclass(frozen=True, eq=False)
class PerTexel(Buffer):
    """A buffer with one record per texel on an ``H x W`` grid (stacks, models, height fields).

    ``texel_fields`` names the arrays that hold per-texel data, with the texel grid at axes
    ``texel_axis, texel_axis + 1``.  :meth:`remap` gathers those arrays through a coordinate map, so a synthesis
    result can be replayed on any per-texel buffer without knowing its type.  ``blendable`` says whether two
    texels' records can be blended into the record of their weighted mean function (true for linear
    representations such as radiance, linear PTM and SH coefficients; false for non-linear ones such as
    Lafortune lobes); :meth:`blend_records` does it.  ``mixes_records`` is wider: it also holds where records are
    linear in display values decoded after evaluation (an sRGB PTM), whose mix cross-fades what a screen shows.
    """

    type_name: ClassVar[str] = "PerTexel"
    texel_fields: ClassVar[tuple[str, ...]] = ()
    texel_axis: ClassVar[int] = 0
    blendable: ClassVar[bool] = True

    @property
    def height(self) -> int:
        return getattr(self, self.texel_fields[0]).shape[self.texel_axis]

    @property
    def width(self) -> int:
        return getattr(self, self.texel_fields[0]).shape[self.texel_axis + 1]

    def remap(self, rows: np.ndarray, cols: np.ndarray, blend_rows: np.ndarray | None = None,
              blend_cols: np.ndarray | None = None, blend_weight: np.ndarray | None = None) -> "PerTexel":
        """A buffer of the same type whose texel (i, j) is this buffer's texel (rows[i, j], cols[i, j]).

        With a blend record, the result is ``(1 - w) * texel(rows, cols) + w * texel(blend_rows, blend_cols)``
        (mixed by :meth:`blend_records`) where the records mix, the same in :meth:`mixing_form` (another buffer of
        the same type) where that exists, and the texel with the larger weight otherwise.
        """
        ax = self.texel_axis
        use_blend = blend_weight is not None and bool(np.any(blend_weight > 0))
        if use_blend and not self.mixes_records:
            form = self.mixing_form()
            if form is not None:
                return form.remap(rows, cols, blend_rows, blend_cols, blend_weight)
            second = blend_weight > 0.5
            rows, cols = np.where(second, blend_rows, rows), np.where(second, blend_cols, cols)
            use_blend = False
        changes = {}
        for name in self.texel_fields:
            array = getattr(self, name)
            index = (slice(None),) * ax
            gathered = array[index + (rows, cols)]
            if use_blend:
                w = blend_weight.reshape(blend_weight.shape + (1,) * (array.ndim - ax - 2)).astype(np.float32)
                gathered = self.blend_records(name, gathered, array[index + (blend_rows, blend_cols)], w)
            changes[name] = gathered
        return dataclasses.replace(self, **changes)

    @property
    def mixes_records(self) -> bool:
        """Whether :meth:`blend_records` mixes two records into the record of a function between theirs: as
        radiance where the buffer is ``blendable``; as display values where the records are linear in values that
        evaluation decodes afterwards (sRGB PTM, SH and HSH coefficients), a cross-fade of what a screen shows, as
        a viewer's texture filtering mixes them (override to say so)."""
        return self.blendable

    def mixing_form(self) -> "PerTexel | None":
        """The same functions in a buffer whose records mix (this buffer where it ``mixes_records``), or None where
        no such form exists.  :meth:`remap` blends through it, so a blend layer replays exactly where it exists
        (override where a record that does not mix has an equivalent that does, as an lrgb PTM has its rgb form)."""
        return self if self.mixes_records else None

    def appearance_features(self) -> np.ndarray:
        """The texel fields concatenated per texel (override where distances between the raw records are not
        distances between reflectance functions)."""
        if not self.texel_fields:
            raise BtforgeInputError(f"buffer type '{self.type_name}'", "declares no texel_fields, so it has no "
                                    "appearance features", "list the per-texel arrays in texel_fields or define "
                                    "appearance_features on the class")
        arrays = [np.asarray(getattr(self, f), np.float32) for f in self.texel_fields]
        return np.concatenate([a.reshape(self.height, self.width, -1) for a in arrays], axis=2)

    def blend_records(self, name: str, first: np.ndarray, second: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """``(1 - weight) * first + weight * second`` for records of field ``name``, in that field's dtype.

        Override where the stored values are not linear in what they represent (as an 8-bit sRGB stack does).
        """
        if not self.mixes_records:
            raise BtforgeInputError(f"buffer type '{self.type_name}'", "does not mix its records: the mean of two "
                                    "of its records is not the record of a function between theirs",
                                    "pick the heavier texel instead (as remap does), or blend its mixing_form()")
        mixed = (1 - weight) * first + weight * second
        dtype = getattr(self, name).dtype
        # Integer records (quantized coefficients) round to the nearest code instead of truncating.
        return (np.rint(mixed) if dtype.kind in "iu" else mixed).astype(dtype)



def central_crop(buffer: PerTexel, size: int) -> PerTexel:
    """The central ``size`` x ``size`` texels of any per-texel buffer, of the same type (all of a side shorter
    than ``size``; ``size`` 0: the whole buffer)."""
    if not size or (buffer.height <= size and buffer.width <= size):
        return buffer
    h, w = min(size, buffer.height), min(size, buffer.width)
    r0, c0 = (buffer.height - h) // 2, (buffer.width - w) // 2
    rows, cols = np.meshgrid(np.arange(r0, r0 + h), np.arange(c0, c0 + w), indexing="ij")
    return buffer.remap(rows, cols)

@dataclasses.dataclass(frozen=True, eq=False)
class SampleStack(PerTexel):
    """Measured radiance of a surface under many lights (and views).

    ``samples`` is ``[n_view, n_light, H, W, C]``: either linear float32 radiance, or - to keep a large 8-bit
    capture at a quarter of the memory - the camera's sRGB-encoded uint8 values (``encoding='srgb8'``), decoded
    to linear on access by :meth:`linear`.  ``lights`` are unit vectors toward the light in the surface frame
    (z up), ``[n_light, 3]``; ``views`` are unit vectors toward the camera, ``[n_view, 3]``.  A top-view RTI
    capture has one view, ``(0, 0, 1)``.
    """

    type_name: ClassVar[str] = "SampleStack"
    texel_fields: ClassVar[tuple[str, ...]] = ("samples",)
    texel_axis: ClassVar[int] = 2
    # True for a stack read lazily from a chunked store (btforge.store.StoredSampleStack): stages then read it by
    # row bands (linear, row_bands, take) instead of holding ``samples`` whole.
    chunked: ClassVar[bool] = False

    samples: np.ndarray
    lights: np.ndarray
    views: np.ndarray
    channels: tuple[str, ...] = ("R", "G", "B")
    encoding: str = "linear"
    names: tuple[str, ...] = ()

    def __post_init__(self):
        if self.encoding not in ("linear", "srgb8"):
            raise BtforgeInputError("SampleStack 'encoding'", f"must be 'linear' or 'srgb8', got {self.encoding!r}")
        dtype = np.float32 if self.encoding == "linear" else np.uint8
        samples = self.samples
        if isinstance(samples, np.ndarray) and samples.ndim == 4:
            samples = samples[None]
        check_array("samples", samples, ("V", "L", "H", "W", "C"), dtype, owner="SampleStack")
        if self.encoding == "linear" and samples.size and not (np.isfinite(samples.min()) and np.isfinite(samples.max())):
            v, l, y, x, c = np.argwhere(~np.isfinite(samples))[0]
            where = f"light {l}" + (f" ({self.names[l]})" if l < len(self.names) else "")
            raise BtforgeInputError(
                f"SampleStack, {where}", f"expected finite radiance, found NaN/Inf at view {v}, pixel (row {y}, column {x})",
                "repair or mask the image before fitting")
        lights = upper_hemisphere("lights", unit_directions("lights", self.lights, owner="SampleStack"))
        views = upper_hemisphere("views", unit_directions("views", self.views, owner="SampleStack"))
        if lights.shape[0] != samples.shape[1]:
            raise BtforgeInputError("SampleStack 'lights'", f"must have one row per light ({samples.shape[1]}), got {lights.shape[0]}")
        if views.shape[0] != samples.shape[0]:
            raise BtforgeInputError("SampleStack 'views'", f"must have one row per view ({samples.shape[0]}), got {views.shape[0]}")
        if len(self.channels) != samples.shape[4]:
            raise BtforgeInputError("SampleStack 'channels'", f"must name {samples.shape[4]} channels, got {self.channels!r}")
        if self.names and len(self.names) != lights.shape[0]:
            raise BtforgeInputError("SampleStack 'names'", f"must have one name per light ({lights.shape[0]}), got {len(self.names)}")
        freeze_fields(self, "channels", "names", samples=samples, lights=lights, views=views)

    @property
    def n_view(self) -> int:
        return self.samples.shape[0]

    @property
    def n_light(self) -> int:
        return self.samples.shape[1]

    @property
    def n_channel(self) -> int:
        return self.samples.shape[4]

    def linear(self, rows: slice = slice(None)) -> np.ndarray:
        """Linear float32 radiance ``[V, L, h, W, C]`` for a band of rows (all rows by default)."""
        band = self.samples[:, :, rows]
        if self.encoding == "linear":
            return band
        return SRGB8_TO_LINEAR[band]

    def take(self, views, lights, rows: slice = slice(None)) -> np.ndarray:
        """The stored samples ``[v, l, h, W, C]`` of the given view and light indices (and rows), a new array."""
        return self.samples[:, :, rows][np.ix_(np.asarray(views, int), np.asarray(lights, int))]

    def in_memory(self) -> "SampleStack":
        """This stack with its samples in one array (itself, unless it is read from a store)."""
        return self

    def image(self, view: int, light: int) -> np.ndarray:
        """Linear float32 radiance ``[H, W, C]`` of one view and light."""
        frame = self.samples[view, light]
        return frame if self.encoding == "linear" else SRGB8_TO_LINEAR[frame]

    def blend_records(self, name: str, first: np.ndarray, second: np.ndarray, weight: np.ndarray) -> np.ndarray:
        if self.encoding == "linear":
            return super().blend_records(name, first, second, weight)
        # Light adds up in linear radiance: the mean of two sRGB codes is darker than the code of the mean.
        mixed = (1 - weight) * SRGB8_TO_LINEAR[first] + weight * SRGB8_TO_LINEAR[second]
        return linear_to_srgb8(mixed)

    def appearance_features(self) -> np.ndarray:
        """Linear radiance under every light and view, per texel."""
        return np.moveaxis(self.linear(), (2, 3), (0, 1)).reshape(self.height, self.width, -1)

    def texel_grid(self, step: int) -> np.ndarray:
        """The stored samples ``[V, L, h, w, C]`` of every ``step``-th row and column: texels spread over the whole
        stack, on which choices about all of them are judged (``space: auto``)."""
        return np.ascontiguousarray(self.samples[:, :, ::step, ::step])

    def row_bands(self, budget_bytes: int = 128 << 20) -> Iterator[slice]:
        """Bands of rows whose linear float32 samples fit in ``budget_bytes``: the unit of streamed work."""
        row_bytes = self.n_view * self.n_light * self.width * self.n_channel * 4
        step = max(1, min(self.height, budget_bytes // max(row_bytes, 1)))
        for start in range(0, self.height, step):
            yield slice(start, min(self.height, start + step))

    def texel_blocks(self, budget_bytes: int = 128 << 20) -> Iterator[tuple[slice, slice]]:
        """Blocks ``(rows, cols)`` of texels whose linear float32 samples fit in ``budget_bytes``, for stages whose
        texels are independent: whole-width :meth:`row_bands` here; a store's blocks follow its chunks."""
        for rows in self.row_bands(budget_bytes):
            yield rows, slice(None)


# ----------------------------------------------------------------------------------------------- models


@dataclasses.dataclass(frozen=True, eq=False)
class ReflectanceModel(PerTexel, abc.ABC):
    """A fitted per-texel reflectance function that can be evaluated at any light (and view).

    Every representation implements :meth:`evaluate`, so a renderer relights any of them without knowing which
    it is.  ``view_dependent`` is False for models of light only, which lets a renderer skip per-pixel view
    directions.
    """

    type_name: ClassVar[str] = "ReflectanceModel"
    view_dependent: ClassVar[bool] = False
    evaluates_texels: ClassVar[bool] = False  # true for a class that defines evaluate_texels (or says so itself)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if "evaluates_texels" not in cls.__dict__:
            cls.evaluates_texels = cls.evaluate_texels is not ReflectanceModel.evaluate_texels

    @property
    @abc.abstractmethod
    def channels(self) -> tuple[str, ...]:
        """Names of the colour channels the model evaluates to."""

    @abc.abstractmethod
    def evaluate(self, lights: np.ndarray, views: np.ndarray | None = None) -> np.ndarray:
        """Linear radiance ``[V, L, H, W, C]`` float32 at unit ``lights [L, 3]`` (and ``views [V, 3]``)."""

    def evaluate_texels(self, rows: np.ndarray, cols: np.ndarray, lights_local: np.ndarray,
                        views_local: np.ndarray | None = None) -> np.ndarray:
        """Linear radiance ``[N, C]`` of texels ``(rows[i], cols[i])`` at one light (and view) each, ``[N, 3]`` in
        the surface frame: what a renderer needs at every shaded point.  ``evaluates_texels`` tells whether a
        class has it."""
        raise BtforgeInputError(f"model type '{self.type_name}'", "cannot be evaluated per texel: the class defines "
                                "no evaluate_texels(rows, cols, lights_local, views_local)",
                                "add evaluate_texels to the model class")

    def evaluation_form(self) -> "ReflectanceModel":
        """The same model in the form that is fastest to evaluate many times (a renderer converts once)."""
        return self

    def appearance_features(self) -> np.ndarray:
        """The texel's radiance at :data:`APPEARANCE_PROBE_LIGHTS` lights spread over the hemisphere."""
        relit = self.evaluate(appearance_probe_lights())
        return np.moveaxis(relit, (2, 3), (0, 1)).reshape(self.height, self.width, -1)


APPEARANCE_PROBE_LIGHTS = 25  # lights at which models without features of their own are sampled


def appearance_probe_lights(n: int = APPEARANCE_PROBE_LIGHTS) -> np.ndarray:
    """``n`` unit directions over the upper hemisphere: a Fibonacci spiral above 10 degrees, float32."""
    from .numerics import fibonacci_directions
    return unit_directions("probe lights", fibonacci_directions(n, float(np.sin(np.radians(10))), rising=True))


@dataclasses.dataclass(frozen=True, eq=False)
class Scores(Buffer):
    """Named scalar measurements (PSNR, error, timing) produced by a comparing stage."""

    type_name: ClassVar[str] = "Scores"

    values: dict

    def __post_init__(self):
        if not isinstance(self.values, dict) or not all(isinstance(k, str) for k in self.values):
            raise BtforgeInputError("Scores 'values'", f"must be a dict with string keys, got {type(self.values).__name__}")
        clean = {}
        for key, value in self.values.items():
            if not isinstance(value, (int, float, str, bool)) and value is not None:
                raise BtforgeInputError(f"Scores '{key}'", f"must be a number or string, got {type(value).__name__}")
            clean[key] = float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else value
        object.__setattr__(self, "values", clean)


@dataclasses.dataclass(frozen=True, eq=False)
class CoordMap(Buffer):
    """For each output texel, the exemplar texel it copies: the result of every synthesizer.

    ``coords`` is ``[H, W, 2]`` int32 (row, column) into an exemplar of ``source_size``.  Where a synthesizer
    blends (overlapping blocks), ``blend_coords`` names the second texel and ``blend_weight`` its weight in
    [0, 1]; both are empty (``[0, 0, 2]``, ``[0, 0]``) when nothing is blended.  A map is a few bytes per texel,
    so a large synthesized texture costs a map rather than a copy, and replays on any per-texel buffer.
    ``tile`` is the side in texels of the square tiles a tiling lays out (0: not a tiling): their borders are
    straight by design, which the scores of straight seams leave out.
    """

    type_name: ClassVar[str] = "CoordMap"

    coords: np.ndarray
    source_size: tuple[int, int]
    blend_coords: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0, 2), np.int32))
    blend_weight: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0), np.float32))
    wrap: bool = False
    tile: int = 0

    def __post_init__(self):
        check_array("coords", self.coords, ("H", "W", 2), np.int32, owner="CoordMap")
        if isinstance(self.tile, bool) or int(self.tile) != self.tile or self.tile < 0:
            raise BtforgeInputError("CoordMap 'tile'", f"expected the tile side as an int >= 0, found {self.tile!r}",
                                    "give the side in texels of a tiling's square tiles, or 0 for any other map")
        object.__setattr__(self, "tile", int(self.tile))
        src_h, src_w = (int(v) for v in self.source_size)
        for name in ("coords",) + (("blend_coords",) if self.blend_weight.size else ()):
            c = getattr(self, name)
            if c.size and (c.min() < 0 or c[..., 0].max() >= src_h or c[..., 1].max() >= src_w):
                raise BtforgeInputError("CoordMap", f"'{name}' must lie inside the {src_h} x {src_w} exemplar, "
                                        f"found rows {c[..., 0].min()}..{c[..., 0].max()}, columns {c[..., 1].min()}..{c[..., 1].max()}",
                                        "give 'source_size' as the exemplar's [H, W], or clip the coordinates to it")
        if self.blend_weight.size:
            h, w = self.coords.shape[:2]
            check_array("blend_coords", self.blend_coords, (h, w, 2), np.int32, owner="CoordMap")
            check_array("blend_weight", self.blend_weight, (h, w), np.float32, finite=True, owner="CoordMap")
            if self.blend_weight.min() < 0 or self.blend_weight.max() > 1:
                raise BtforgeInputError("CoordMap", f"'blend_weight' must lie in [0, 1], found "
                                        f"{self.blend_weight.min():g}..{self.blend_weight.max():g}",
                                        "give the blend partner's share of each texel, clipped to [0, 1]")
        freeze_fields(self, "coords", "blend_coords", "blend_weight", source_size=(src_h, src_w))

    @property
    def height(self) -> int:
        return self.coords.shape[0]

    @property
    def width(self) -> int:
        return self.coords.shape[1]

    def apply(self, source: PerTexel) -> PerTexel:
        """Replay the map on ``source`` (which must have the exemplar's size)."""
        if (source.height, source.width) != self.source_size:
            raise BtforgeInputError("materialize 'source'", f"expected a {self.source_size[0]} x {self.source_size[1]} "
                                    f"exemplar, found {source.height} x {source.width}",
                                    "replay the map on a buffer of the exemplar it was synthesized from")
        rows, cols = self.coords[..., 0], self.coords[..., 1]
        if self.blend_weight.size:
            return source.remap(rows, cols, self.blend_coords[..., 0], self.blend_coords[..., 1], self.blend_weight)
        return source.remap(rows, cols)


def scattered_lookup(model: "ReflectanceModel", rows, cols, lights, views=None):
    """Checked arguments of ``evaluate_texels``: int rows and cols ``[N]`` inside the model, float32 unit
    ``lights [N, 3]`` and ``views [N, 3]`` (straight up when None)."""
    owner = f"{model.type_name} evaluate_texels"
    rows, cols = np.asarray(rows), np.asarray(cols)
    lights = np.ascontiguousarray(lights, dtype=np.float32)
    n = rows.shape[0] if rows.ndim == 1 else -1
    views = np.tile(np.float32([0, 0, 1]), (max(n, 0), 1)) if views is None else np.ascontiguousarray(views, np.float32)
    if rows.shape != cols.shape or rows.ndim != 1 or lights.shape != (n, 3) or views.shape != (n, 3):
        raise BtforgeInputError(owner, f"expected rows [N], cols [N], lights [N, 3] and views [N, 3], found "
                                f"{rows.shape}, {cols.shape}, {lights.shape} and {views.shape}")
    if rows.size and (rows.min() < 0 or rows.max() >= model.height or cols.min() < 0 or cols.max() >= model.width):
        raise BtforgeInputError(owner, f"texel indices must lie inside the {model.height} x {model.width} model")
    return rows, cols, lights, views


CORE_TYPES: tuple[type[Buffer], ...] = (Buffer, SampleStack, PerTexel, ReflectanceModel, Scores, CoordMap)
