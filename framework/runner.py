"""Demand-driven execution of a checked graph, with caching and a per-node report."""
from __future__ import annotations

import dataclasses
import functools
import json
import os
import sys
import threading
import time
import warnings
from pathlib import Path
from typing import Any, Mapping

from . import profile
from .atomic import atomic_write_text
from .buffers import Buffer
from .cache import DamagedEntry, NodeCache, node_key_of_output, plain_notes
from .context import StageContext
from .errors import BtforgeError, BtforgeInputError, BtforgeWarning, collect_warnings
from .graph import CheckedGraph, check_graph, load_graph
from .locations import default_cache_root
from .registry import Registry, default_registry
from .stages import RunPaths
from .streaming import not_split_reason, per_texel_input, run_banded, streamed_outputs


DEFAULT_OUT = Path("out")  # relative: resolved against the current folder when a stage writes


_statm: list[tuple[int, int]] = []  # (process id, open /proc/self/statm of that process)


def _rss_bytes() -> int:
    """This process's resident memory: a ``pread`` of ``/proc/self/statm`` kept open (half the cost of opening it
    on every sample; opened again in a forked child, where the parent's file would describe the parent)."""
    try:
        if not _statm or _statm[0][0] != os.getpid():
            _statm[:] = [(os.getpid(), os.open("/proc/self/statm", os.O_RDONLY))]
        return int(os.pread(_statm[0][1], 128, 0).split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:  # not Linux: fall back to the lifetime peak
        import resource
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


class _PeakMemory:
    """Samples resident memory in a background thread while a node runs."""

    def __init__(self, interval: float = 0.002):
        self.interval = interval
        self.peak = 0

    def __enter__(self):
        self.start = self.peak = _rss_bytes()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()
        return self

    def _watch(self):
        while not self._stop.wait(self.interval):
            self.peak = max(self.peak, _rss_bytes())

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_bytes())


@dataclasses.dataclass
class NodeReport:
    node: str
    stage: str
    status: str  # 'ran', 'cached' or 'not needed'
    seconds: float = 0.0
    peak_rss_mb: float | None = None
    notes: dict[str, Any] = dataclasses.field(default_factory=dict)
    # where it ran: {"where": "local"} (with "bands" when streamed band by band), {"where": SCHEDULER, "tasks",
    # "workers"} on a cluster, {"where": "cache"}; empty when it did not run
    placement: dict[str, Any] = dataclasses.field(default_factory=dict)


class RunResult(dict):
    """``{node: {port: Buffer}}`` for the requested nodes, plus the run ``report`` (one entry per graph node)."""

    report: list[NodeReport]
    startup: dict[str, Any]
    output_paths: list[Path]  # the output paths stages asked for (files or folders; some may not be written)

    def report_dict(self) -> dict[str, Any]:
        """The run report: one entry per node, and under ``startup`` where the process spent its time besides."""
        return {"nodes": [dataclasses.asdict(r) for r in self.report], "startup": getattr(self, "startup", {})}


class _Lazy:
    """An output that stayed in the cache: its content key is known, its data is loaded only if needed."""

    def __init__(self, cache: NodeCache, key: str, port: str, content_key: str, registry: Registry):
        self.cache, self.key, self.port, self.content_key, self.registry = cache, key, port, content_key, registry

    def load(self) -> Buffer:
        return self.cache.load(self.key, self.port, self.registry.types)


class _Deferred:
    """An output of a node that is not stored: keyed by the node's own key (a function of its code, params, files
    and inputs), so its consumers find their cache entries without it; it runs the first time one needs data."""

    def __init__(self, run_node, node_key: str, port: str):
        self.run_node, self.port = run_node, port
        self.content_key = node_key_of_output(node_key, port)

    def load(self) -> Buffer:
        return self.run_node()[self.port]


