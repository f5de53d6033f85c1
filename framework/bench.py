"""Benchmarks (``btforge bench NAME ...``): measured figures, never asserted in tests.

Every bench comes from a plugin (hook ``btforge_bench_commands``), so each stage family owns its own;
``btforge bench`` lists them with their one-line help, ``btforge bench NAME --help`` shows a bench's options.
This module holds what benches share: argument types, printing and writing figures, peak memory, and a
summary of the warnings a bench's internal runs raise.
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import inspect
import json
import re
import sys
import warnings
from pathlib import Path
from typing import Iterator

from .errors import BtforgeInputError, BtforgeWarning
from .profile import peak_rss_mb  # noqa: F401  (benches import it from here)


def add_parser(sub):
    p = sub.add_parser("bench", help="measure speed and memory (benches come from plugins; no NAME lists them)",
                       description="Run a benchmark a plugin contributes; without NAME, list them.")
    p.add_argument("name", nargs="?", help="the bench to run")
    p.add_argument("args", nargs=argparse.REMAINDER, help="the bench's own options (see btforge bench NAME --help)")
    return p


def summary(fn) -> str:
    doc = inspect.getdoc(fn) or ""
    return doc.splitlines()[0] if doc else ""


def main(args) -> int:
    from .registry import default_registry, did_you_mean
    benches = default_registry().bench_commands
    if not args.name:
        if not benches:
            print("no installed plugin contributes a bench")
            return 0
        width = max(len(n) for n in benches)
        for name in sorted(benches):
            print(f"  {name.ljust(width)}  {summary(benches[name])}")
        return 0
    if args.name not in benches:
        raise BtforgeInputError(f"bench '{args.name}'", "is not contributed by any installed plugin",
                                did_you_mean(args.name, benches))
    return int(benches[args.name](list(args.args)) or 0)


# ----------------------------------------------------------------------------------------------- shared helpers


def positive_count(text: str) -> int:
    """An argparse type: an int of at least 1."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a count of at least 1, found {value}")
    return value


def _short(value):
    """Long per-step lists (e.g. the fraction rejected after each projection) at a few steps, for the screen."""
    if isinstance(value, list) and len(value) > 12 and all(isinstance(v, (int, float)) for v in value):
        steps = [k for k in (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024) if k <= len(value)] + [len(value)]
        return "after " + ", ".join(f"{k}: {value[k - 1]}" for k in dict.fromkeys(steps))
    return value


def print_figures(figures: dict, json_path: str | None = None) -> None:
    """Print ``key: value`` lines (long lists shortened) and, with ``json_path``, write all figures as JSON."""
    for key, value in figures.items():
        print(f"  {key}: {_short(value)}")
    write_json(figures, json_path)


def write_json(figures: dict, json_path: str | None) -> None:
    if json_path:
        from .atomic import atomic_write_text
        atomic_write_text(json_path, json.dumps(figures, indent=2, default=str))


def fresh_run(graph, out, *extra: str) -> dict:
    """One ``btforge run GRAPH --no-cache --out OUT [extra]`` in a fresh process, start-up included: ``seconds``
    (wall), ``cpu_seconds`` (user + system, of the process and every process it waited for) and ``peak_rss_mb``
    (of the largest of them; with ``--report`` among ``extra``, the run's own peak from its report: the kernel's
    figure for a child starts from its parent's peak, e.g. a bench that rendered its capture first)."""
    import os
    import subprocess
    import time
    start = time.perf_counter()
    child = subprocess.Popen([sys.executable, "-m", "btforge.cli", "run", str(graph), "--no-cache", "--out", str(out),
                              *extra], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(child.pid, 0)
    seconds = time.perf_counter() - start
    error = child.stderr.read().decode()
    child.stderr.close()
    if os.waitstatus_to_exitcode(status) != 0:
        from .errors import BtforgeError
        raise BtforgeError(f"btforge run {graph} failed:\n{error[-2000:]}")
    peak = usage.ru_maxrss / 1024
    if "--report" in extra:
        report = json.loads(Path(extra[extra.index("--report") + 1]).read_text())
        peak = report.get("startup", {}).get("peak_rss_mb", peak)
    return {"seconds": round(seconds, 2), "cpu_seconds": round(usage.ru_utime + usage.ru_stime, 2),
            "peak_rss_mb": round(peak, 1)}




@contextlib.contextmanager
def counted_warnings(stream=sys.stderr, show: int = 3) -> Iterator[collections.Counter]:
    """Count the warnings raised in the block instead of printing each, and print a summary at the end: the
    ``show`` most frequent kinds (warnings that differ only in their numbers are one kind), with an example
    each.  A bench runs many fits, whose warnings would otherwise flood the screen."""
    counts: collections.Counter = collections.Counter()
    examples: dict[str, str] = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield counts
        finally:
            for w in caught:
                text = str(w.message) if issubclass(w.category, BtforgeWarning) else \
                    f"{w.category.__name__}: {w.message}"
                kind = re.sub(r"\d+(\.\d+)?", "N", text)
                counts[kind] += 1
                examples.setdefault(kind, text)
    if counts:
        total = sum(counts.values())
        print(f"{total} warning{'s' * (total != 1)} during the bench, {len(counts)} kind{'s' * (len(counts) != 1)}; "
              f"the most frequent, with an example:", file=stream)
        for kind, n in counts.most_common(show):
            print(f"  {n} x {examples[kind][:200]}", file=stream)
