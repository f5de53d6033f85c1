"""Streaming stacks through per-texel stages: decided from the graph, run band by band of rows.

A capture read whole costs the process its full size (a 1024 x 1024, 49-light RGB capture is 154 MB of bytes)
although a per-texel fit only ever needs the samples of a band of texels at a time.  So, before a run, the
runner looks at who reads each output a stage can stream (declared ``streams``, as ``stackio.read`` does): when
every node reading it in this run is per texel (declared ``per_texel`` for its params) and reads nothing else,
the reader is asked for a stack read band by band (``ctx.streamed``; ``stack.chunked`` is then true), and each
of those nodes runs band by band (:func:`run_banded`): a band of rows of every image is paged in, the stage runs
on it as on a small stack, its outputs are copied into their rows of spilled arrays (``framework/spill.py``),
and the band's pages are handed back.  A graph in which any node reads the stack whole (a split, a compare, a
relight, the stack asked for as a result) streams nothing.

Choices a stage makes from all texels (``space: auto``, judged on a grid of texels) are made first, on the
whole input, by the stage's ``settle``; every band then runs with the settled params, so the result equals the
whole-stack fit's.  A distributed run (``framework/scheduler.py``) uses the same bands and the same joiner.
"""
from __future__ import annotations

import warnings
from typing import Any, Callable, Mapping

import numpy as np

from .buffers import Buffer, PerTexel, SampleStack, values_already_checked
from .errors import BtforgeInputError
from .spill import read_block, release, spilled_empty, write_items

# linear float32 samples of the bands of rows in memory at once (a uint8 capture reads a quarter of it): one
# band of a store, two half-size bands of a spilled capture (one of them read ahead)
BAND_BYTES = 64 << 20


def streamed_outputs(graph, order: list[str], targets: set[str]) -> dict[str, frozenset[str]]:
    """For each node of ``order``, the outputs it should hand over band by band: those it declares ``streams``,
    that are not asked for as results, and whose every reader in this run is per texel on that input alone."""
    readers: dict[tuple[str, str], list[tuple[str, str]]] = {}
    for name in order:
        for port, (source, source_port) in graph.spec.nodes[name].inputs.items():
            readers.setdefault((source, source_port), []).append((name, port))
    result = {}
    for name in order:
        ports = frozenset(port for port in graph.stages[name].streams if name not in targets
                          and readers.get((name, port))
                          and all(_reads_per_texel(graph, node, port_in) for node, port_in in readers[(name, port)]))
        if ports:
            result[name] = ports
    return result


def _reads_per_texel(graph, node: str, port: str) -> bool:
    stage = graph.stages[node]
    return set(graph.spec.nodes[node].inputs) == {port} and stage.is_per_texel(graph.params[node])


def per_texel_input(stage, params: Mapping[str, Any], inputs: Mapping[str, Any]) -> str | None:
    """The input a node can be split along texels (its one stack input, the stage per texel with these params),
    or None."""
    if len(inputs) != 1 or not stage.is_per_texel(params):
        return None
    (port, value), = inputs.items()
    return port if isinstance(value, SampleStack) else None


def not_split_reason(stage, params: Mapping[str, Any], inputs: Mapping[str, Any]) -> str | None:
    """Why a stage that fits stacks cannot be split into bands of texels with these params (None for stages that
    are not about stacks at all, which need no explanation)."""
    if stage.per_texel is False and stage.role != "fit":
        return None
    if not any(isinstance(value, SampleStack) for value in inputs.values()):
        return None
    if len(inputs) != 1:
        return f"it reads {len(inputs)} inputs; only a stage reading one stack is split into bands of texels"
    if stage.per_texel is False:
        return f"stage '{stage.name}' is not declared per texel"
    return f"stage '{stage.name}' is not per texel with these params ({_params_text(params)})"


def _params_text(params: Mapping[str, Any]) -> str:
    return ", ".join(f"{key}: {value}" for key, value in params.items())