def run_checked(graph: CheckedGraph, *, only: list[str] | None = None, registry: Registry | None = None,
                out_dir: Path | None = None, cache_dir: Path | None = None, use_cache: bool = True,
                quiet: bool = False, scheduler: str = "local") -> RunResult:
    registry = registry or default_registry()
    paths = RunPaths(graph.spec.graph_dir, Path(out_dir) if out_dir else DEFAULT_OUT)
    cache = NodeCache(cache_dir or default_cache_root() / "nodes")
    order = graph.needed_for(only)
    targets = set(only) if only else {n for n in order if graph.dag.out_degree(n) == 0}
    consumers = {n: sum(1 for s in graph.dag.successors(n) if s in order) for n in order}
    streamed = streamed_outputs(graph, order, targets)  # read band by band: only per-texel nodes read them
    if not use_cache and any(graph.stages[n].device for n in order):
        _start_device_early()  # nothing comes from the cache: a node on the device will run

    values: dict[str, dict[str, Any]] = {}
    reports = {n: NodeReport(n, graph.stages[n].name, "not needed") for n in graph.spec.nodes}
    for index, name in enumerate(order, 1):
        st = graph.stages[name]
        wired = graph.spec.nodes[name].inputs
        report = reports[name]
        if not quiet:
            print(f"[{index}/{len(order)}] {name} ({st.name}) ...", file=sys.stderr, flush=True)
            for what, why in graph.notes.get(name, {}).items():  # an 'auto' param the graph check narrowed
                print(f"      {what}: {why}", file=sys.stderr, flush=True)
        cacheable = use_cache and not st.side_effects
        key = _node_key(graph, name, values, cache, registry) if cacheable else ""
        with collect_warnings() as cache_warnings:
            manifest = _cached_manifest(cache, key, name, st) if cacheable and st.cache_outputs else None
        if manifest is not None:
            values[name] = {port: _Lazy(cache, key, port, info["content_key"], registry)
                            for port, info in manifest["outputs"].items()}
            report.status, report.notes, report.placement = "cached", manifest.get("notes", {}), {"where": "cache"}
        elif cacheable and not st.cache_outputs:  # cheaper to recompute than to store: run only if data is needed
            sources = {port: values[src][src_port] for port, (src, src_port) in wired.items()}
            run_node = functools.cache(lambda name=name, sources=sources: _evaluate(
                graph, name, {p: _materialize(sources, p) for p in sources}, paths, reports[name], registry, quiet,
                scheduler, streamed.get(name, frozenset())))
            values[name] = {port: _Deferred(run_node, key, port) for port in st.outputs}
            report.status = "deferred"
        else:
            if st.device:
                _start_device_early()  # overlaps reading the inputs that were deferred until now
            inputs = {port: _materialize(values[src], src_port) for port, (src, src_port) in wired.items()}
            values[name] = _evaluate(graph, name, inputs, paths, report, registry, quiet, scheduler,
                                     streamed.get(name, frozenset()))
            if cacheable:
                started = time.perf_counter()
                cache.store(key, values[name], report.notes)
                profile.record_phase("cache_store_s", time.perf_counter() - started)
        _add_warnings(report.notes, name, [*graph.warnings.get(name, ()), *cache_warnings])
        if not quiet:
            print(f"      {report.status} in {report.seconds:.2f} s" if report.status != "deferred" else
                  "      deferred: its outputs are not stored; it runs if a node that reads them does",
                  file=sys.stderr, flush=True)
        for src in {src for src, _ in wired.values()}:  # free what no remaining node needs
            consumers[src] -= 1
            if consumers[src] == 0 and src not in targets:
                values.pop(src, None)

    return _result(graph, order, targets, values, reports, paths)


def _result(graph: CheckedGraph, order: list[str], targets: set[str], values: Mapping[str, Mapping[str, Any]],
            reports: Mapping[str, NodeReport], paths: RunPaths) -> RunResult:
    """The requested nodes' outputs, loaded, with the report of every node."""
    result = RunResult()
    for name in order:
        if name in targets:
            result[name] = {port: _materialize(values[name], port) for port in values[name]}
    for report in reports.values():
        if report.status == "deferred":  # no node needed its data: every consumer came from the cache
            report.status = "not needed"
        if report.status in ("ran", "cached") and graph.notes.get(report.node):  # choices the graph check made
            report.notes = {**graph.notes[report.node], **report.notes}
    result.report = [reports[n] for n in graph.spec.nodes]
    result.output_paths = list(dict.fromkeys(paths.requested))
    return result


_device_starting: list[threading.Thread] = []


