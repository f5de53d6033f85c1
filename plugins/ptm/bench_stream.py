"""``btforge bench ptm-stream``: a capture to a ``.ptm`` file, whole process: the ordinary graph streamed (the
default), the same graph with the stack read whole, fit-while-reading, and optionally on a dask cluster."""
from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
from pathlib import Path

# `space` is the fit's default, auto, unless `--space srgb`: fed to ptm.write, auto fits display values as the
# .ptm file holds them (the graph check narrows it), so both give the same graph
ORDINARY = ("nodes:\n  read: {{stage: stackio.read, params: {{path: {lp}}}}}\n"
            "  fit: {{stage: ptm.fit, params: {{variant: {variant}, space: {space}}}, inputs: {{stack: read.stack}}}}\n"
            "  save: {{stage: ptm.write, params: {{path: out.ptm}}, inputs: {{model: fit.model}}}}\n")
CAPTURE = ("nodes:\n  fit: {{stage: ptm.fit_capture, params: {{path: {lp}, variant: {variant}, space: {space}}}}}\n"
           "  save: {{stage: ptm.write, params: {{path: out.ptm}}, inputs: {{model: fit.model}}}}\n")
# label: (graph, extra arguments of `btforge run`); asking for the read's stack as a result keeps it whole
RUNS = {
    "streamed (default)": (ORDINARY, ()),
    "stack read whole": (ORDINARY, ("--only", "read", "--only", "save")),
    "fit while reading": (CAPTURE, ()),
}


def _whole_process(graph: Path, out: Path, extra: tuple[str, ...]) -> dict:
    """Seconds, CPU seconds and peak resident MB of one fresh ``btforge run`` (start-up, imports and OpenCL
    included), and where its fit ran (from the run report)."""
    from btforge.bench import fresh_run
    report = out / "report.json"
    figures = fresh_run(graph, out, *extra, "--report", str(report))
    fit = next(node for node in json.loads(report.read_text())["nodes"] if node["node"] == "fit")
    return {**figures, "fit_placement": fit.get("placement", {}), "fit_space": fit.get("notes", {}).get("space")}


def _medians(runs: list[dict]) -> dict:
    return {"seconds": round(statistics.median(r["seconds"] for r in runs), 3),
            "cpu_seconds": round(statistics.median(r["cpu_seconds"] for r in runs), 3),
            "peak_rss_mb": round(statistics.median(r["peak_rss_mb"] for r in runs), 1),
            "fit_placement": runs[-1]["fit_placement"], "fit_space": runs[-1]["fit_space"]}


def bench_ptm_stream(args: list[str]) -> int:
    """A JPEG capture to a .ptm file in a fresh process: time and peak memory, streamed vs whole vs fit-while-reading."""
    parser = argparse.ArgumentParser(prog="btforge bench ptm-stream")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--stack", help="a .lp capture")
    source.add_argument("--synthetic", type=int, metavar="SIZE", help="render a SIZE x SIZE JPEG capture first")
    parser.add_argument("--lights", type=int, default=49, help="lights of the synthetic capture (default 49)")
    parser.add_argument("--variant", default="rgb", choices=("rgb", "lrgb"))
    parser.add_argument("--space", default="auto", choices=("auto", "srgb"),
                        help="ptm.fit's space (auto: ptm.fit's default, which the graph check narrows to srgb for "
                             "ptm.write: a .ptm file holds display values)")
    parser.add_argument("--repeat", type=int, default=3, help="runs of each; medians are reported")
    parser.add_argument("--scheduler", metavar="dask|tcp://HOST:PORT",
                        help="also run the ordinary graph with this --scheduler (its fit on the cluster's workers)")
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    options = parser.parse_args(args)
    runs = dict(RUNS)
    if options.scheduler:
        runs[f"on {options.scheduler}"] = (ORDINARY, ("--scheduler", options.scheduler))
    with tempfile.TemporaryDirectory(prefix="btforge-bench-") as tmp:
        folder = Path(tmp)
        if options.synthetic:
            from .bench import make_synthetic_capture
            lp = make_synthetic_capture(folder, options.synthetic, options.lights)
        else:
            lp = Path(options.stack).resolve()
        figures = {"stack": str(options.stack or f"synthetic {options.synthetic}x{options.synthetic} JPEG"),
                   "lights": options.lights if options.synthetic else None, "variant": options.variant,
                   "space": options.space,
                   "repeat": options.repeat, "load": os.getloadavg()[0]}
        outputs = {}
        for index, (label, (text, extra)) in enumerate(runs.items()):
            graph = folder / f"graph{index}.yaml"
            graph.write_text(text.format(lp=json.dumps(str(lp)), variant=options.variant, space=options.space))
            out = folder / f"out{index}"
            figures[label] = _medians([_whole_process(graph, out, extra) for _ in range(max(1, options.repeat))])
            outputs[label] = (out / "out.ptm").read_bytes()
        figures["same_ptm_file"] = len(set(outputs.values())) == 1
    _print(figures, runs, options)
    if options.json:
        from btforge.atomic import atomic_write_text
        atomic_write_text(options.json, json.dumps(figures, indent=2))
    return 0


def _print(figures: dict, runs: dict, options) -> None:
    print(f"PTM {options.variant} (space {options.space}) to .ptm, whole process (fresh `btforge run`, medians of {options.repeat}), "
          f"{figures['stack']}, load {figures['load']:.1f}")
    for label in runs:
        row = figures[label]
        print(f"  {label:22s} {row['seconds']:7.2f} s  cpu {row['cpu_seconds']:6.2f} s  peak "
              f"{row['peak_rss_mb']:6.0f} MB   fit: space {row['fit_space']}, {row['fit_placement']}")
    print(f"  identical .ptm files: {figures['same_ptm_file']}")