def band_stack(stack: SampleStack, rows: slice, out: np.ndarray | None = None) -> SampleStack:
    """An in-memory stack of the samples of a band of rows (decompressed from a store, or paged in: into ``out``
    when given, a buffer as :func:`~btforge.spill.read_block` takes)."""
    samples = read_block(stack.samples, 2, rows, out) if isinstance(stack.samples, np.ndarray) \
        else np.asarray(stack.samples[:, :, rows])
    return SampleStack(samples, stack.lights, stack.views, stack.channels, stack.encoding, stack.names)


def run_banded(stage, ctx, port: str, stack: SampleStack, params: Mapping[str, Any] | Callable[[], Mapping[str, Any]],
               types: Mapping[str, type[Buffer]]) -> tuple[dict[str, Buffer], int]:
    """Run a per-texel stage on ``stack`` band by band of rows in this process (``params`` already settled, or a
    function settling them, called while the first band is read); return its outputs joined along the texel
    grid, and the number of bands.  Each band's pages are handed back after it ran.  Bands paged in from a file
    are read into two buffers in turn (:class:`_BandReader`), and a band's outputs are written to their files
    while the next band runs (:class:`Joiner`)."""
    from .context import StageContext
    # a spilled stack's bands are read ahead into two buffers (_BandReader): half a band each, the memory of one
    bands = list(stack.row_bands(BAND_BYTES // 2 if isinstance(stack.samples, np.ndarray) else BAND_BYTES))
    joiners: dict[str, Joiner] = {}
    notes = []
    band_arrays: dict[str, np.ndarray] = {}  # what StageContext.output_array lends every band
    with _BandReader(stack, bands) as reader:
        params = params() if callable(params) else params
        for index, rows in enumerate(bands):
            band_ctx = StageContext(node=ctx.node, paths=ctx.paths, quiet=True, band_arrays=band_arrays,
                                    band_index=index)
            band = reader.band(index)  # and the next band's samples start to be read meanwhile
            with warnings.catch_warnings():
                if index:  # every band warns alike: the first band's warnings are raised, the others' noted
                    warnings.simplefilter("ignore")
                outputs = stage.fn(band_ctx, **{port: band}, **params)
            del band
            for name, buffer in outputs.items():
                joiners.setdefault(name, Joiner(types, [band.start for band in bands], stack.height,
                                                reader.defer)).add(index, (type(buffer).type_name, *buffer.payload()))
            del outputs
            notes.append(band_ctx.notes)
            if isinstance(stack.samples, np.ndarray):
                release(stack.samples[:, :, rows])
        reader.finish()
    ctx.notes.update(merge_band_notes(notes))
    with values_already_checked():  # each band's outputs were checked as buffers of their types in this process
        return {name: joiner.buffer() for name, joiner in joiners.items()}, len(bands)


class _BandReader:
    """The band stacks of a walk over ``bands`` in order.  A spilled stack's bands are read from its file into
    two buffers in turn (each faulted into memory once), the next band in a thread while the stage runs on
    this one: the read (a copy out of the file) overlaps the stage's work.  The same thread writes each band's
    outputs out (:meth:`defer`) while the next band runs, in order, before it reads the band after next: so a
    buffer, or memory lent to every other band's outputs (``StageContext.output_array``), is taken again only
    once what was in it has been written out."""

    def __init__(self, stack: SampleStack, bands: list[slice]):
        self.stack, self.bands = stack, bands
        self.pool = self.next = None
        self.writes: list = []
        if isinstance(stack.samples, np.ndarray) and len(bands) > 1:
            import concurrent.futures
            rows = max(band.stop - band.start for band in bands)
            self.buffers = [np.empty(stack.samples[:, :, :rows].size, stack.samples.dtype) for _ in range(2)]
            self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="btforge-band")
            self.next = self.pool.submit(self._read, 0)

    def _read(self, index: int) -> SampleStack:
        rows = self.bands[index]
        buffer = self.buffers[index % 2]
        # the band stack read into it two bands before froze it; that band was joined before this read began
        buffer.flags.writeable = True
        samples = read_block(self.stack.samples, 2, rows, buffer)
        # Read-only as a whole, so that a shorter last band's samples, a part of the buffer, are frozen in place
        # like a full band's: a new array for them would cost a page fault per page (0.05 s of system time for
        # the last band of a 1024^2 x 49 capture).
        buffer.flags.writeable = False
        stack = self.stack
        return SampleStack(samples, stack.lights, stack.views, stack.channels, stack.encoding, stack.names)

    def band(self, index: int) -> SampleStack:
        if self.pool is None:
            return band_stack(self.stack, self.bands[index])
        band = self.next.result()
        self.next = self.pool.submit(self._read, index + 1) if index + 1 < len(self.bands) else None
        return band

    def defer(self, function, *args) -> None:
        """``function(*args)`` on the reading thread, after the read under way (at once without that thread)."""
        if self.pool is None:
            function(*args)
            return
        self.writes.append(self.pool.submit(function, *args))

    def finish(self) -> None:
        """Wait for every deferred write; the first one that failed raises."""
        writes, self.writes = self.writes, []
        for write in writes:
            write.result()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            if self.next is not None:
                self.next.cancel()
            self.pool.shutdown(wait=True)


def merge_band_notes(band_notes: list[dict[str, Any]]) -> dict[str, Any]:
    """One node's notes from its bands' notes: the first band's, with every band's distinct warnings."""
    merged = dict(band_notes[0]) if band_notes else {}
    found = sorted({w for notes in band_notes for w in notes.get("warnings", [])})
    if found:
        merged["warnings"] = found
    if len(band_notes) > 1:
        merged["notes_from"] = "the first band of texels (each band reports its own)"
    return merged


class Joiner:
    """Assembles one output port from bands of texels as they arrive, in any order: texel fields are copied into
    their rows of one array (allocated on the first band, filled band by band, so the bands are not held twice);
    every other field must be the same in every band.  The joined arrays are spilled to a file, so the result
    never becomes resident until a stage reads it."""

    def __init__(self, types: Mapping[str, type[Buffer]], starts: list[int], height: int, defer=None):
        self.types, self.starts, self.height = types, starts, height
        # how whole rows are written to their file: at once, or handed to a thread (run_banded's reader)
        self.defer = defer or (lambda function, *args: function(*args))
        self.type_name = self.meta = None
        self.arrays: dict[str, np.ndarray] = {}

    def add(self, band: int, part: tuple[str, dict, dict]) -> None:
        type_name, meta, arrays = part
        if self.type_name is None:
            self.type_name, self.meta = type_name, meta
            self.cls = self.types[type_name]
            if not issubclass(self.cls, PerTexel):
                raise BtforgeInputError(type_name, "is not a per-texel buffer, so bands of it cannot be joined",
                                        "declare the stage per_texel only if its outputs are per-texel buffers")
        if meta != self.meta:
            raise BtforgeInputError(type_name, "bands disagree on parameters that are not per-texel",
                                    "a bug in the stage's per_texel declaration")
        axis = self.cls.texel_axis
        for name, piece in arrays.items():
            if name not in self.cls.texel_fields:
                if name not in self.arrays:  # a copy: the band's arrays may lie in a buffer the next band reuses
                    self.arrays[name] = piece.copy() if isinstance(piece, np.ndarray) else piece
                known = self.arrays[name]
                if not np.array_equal(known, piece):
                    raise BtforgeInputError(f"{type_name} '{name}'", "differs between bands of texels",
                                            "a bug in the stage's per_texel declaration")
                continue
            if name not in self.arrays:  # spilled: the joined result never becomes resident (framework/spill.py)
                shape = piece.shape[:axis] + (self.height,) + piece.shape[axis + 1:]
                self.arrays[name] = spilled_empty(shape, piece.dtype)
            if axis == 0:  # whole rows: plain writes to the file, no pages mapped
                self.defer(write_items, self.arrays[name], self.starts[band], piece)
                continue
            index = (slice(None),) * axis + (slice(self.starts[band], self.starts[band] + piece.shape[axis]),)
            self.arrays[name][index] = piece
            release(self.arrays[name][index])

    def buffer(self) -> Buffer:
        return self.cls.from_payload(self.meta, self.arrays)


__all__ = ["streamed_outputs", "per_texel_input", "not_split_reason", "run_banded", "band_stack",
           "merge_band_notes", "Joiner", "BAND_BYTES"]
