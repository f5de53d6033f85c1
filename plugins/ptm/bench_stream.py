"""``btforge bench ptm-stream``: a capture to a ``.ptm`` file, whole process, read-then-fit against fit-while-reading."""
from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
from pathlib import Path

# .ptm files hold display values, so both fit them (auto might choose linear radiance)
GRAPHS = {
    "read then fit": "nodes:\n  read: {{stage: stackio.read, params: {{path: {lp}}}}}\n"
                     "  fit: {{stage: ptm.fit, params: {{variant: {variant}, space: srgb}}, inputs: {{stack: read.stack}}}}\n"
                     "  save: {{stage: ptm.write, params: {{path: out.ptm}}, inputs: {{model: fit.model}}}}\n",
    "fit while reading": "nodes:\n  fit: {{stage: ptm.fit_capture, params: {{path: {lp}, variant: {variant}, space: srgb}}}}\n"
                         "  save: {{stage: ptm.write, params: {{path: out.ptm}}, inputs: {{model: fit.model}}}}\n",
}


def _whole_process(graph: Path, out: Path) -> tuple[float, float]:
    """Seconds and peak resident MB of one fresh ``btforge run`` (start-up, imports and OpenCL included)."""
    from btforge.bench import fresh_run
    figures = fresh_run(graph, out)
    return figures["seconds"], figures["peak_rss_mb"]


def bench_ptm_stream(args: list[str]) -> int:
    """A JPEG capture to a .ptm file in a fresh process: time and peak memory, read-then-fit vs fit-while-reading."""
    parser = argparse.ArgumentParser(prog="btforge bench ptm-stream")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--stack", help="a .lp capture")
    source.add_argument("--synthetic", type=int, metavar="SIZE", help="render a SIZE x SIZE JPEG capture first")
    parser.add_argument("--lights", type=int, default=49, help="lights of the synthetic capture (default 49)")
    parser.add_argument("--variant", default="rgb", choices=("rgb", "lrgb"))
    parser.add_argument("--repeat", type=int, default=3, help="runs of each; medians are reported")
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    options = parser.parse_args(args)
    with tempfile.TemporaryDirectory(prefix="btforge-bench-") as tmp:
        folder = Path(tmp)
        if options.synthetic:
            from .bench import make_synthetic_capture
            lp = make_synthetic_capture(folder, options.synthetic, options.lights)
        else:
            lp = Path(options.stack).resolve()
        figures = {"stack": str(options.stack or f"synthetic {options.synthetic}x{options.synthetic} JPEG"),
                   "lights": options.lights if options.synthetic else None, "variant": options.variant,
                   "repeat": options.repeat, "load": os.getloadavg()[0]}
        outputs = {}
        for label, text in GRAPHS.items():
            graph = folder / f"{label.replace(' ', '_')}.yaml"
            graph.write_text(text.format(lp=json.dumps(str(lp)), variant=options.variant))
            out = folder / label.replace(" ", "_")
            runs = [_whole_process(graph, out) for _ in range(max(1, options.repeat))]
            figures[label] = {"seconds": round(statistics.median(r[0] for r in runs), 3),
                              "peak_rss_mb": round(statistics.median(r[1] for r in runs), 1)}
            outputs[label] = (out / "out.ptm").read_bytes()
        figures["same_ptm_file"] = len(set(outputs.values())) == 1
    print(f"PTM {options.variant} to .ptm, whole process (fresh `btforge run`, medians of {options.repeat}), "
          f"{figures['stack']}, load {figures['load']:.1f}")
    for label in GRAPHS:
        print(f"  {label:18s} {figures[label]['seconds']:7.2f} s   peak {figures[label]['peak_rss_mb']:6.0f} MB")
    print(f"  identical .ptm files: {figures['same_ptm_file']}")
    if options.json:
        from btforge.atomic import atomic_write_text
        atomic_write_text(options.json, json.dumps(figures, indent=2))
    return 0
