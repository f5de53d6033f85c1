"""``btforge bench btf-store``: a synthetic BTF rendered into a store, then double SH fitted from it, whole process."""
from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

import numpy as np

MAKE = "nodes:\n  btf: {{stage: demo.btf, params: {{size: [{size}, {size}], lights: {lights}, views: {views}, " \
       "store: {store}, block: [8, 8]}}}}\n"
# An explicit space and smoothness: `auto` judges them on a sample of all texels, which no single dask task sees.
FIT = "nodes:\n  read: {{stage: stackio.read, params: {{path: {store}}}}}\n" \
      "  fit: {{stage: sh.fit, params: {{light_order: {order}, view_order: {order}, space: srgb, smoothness: 0}}, " \
      "inputs: {{stack: read.stack}}}}\n" \
      "  save: {{stage: models.write, params: {{path: sh.btfm}}, inputs: {{model: fit.model}}}}\n"


def _node_seconds(report: Path, node: str) -> float:
    entries = json.loads(report.read_text())["nodes"]
    return round(next(e["seconds"] for e in entries if e["node"] == node), 2)


def _largest_difference(first: Path, second: Path) -> float:
    from btforge.plugins.models.modelfile import read_model
    from btforge.registry import default_registry
    types = default_registry().types
    a, b = read_model(first, types), read_model(second, types)
    return float(np.abs(a.coeffs - b.coeffs).max())


def bench_btf_store(args: list[str]) -> int:
    """A synthetic BTF into a store (demo.btf), then double SH from it: whole-process time, CPU and peak memory."""
    from btforge.bench import fresh_run, write_json
    parser = argparse.ArgumentParser(prog="btforge bench btf-store")
    parser.add_argument("--size", type=int, default=256, help="texels per side (default 256; 128 for a quicker run)")
    parser.add_argument("--lights", type=int, default=81)
    parser.add_argument("--views", type=int, default=81)
    parser.add_argument("--order", type=int, default=5, help="SH order over light and view (5: 25 x 25 coefficients)")
    parser.add_argument("--store", help="the store to use, rendered first when absent (default: a temporary one)")
    parser.add_argument("--dask", action="store_true", help="also fit with --scheduler dask (2-worker LocalCluster) "
                        "and compare the coefficients")
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    options = parser.parse_args(args)
    with tempfile.TemporaryDirectory(prefix="btforge-bench-") as tmp:
        folder = Path(tmp)
        store = Path(options.store).resolve() if options.store else folder / "btf.zarr"
        size = f"{options.size}^2 x {options.lights} lights x {options.views} views"
        figures: dict = {"btf": size, "sh": f"{options.order ** 2} x {options.order ** 2}", "load_before": os.getloadavg()[0]}
        if not store.exists():
            graph = folder / "make.yaml"
            graph.write_text(MAKE.format(size=options.size, lights=options.lights, views=options.views,
                                         store=json.dumps(str(store))))
            figures["render into store"] = fresh_run(graph, folder / "make")
        graph = folder / "fit.yaml"
        graph.write_text(FIT.format(store=json.dumps(str(store)), order=options.order))
        runs = {"sh fit, local": ()}
        if options.dask:
            runs["sh fit, dask"] = ("--scheduler", "dask")
        for label, extra in runs.items():
            out = folder / label.split()[-1]
            report = folder / f"{out.name}.json"
            figures[label] = fresh_run(graph, out, "--report", str(report), *extra)
            figures[label]["fit_node_seconds"] = _node_seconds(report, "fit")
        if options.dask:
            figures["largest coefficient difference, dask - local"] = _largest_difference(
                folder / "local" / "sh.btfm", folder / "dask" / "sh.btfm")
        figures["load_after"] = os.getloadavg()[0]
    print(f"btf-store: {size}, double SH {figures['sh']} (load {figures['load_before']:.1f} -> "
          f"{figures['load_after']:.1f})")
    for label, value in figures.items():
        if isinstance(value, dict):
            node = f", fit node {value['fit_node_seconds']:.1f} s" if "fit_node_seconds" in value else ""
            print(f"  {label:18s} {value['seconds']:7.1f} s wall, {value['cpu_seconds']:7.1f} s CPU, "
                  f"peak {value['peak_rss_mb']:6.0f} MB{node}")
    if options.dask:
        print(f"  largest coefficient difference, dask - local: {figures['largest coefficient difference, dask - local']:.3g}")
    write_json(figures, options.json)
    return 0
