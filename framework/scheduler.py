"""Running per-texel stages on dask.distributed: ``btforge run --scheduler dask|tcp://HOST:PORT``.

A node whose stage is per texel with its params (``per_texel``, once ``settle`` has decided ``space: auto`` on
a sample of the whole input) and whose one input is a stack read band by band (``stack.chunked``: a chunked
store, or a capture ``stackio.read`` streams because only per-texel nodes read it) runs as one task per band of
rows of texels.  A worker reads its band of a store itself (the store must be on a filesystem every worker
sees); the bands of a streamed capture are sent from this process, two per worker at a time.  Each worker opens
its own OpenCL context in its own process (contexts cannot be pickled) and runs one kernel at a time (a lock
per worker process, and LocalCluster workers have one thread).  The client joins the bands' outputs along the
texel grid (``framework/streaming.py``); the run report gets where each node ran (``placement``), the tasks,
the workers and the bytes that came back to the client.  A node that reads stacks but cannot be split runs in
this process with a warning that says why.

``dask`` starts a LocalCluster of 2 worker processes on the loopback interface; ``tcp://HOST:PORT`` connects to
a running scheduler (``dask scheduler`` and ``dask worker tcp://HOST:PORT --nthreads 1`` on each machine).
"""
from __future__ import annotations

import threading
from typing import Any, Mapping

import numpy as np

from .buffers import Buffer, SampleStack
from .errors import BtforgeInputError
from .streaming import Joiner, band_stack, merge_band_notes

SCHEDULERS = ("local", "dask")
BAND_BYTES = 64 << 20  # linear float32 samples of one task's band of rows
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


def _band_meta(stack) -> dict:
    return {"lights": stack.lights.tolist(), "views": stack.views.tolist(), "channels": list(stack.channels),
            "encoding": stack.encoding, "names": list(stack.names)}


def _run_band(samples, stage_name: str, meta: dict, port: str, params: dict) -> dict:
    """On a worker: the stage on one band of texels (its samples, or ``(store, rows)`` to read them from a
    store every worker sees); returns each output's payload and the notes."""
    from .context import StageContext
    from .registry import default_registry
    if isinstance(samples, tuple):
        from .store import open_store, read_samples
        samples = read_samples(open_store(samples[0])[0], samples[1])
    band = SampleStack(samples, np.asarray(meta["lights"]), np.asarray(meta["views"]), tuple(meta["channels"]),
                       meta["encoding"], tuple(meta.get("names") or ()))
    stage = default_registry().stage(stage_name)
    ctx = StageContext(node=stage_name, quiet=True)
    with _kernel_lock:
        outputs = stage.fn(ctx, **{port: band}, **params)
    return {"outputs": {name: (type(buf).type_name, *buf.payload()) for name, buf in outputs.items()},
            "notes": ctx.notes}


def _band_source(stack, rows: slice):
    """What a task gets for a band: the store and rows to read (the samples never pass through the client), or
    the band's samples themselves (a capture streamed in this process)."""
    store = getattr(stack, "store", "")
    return (store, rows) if store else band_stack(stack, rows).samples


def run_distributed(scheduler: str, stage, port: str, stack, params: Mapping[str, Any],
                    types: Mapping[str, type[Buffer]]) -> tuple[dict[str, Buffer], dict[str, Any]]:
    """Run a per-texel stage (``params`` settled) on bands of rows of a stack read band by band, one task per
    band on the cluster, at most two bands per worker in flight; return the joined outputs and report notes."""
    from dask.distributed import as_completed

    client = client_for(scheduler)
    bands = list(stack.row_bands(BAND_BYTES))
    workers = max(1, len(client.scheduler_info()["workers"]))
    meta, params = _band_meta(stack), dict(params)
    joiners: dict[str, Joiner] = {}
    moved, band_notes, band_of = 0, {}, {}

    def submit(index: int):
        future = client.submit(_run_band, _band_source(stack, bands[index]), stage.name, meta, port, params,
                               pure=False)
        band_of[future.key] = index
        return future

    waiting = iter(range(len(bands)))
    running = as_completed([submit(i) for _, i in zip(range(2 * workers), waiting)], with_results=True)
    for future, result in running:  # joined as they come: held once
        band = band_of.pop(future.key)
        for name, part in result["outputs"].items():
            joiners.setdefault(name, Joiner(types, [b.start for b in bands], stack.height)).add(band, part)
            moved += sum(a.nbytes for a in part[2].values())
        band_notes[band] = result["notes"]
        del result
        following = next(waiting, None)
        if following is not None:
            running.add(submit(following))
    notes = {"scheduler": scheduler, "tasks": len(bands), "bands": len(bands), "workers": workers,
             "bytes_to_client": int(moved)}
    notes.update(merge_band_notes([band_notes[band] for band in sorted(band_notes)]))
    return {name: joiner.buffer() for name, joiner in joiners.items()}, notes


__all__ = ["run_distributed", "check_scheduler", "client_for", "close_clients"]
