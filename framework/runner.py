"""Demand-driven execution of a checked graph, with caching and a per-node report."""
from __future__ import annotations

import dataclasses
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any, Mapping

from .atomic import atomic_write_text
from .backend import default_cache_root
from .buffers import Buffer
from .cache import NodeCache
from .context import StageContext
from .errors import BtforgeError, BtforgeInputError
from .graph import CheckedGraph, check_graph, load_graph
from .registry import Registry, default_registry
from .stages import RunPaths


DEFAULT_OUT = Path("out")  # relative: resolved against the current folder when a stage writes


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
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


class RunResult(dict):
    """``{node: {port: Buffer}}`` for the requested nodes, plus the run ``report`` (one entry per graph node)."""

    report: list[NodeReport]

    def report_dict(self) -> dict[str, Any]:
        return {"nodes": [dataclasses.asdict(r) for r in self.report]}


class _Lazy:
    """An output that stayed in the cache: its content key is known, its data is loaded only if needed."""

    def __init__(self, cache: NodeCache, key: str, port: str, content_key: str, registry: Registry):
        self.cache, self.key, self.port, self.content_key, self.registry = cache, key, port, content_key, registry

    def load(self) -> Buffer:
        return self.cache.load(self.key, self.port, self.registry.types)


def run_checked(graph: CheckedGraph, *, only: list[str] | None = None, registry: Registry | None = None,
                out_dir: Path | None = None, cache_dir: Path | None = None, use_cache: bool = True,
                quiet: bool = False, scheduler: str = "local") -> RunResult:
    registry = registry or default_registry()
    paths = RunPaths(graph.spec.graph_dir, Path(out_dir) if out_dir else DEFAULT_OUT)
    cache = NodeCache(cache_dir or default_cache_root() / "nodes")
    order = graph.needed_for(only)
    targets = set(only) if only else {n for n in order if graph.dag.out_degree(n) == 0}
    consumers = {n: sum(1 for s in graph.dag.successors(n) if s in order) for n in order}

    values: dict[str, dict[str, Any]] = {}
    reports = {n: NodeReport(n, graph.stages[n].name, "not needed") for n in graph.spec.nodes}
    for index, name in enumerate(order, 1):
        st = graph.stages[name]
        params = graph.params[name]
        wired = graph.spec.nodes[name].inputs
        input_keys = {port: _key_of(values[src][src_port]) for port, (src, src_port) in wired.items()}
        key = cache.key(st.name, st.version, params, input_keys, graph.files.get(name, ()))
        report = reports[name]
        if not quiet:
            print(f"[{index}/{len(order)}] {name} ({st.name}) ...", file=sys.stderr, flush=True)
        manifest = cache.manifest(key, st.outputs) if use_cache and not st.side_effects else None
        if manifest is not None:
            values[name] = {port: _Lazy(cache, key, port, info["content_key"], registry)
                            for port, info in manifest["outputs"].items()}
            report.status, report.notes = "cached", manifest.get("notes", {})
        else:
            inputs = {port: _materialize(values[src], src_port) for port, (src, src_port) in wired.items()}
            ctx = StageContext(node=name, paths=paths, quiet=quiet)
            start = time.perf_counter()
            with _PeakMemory() as mem:
                try:
                    outputs = _execute(st, ctx, inputs, params, scheduler, registry)
                except BtforgeInputError as exc:
                    raise exc.located(graph.spec.where(name, graph.spec.nodes[name].line)) from exc
                except BtforgeError:
                    raise
                except Exception as exc:  # a bug in the stage: say where it happened (traceback behind --debug)
                    raise BtforgeError(f"node '{name}' ({st.name}, plugin {st.plugin}) failed: "
                                       f"{type(exc).__name__}: {exc} (a bug in the stage; the CLI shows the traceback with --debug)") from exc
            report.seconds = time.perf_counter() - start
            report.peak_rss_mb = round(mem.peak / 2**20, 1)
            report.status, report.notes = "ran", ctx.notes
            _check_outputs(name, st, outputs or {}, inputs, registry)
            values[name] = dict(outputs or {})
            if use_cache and not st.side_effects:
                cache.store(key, values[name], ctx.notes)
        if not quiet:
            print(f"      {report.status} in {report.seconds:.2f} s", file=sys.stderr, flush=True)
        for src in {src for src, _ in wired.values()}:  # free what no remaining node needs
            consumers[src] -= 1
            if consumers[src] == 0 and src not in targets:
                values.pop(src, None)

    result = RunResult()
    for name in order:
        if name in targets:
            result[name] = {port: _materialize(values[name], port) for port in values[name]}
    result.report = [reports[n] for n in graph.spec.nodes]
    return result


def _execute(st, ctx: StageContext, inputs: Mapping[str, Any], params: Mapping[str, Any], scheduler: str,
             registry: Registry):
    """Run one node: in this process, or - a per-texel stage on a stored stack with a distributed scheduler -
    as dask tasks over bands of texels (``framework/scheduler.py``)."""
    if scheduler != "local":
        from .scheduler import distributable, run_distributed
        port = distributable(st, params, inputs)
        if port is not None:
            outputs, notes = run_distributed(scheduler, st, port, inputs[port], params, registry.types)
            ctx.notes.update(notes)
            return outputs
    return st.fn(ctx, **inputs, **params)


def _key_of(value: Any) -> str:
    return value.content_key


def _materialize(outputs: Mapping[str, Any], port: str) -> Buffer:
    value = outputs[port]
    return value.load() if isinstance(value, _Lazy) else value


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
    if scheduler != "local":
        from .scheduler import check_scheduler
        check_scheduler(scheduler)
    spec = load_graph(graph, set)
    out = Path(out_dir) if out_dir else DEFAULT_OUT
    checked = check_graph(spec, registry, out)
    result = run_checked(checked, only=list(only) if only else None, registry=registry, out_dir=out,
                         cache_dir=Path(cache_dir) if cache_dir else None, use_cache=use_cache, quiet=quiet,
                         scheduler=scheduler)
    if report_path:
        atomic_write_text(report_path, json.dumps(result.report_dict(), indent=2, default=str))
    return result
