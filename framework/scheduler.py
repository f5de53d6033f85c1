"""Running per-texel stages on dask.distributed: ``btforge run --scheduler dask|tcp://HOST:PORT``.

A node whose stage is declared ``per_texel`` and whose input stack is read from a chunked store
(``stack.chunked``) becomes a dask.array computation: the store's samples are a ``dask.array`` (``from_zarr``)
split into bands of chunk rows, and each band is one task that runs the stage on that band of texels.  Each
worker reads its band from the store itself (the store must be on a filesystem every worker sees), opens its
own OpenCL context in its own process (contexts cannot be pickled), and runs one kernel at a time (a lock per
worker process, and LocalCluster workers have one thread).  The client joins the bands' outputs along the
texel grid; the run report gets the tasks, the workers and the bytes that came back to the client (the samples
themselves are read by the workers from the store and never pass through the client).

``dask`` starts a LocalCluster of 2 worker processes on the loopback interface; ``tcp://HOST:PORT`` connects to
a running scheduler (``dask scheduler`` and ``dask worker tcp://HOST:PORT --nthreads 1`` on each machine).
"""
from __future__ import annotations

import threading
from typing import Any, Mapping

import numpy as np

from .buffers import Buffer, PerTexel, SampleStack
from .errors import BtforgeInputError
from .spill import release, spilled_empty

SCHEDULERS = ("local", "dask")
BAND_BYTES = 64 << 20
_kernel_lock = threading.Lock()  # per worker process: one OpenCL kernel at a time
_clients: dict[str, Any] = {}


def check_scheduler(name: str) -> str:
    if name in SCHEDULERS or name.startswith("tcp://"):
        return name
    raise BtforgeInputError("--scheduler", f"expected local, dask or tcp://HOST:PORT, found {name!r}",
                            "local runs in this process; dask starts 2 local workers; tcp:// joins a cluster")


def client_for(name: str):
    """A dask.distributed client: a 2-process LocalCluster on loopback (``dask``) or an existing scheduler."""
    if name not in _clients:
        from dask.distributed import Client, LocalCluster
        if name == "dask":
            cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                   dashboard_address=None)
            _clients[name] = Client(cluster)
        else:
            try:
                _clients[name] = Client(name, timeout="20s")
            except (OSError, TimeoutError) as exc:
                raise BtforgeInputError(f"--scheduler {name}", f"cannot reach the dask scheduler ({exc})",
                                        "start one with `dask scheduler` and workers with `dask worker "
                                        f"{name} --nthreads 1`, or use --scheduler dask for a local cluster") from None
    return _clients[name]


def close_clients() -> None:
    for client in _clients.values():
        cluster = getattr(client, "cluster", None)
        client.close()
        if cluster is not None:
            cluster.close()
    _clients.clear()


def distributable(stage, params: Mapping[str, Any], inputs: Mapping[str, Any]) -> str | None:
    """The input port a distributed run splits (a chunked stack), or None when the node runs locally."""
    if not stage.is_per_texel(params):
        return None
    chunked = [port for port, value in inputs.items() if getattr(value, "chunked", False)]
    return chunked[0] if len(chunked) == 1 and len(inputs) == 1 else None


def _run_band(samples: np.ndarray, stage_name: str, meta: dict, port: str, params: dict) -> dict:
    """On a worker: the stage on one band of texels; returns each output's payload and the notes."""
    from .context import StageContext
    from .registry import default_registry
    band = SampleStack(samples, np.asarray(meta["lights"]), np.asarray(meta["views"]), tuple(meta["channels"]),
                       meta["encoding"], tuple(meta.get("names") or ()))
    stage = default_registry().stage(stage_name)
    ctx = StageContext(node=stage_name, quiet=True)
    with _kernel_lock:
        outputs = stage.fn(ctx, **{port: band}, **params)
    return {"outputs": {name: (type(buf).type_name, *buf.payload()) for name, buf in outputs.items()},
            "notes": ctx.notes}


class _Joiner:
    """Assembles one output port from bands of texels as they arrive, in any order: texel fields are copied into
    their rows of one array (allocated on the first band, filled band by band, so the bands are not held twice);
    every other field must be the same in every band.  The joined arrays are spilled to a file, as a store's
    single-process fit is."""

    def __init__(self, types: Mapping[str, type[Buffer]], starts: list[int], height: int):
        self.types, self.starts, self.height = types, starts, height
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
                known = self.arrays.setdefault(name, piece)
                if not np.array_equal(known, piece):
                    raise BtforgeInputError(f"{type_name} '{name}'", "differs between bands of texels",
                                            "a bug in the stage's per_texel declaration")
                continue
            if name not in self.arrays:  # spilled: the joined result never becomes resident (framework/spill.py)
                shape = piece.shape[:axis] + (self.height,) + piece.shape[axis + 1:]
                self.arrays[name] = spilled_empty(shape, piece.dtype)
            index = (slice(None),) * axis + (slice(self.starts[band], self.starts[band] + piece.shape[axis]),)
            self.arrays[name][index] = piece
            release(self.arrays[name][index])

    def buffer(self) -> Buffer:
        return self.cls.from_payload(self.meta, self.arrays)


def run_distributed(scheduler: str, stage, port: str, stack, params: Mapping[str, Any],
                    types: Mapping[str, type[Buffer]]) -> tuple[dict[str, Buffer], dict[str, Any]]:
    """Run a per-texel stage on bands of a stored stack as dask.array tasks; return outputs and report notes."""
    import dask
    import dask.array as da

    client = client_for(scheduler)
    rows = [band.stop - band.start for band in stack.row_bands(BAND_BYTES)]
    samples = da.from_zarr(stack.samples).rechunk((-1, -1, tuple(rows), -1, -1))
    meta = {"lights": stack.lights.tolist(), "views": stack.views.tolist(), "channels": list(stack.channels),
            "encoding": stack.encoding, "names": list(stack.names)}
    blocks = samples.to_delayed().ravel()
    run = dask.delayed(_run_band, pure=True)
    tasks = [run(block, stage.name, meta, port, dict(params)) for block in blocks]
    graph_tasks = len(dask.delayed(list)(tasks).__dask_graph__())
    from dask.distributed import as_completed
    futures = client.compute(tasks)
    band_of = {future.key: band for band, future in enumerate(futures)}
    starts = list(np.cumsum([0] + rows[:-1]))
    joiners: dict[str, _Joiner] = {}
    moved, band_notes = 0, {}
    for future, result in as_completed(futures, with_results=True):  # joined as they come: held once
        band = band_of[future.key]
        for name, part in result["outputs"].items():
            joiners.setdefault(name, _Joiner(types, starts, stack.height)).add(band, part)
            moved += sum(a.nbytes for a in part[2].values())
        band_notes[band] = result["notes"]
        del result
    futures.clear()
    outputs = {name: joiner.buffer() for name, joiner in joiners.items()}
    results = [{"notes": band_notes[band]} for band in sorted(band_notes)]
    notes = {"scheduler": scheduler, "tasks": graph_tasks, "bands": len(tasks),
             "workers": len(client.scheduler_info()["workers"]), "bytes_to_client": int(moved)}
    notes.update(results[0]["notes"])
    warnings = sorted({w for r in results for w in r["notes"].get("warnings", [])})
    if warnings:
        notes["warnings"] = warnings
    if len(results) > 1:
        notes["notes_from"] = "the first band of texels (each band reports its own)"
    return outputs, notes


__all__ = ["run_distributed", "distributable", "check_scheduler", "client_for", "close_clients"]