def _start_device_early() -> None:
    """Start the OpenCL device (importing pyopencl, choosing the device: a few tenths of a second) in a thread,
    once per process, while this one reads inputs.  A failure is left for the node that needs the device to
    report."""
    def start() -> None:
        try:
            from .backend import get_backend
            get_backend()
        except Exception:  # noqa: BLE001 - reported where the device is used
            pass
    if not _device_starting:
        _device_starting.append(threading.Thread(target=start, name="btforge-device-start"))
        _device_starting[0].start()


def _node_key(graph: CheckedGraph, name: str, values: Mapping[str, Mapping[str, Any]], cache: NodeCache,
              registry: Registry) -> str:
    started = time.perf_counter()
    st = graph.stages[name]
    input_keys = {port: _key_of(values[src][src_port]) for port, (src, src_port) in graph.spec.nodes[name].inputs.items()}
    key = cache.key(st.name, st.version, graph.params[name], input_keys, graph.files.get(name, ()),
                    registry.code_digest(st.name, cache.file_memo))
    profile.record_phase("cache_keys_s", time.perf_counter() - started)
    return key


def _evaluate(graph: CheckedGraph, name: str, inputs: Mapping[str, Buffer], paths: RunPaths, report: NodeReport,
              registry: Registry, quiet: bool, scheduler: str = "local",
              streamed: frozenset[str] = frozenset()) -> dict[str, Buffer]:
    """Run one node's stage; fill its report (time, peak memory, notes and every warning raised meanwhile).
    ``streamed`` are the outputs to hand over band by band (``framework/streaming.py``)."""
    st = graph.stages[name]
    ctx = StageContext(node=name, paths=paths, quiet=quiet, streamed=streamed)
    start = time.perf_counter()
    with _PeakMemory() as mem, collect_warnings() as raised:
        try:
            outputs = _execute(st, ctx, inputs, graph.params[name], scheduler, registry, report)
        except BtforgeInputError as exc:
            raise exc.located(graph.spec.where(name, graph.spec.nodes[name].line)) from exc
        except BtforgeError:
            raise
        except Exception as exc:  # a bug in the stage: say where it happened (traceback behind --debug)
            raise BtforgeError(f"node '{name}' ({st.name}, plugin {st.plugin}) failed: "
                               f"{type(exc).__name__}: {exc} (a bug in the stage; the CLI shows the traceback with --debug)") from exc
    report.seconds = time.perf_counter() - start
    report.peak_rss_mb = round(mem.peak / 2**20, 1)
    earlier = report.notes.get("warnings", [])  # a deferred node's: noted before it ran
    plain = plain_notes(ctx.notes)  # as a cache hit will give them back; the same dict, which the report shares
    ctx.notes.clear()
    ctx.notes.update(plain)
    report.status, report.notes = "ran", ctx.notes
    _add_warnings(report.notes, name, [*earlier, *raised])
    _check_outputs(name, st, outputs or {}, inputs, registry)
    return dict(outputs or {})


def _add_warnings(notes: dict[str, Any], node: str, raised) -> None:
    """Put warnings into a node's notes once each (``ctx.warn`` has already noted its own, without the prefix)."""
    prefix = f"node '{node}': "
    kept = notes.setdefault("warnings", [])
    for text in raised:
        text = text[len(prefix):] if text.startswith(prefix) else text
        if text not in kept:
            kept.append(text)
    if not kept:
        del notes["warnings"]


def _cached_manifest(cache: NodeCache, key: str, name: str, st) -> dict[str, Any] | None:
    """The node's cache entry, or None to compute it; a damaged entry is recomputed with a warning."""
    try:
        return cache.manifest(key, st.outputs)
    except DamagedEntry as exc:
        warnings.warn(f"node '{name}': its cache entry is damaged ({exc}); computing it again", BtforgeWarning,
                      stacklevel=2)
        return None


