"""Where a process spends its time: the start-up budget of ``btforge run --profile`` and the report's ``startup``.

Start-up is what a fresh process pays before and besides its nodes: the interpreter and imports (measured from
the process's start, which Linux records in 10 ms ticks), loading the plugins, checking the graph, starting the
OpenCL device, and building kernels (from the binary cache or from source).  Kernel builds happen inside the
nodes that need them, so a node's time includes its builds.
"""
from __future__ import annotations

import os
import threading
import time
from typing import Any

_lock = threading.Lock()
_phases: dict[str, float] = {}
_builds: list[dict[str, Any]] = []


def seconds_since_process_start() -> float | None:
    """Wall seconds since this process started (Linux; None elsewhere)."""
    try:
        with open("/proc/self/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()  # the command name may hold spaces
        start_ticks = int(fields[19])                          # field 22 of proc(5): starttime
        return time.clock_gettime(time.CLOCK_BOOTTIME) - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError, AttributeError):
        return None


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM: unlike ru_maxrss it is not inherited from the parent)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    import resource  # not Linux
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def record_phase(name: str, seconds: float) -> None:
    """Add ``seconds`` to start-up phase ``name`` (e.g. ``"device_start"``)."""
    with _lock:
        _phases[name] = _phases.get(name, 0.0) + seconds


def record_build(source: str, options: str, seconds: float, how: str) -> None:
    """One OpenCL program build: ``how`` is ``"binary cache"`` or ``"source"``."""
    with _lock:
        _builds.append({"file": source, "options": options, "seconds": round(seconds, 4), "from": how})


def startup() -> dict[str, Any]:
    """The start-up figures so far: phases in seconds and every kernel build."""
    with _lock:
        phases = {k: round(v, 4) for k, v in _phases.items()}
        builds = list(_builds)
    return {**phases, "kernel_builds": builds,
            "kernel_builds_s": round(sum(b["seconds"] for b in builds), 4),
            "kernel_builds_from_cache": sum(b["from"] == "binary cache" for b in builds)}


def format_profile(report: dict[str, Any]) -> str:
    """The ``--profile`` table: start-up phases, kernel builds and nodes, from a run report."""
    start = report.get("startup", {})
    lines = ["where the time went:"]
    labels = (("interpreter_and_imports_s", "interpreter and imports"), ("plugins_s", "plugins loaded"),
              ("graph_check_s", "graph checked"), ("cache_keys_s", "cache keys (content hashes)"),
              ("cache_store_s", "cache entries written"),
              ("device_start_s", "OpenCL device started"))
    for key, label in labels:
        if key in start:
            lines.append(f"  {label:28s} {start[key]:7.3f} s")
    builds = start.get("kernel_builds", [])
    lines.append(f"  {'kernel builds':28s} {start.get('kernel_builds_s', 0.0):7.3f} s  ({len(builds)} programs, "
                 f"{start.get('kernel_builds_from_cache', 0)} from the binary cache; inside the nodes below)")
    for b in builds:
        lines.append(f"      {b['file']} {b['options'] or '(no options)'}: {b['seconds']:.3f} s from {b['from']}")
    nodes = [n for n in report.get("nodes", []) if n["status"] != "not needed"]
    lines.append(f"  {'nodes':28s} {sum(n['seconds'] for n in nodes):7.3f} s")
    for n in nodes:
        lines.append(f"      {n['node']} ({n['stage']}): {n['seconds']:.3f} s {n['status']}")
    if "process_s" in start:
        lines.append(f"  {'whole process so far':28s} {start['process_s']:7.3f} s")
    if "peak_rss_mb" in start:
        lines.append(f"  {'peak memory so far':28s} {start['peak_rss_mb']:7.0f} MB (MiB: 2^20 bytes)")
    return "\n".join(lines)