def _execute(st, ctx: StageContext, inputs: Mapping[str, Any], params: Mapping[str, Any], scheduler: str,
             registry: Registry, report: NodeReport):
    """Run one node: whole in this process; band by band in this process (a per-texel stage whose one input is a
    stack read band by band, ``framework/streaming.py``); or, with a distributed scheduler, the same bands as
    tasks on the cluster (``framework/scheduler.py``).  Fill the report's placement."""
    port = per_texel_input(st, params, inputs)
    banded = port is not None and inputs[port].chunked
    if scheduler != "local" and banded:
        from .scheduler import run_distributed
        outputs, notes = run_distributed(scheduler, st, port, inputs[port], _settled(st, ctx, inputs, params),
                                         registry.types)
        ctx.notes.update(notes)
        report.placement = {"where": scheduler, "tasks": notes["tasks"], "workers": notes["workers"]}
        return outputs
    if scheduler != "local":
        reason = not_split_reason(st, params, inputs) if port is None else (
            "its stack is held whole in this process (another node reads it whole, or it is not a capture "
            "stackio.read streams); read a store made by stackio.import to fit it on the cluster")
        if reason:
            ctx.warn(f"runs in this process, not on {scheduler}: {reason}")
    if banded:
        # settled while the reader takes in the first band
        outputs, bands = run_banded(st, ctx, port, inputs[port], lambda: _settled(st, ctx, inputs, params),
                                    registry.types)
        report.placement = {"where": "local", "bands": bands}
        return outputs
    report.placement = {"where": "local"}
    return st.fn(ctx, **inputs, **params)


def _settled(st, ctx: StageContext, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, Any]:
    """The params with what depends on all texels decided once on the whole input (noted when it changed)."""
    settled = st.settled(inputs, params)
    changed = {key: value for key, value in settled.items() if params.get(key) != value}
    if changed:
        ctx.note("settled", changed)
    return settled


def _key_of(value: Any) -> str:
    return value.content_key


def _materialize(outputs: Mapping[str, Any], port: str) -> Buffer:
    value = outputs[port]
    return value.load() if isinstance(value, (_Lazy, _Deferred)) else value


def _check_outputs(name: str, st, outputs: Mapping[str, Any], inputs: Mapping[str, Any], registry: Registry) -> None:
    if set(outputs) != set(st.outputs):
        raise BtforgeError(f"node '{name}': stage '{st.name}' ({st.plugin}) returned ports {sorted(outputs)}, "
                           f"declared {sorted(st.outputs)}")
    for port, value in outputs.items():
        declared = st.outputs[port]
        want = type(inputs[declared[1:]]) if declared.startswith("=") else registry.types[declared]
        if not isinstance(value, want):
            raise BtforgeError(f"node '{name}': stage '{st.name}' returned {type(value).__name__} on port '{port}', "
                               f"declared {want.type_name}")


def run(graph, only: list[str] | None = None, set: Mapping[str, Any] | None = None, *,
        out_dir: str | os.PathLike | None = None, cache_dir: str | os.PathLike | None = None,
        use_cache: bool = True, quiet: bool = True, registry: Registry | None = None,
        report_path: str | os.PathLike | None = None, scheduler: str = "local") -> RunResult:
    """Check and run a graph (a YAML path or a mapping); return the outputs of the requested nodes.

    Parameters
    ----------
    graph
        Path of a graph YAML file, or the same structure as a dict.
    only
        Nodes whose outputs are wanted; only they and what they depend on run.  Default: every sink node.
    set
        Parameter overrides ``{"node.param": value}``.
    out_dir, cache_dir
        Where output paths resolve (default: ``out`` in the current folder) and where node outputs are cached.
    scheduler
        ``local`` (this process), ``dask`` (a 2-worker LocalCluster) or ``tcp://HOST:PORT`` (a running dask
        scheduler): where per-texel stages on stored stacks run.  Results do not depend on it.
    """
    registry = registry or default_registry()
    start = time.perf_counter()
    if scheduler != "local":
        from .scheduler import check_scheduler
        check_scheduler(scheduler)
    spec = load_graph(graph, set)
    out = Path(out_dir) if out_dir else DEFAULT_OUT
    checked = check_graph(spec, registry, out)
    profile.record_phase("graph_check_s", time.perf_counter() - start)
    result = run_checked(checked, only=list(only) if only else None, registry=registry, out_dir=out,
                         cache_dir=Path(cache_dir) if cache_dir else None, use_cache=use_cache, quiet=quiet,
                         scheduler=scheduler)
    result.startup = profile.startup()
    process_s = profile.seconds_since_process_start()
    if process_s is not None:
        result.startup["process_s"] = round(process_s, 3)
    result.startup["peak_rss_mb"] = round(profile.peak_rss_mb(), 1)  # the whole process's, so far
    if report_path:
        atomic_write_text(report_path, json.dumps(result.report_dict(), indent=2, default=str))
    return result
