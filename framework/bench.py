"""Benchmarks (``btforge bench ...``): measured figures, never asserted in tests.

``btforge bench ptm`` reports, in one run, the PTM fit throughput of the OpenCL kernel and the NumPy reference
on the same stack, and the end-to-end time and peak memory of reading + fitting (measured in a fresh child
process, so the peak is that of the work and not of the benchmark harness).
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .errors import BtforgeError, BtforgeInputError


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a count of at least 1, found {value}")
    return value


def add_parser(sub):
    p = sub.add_parser("bench", help="measure speed and memory")
    which = p.add_subparsers(dest="bench", required=True)
    q = which.add_parser("ptm", help="PTM fit throughput (OpenCL vs NumPy) and read+fit time and peak memory")
    src = q.add_mutually_exclusive_group(required=True)
    src.add_argument("--stack", help="a .lp capture to measure on")
    src.add_argument("--synthetic", type=int, metavar="SIZE",
                     help="render a SIZE x SIZE JPEG capture of the demo material first and measure on it")
    q.add_argument("--lights", type=int, default=49, help="lights of the synthetic capture (default 49)")
    q.add_argument("--variant", default="rgb", choices=("rgb", "lrgb"))
    q.add_argument("--repeat", type=_positive, default=5, help="repetitions; medians are reported")
    q.add_argument("--json", metavar="FILE", help="also write the figures as JSON")

    g = which.add_parser("render", help="one 640 x 480 frame: PTM sphere, directional light + shadows; 64-light environment")
    g.add_argument("--repeat", type=_positive, default=5)
    g.add_argument("--json", metavar="FILE", help="also write the figures as JSON")

    qb = which.add_parser("quilt", help="quilting 512 x 512 from a 128 x 128 9-D PTM exemplar: rejection vs brute force")
    qb.add_argument("--ptm", help="take the exemplar from the centre of this .ptm file (default: random smooth fields)")
    qb.add_argument("--repeat", type=_positive, default=5)
    qb.add_argument("--json", metavar="FILE", help="also write the figures as JSON")

    kb = which.add_parser("kcoherence", help="k-coherence 256 x 256, 3 levels, k = 6, 5 x 5 neighbourhood")
    kb.add_argument("--exemplar-size", type=int, default=64, help="exemplar side in texels (default 64)")
    kb.add_argument("--repeat", type=_positive, default=5)
    kb.add_argument("--json", metavar="FILE", help="also write the figures as JSON")

    y = which.add_parser("synthesis", help="synthesis quality (scores) against time over the synthesizers' knobs")
    y.add_argument("--exemplar", required=True, help="the capture (.lp) whose central crop is the exemplar")
    y.add_argument("--out", required=True, help="folder for synthesis.csv and synthesis.png")
    y.add_argument("--crop", type=int, default=64, help="exemplar size in texels (default 64)")
    y.add_argument("--size", type=int, default=256, help="output size in texels (default 256)")
    y.add_argument("--repeat", type=_positive, default=1, help="runs per configuration; the median time is reported")
    y.add_argument("--only", action="append", help="only these synthesizers (quilt, kcoherence, jumpmap)")

    r = which.add_parser("representations", help="fit time, relight time, size and held-out error of every representation")
    r.add_argument("--stack", required=True, help="the capture to fit (.lp or .lvp)")
    r.add_argument("--test", help="held-out capture at other lights (default: every fifth light of --stack)")
    r.add_argument("--out", required=True, help="folder for representations.csv and representations.png")
    r.add_argument("--crop", type=int, default=0, help="use only the central CROP x CROP texels (0: all)")
    r.add_argument("--repeat", type=_positive, default=1, help="fits per representation; the median time is reported")
    r.add_argument("--only", action="append", help="only these representation families (ptm, lafortune, sh)")
    return p


def make_synthetic_capture(folder: Path, size: int, n_lights: int, quality: int = 95) -> Path:
    """Write a JPEG capture of the procedural demo material with its ``.lp`` file; return the ``.lp`` path."""
    import numpy as np
    from PIL import Image

    from btforge.buffers import linear_to_srgb8
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights
    from btforge.plugins.stackio.lightfile import write_light_file

    material = make_material(size, size, bumps=max(8, size * size // 400), seed=1)
    lights = hemisphere_lights(n_lights, min_elevation_deg=15.0)
    names = []
    for start in range(0, n_lights, 8):  # render a few lights at a time to bound memory
        batch = render_lights(material, lights[start:start + 8])
        for i, image in enumerate(batch, start):
            name = f"light_{i:03d}.jpg"
            Image.fromarray(linear_to_srgb8(image)).save(folder / name, quality=quality)
            names.append(name)
    lp = folder / "dirs.lp"
    write_light_file(lp, names, lights)
    return lp


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM: unlike ru_maxrss it is not inherited from the parent)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    import resource  # not Linux
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _child_read_fit(lp: str, variant: str) -> dict:
    import btforge.plugins.ptm.model as ptm_model
    from btforge.backend import get_backend
    from btforge.plugins.stackio.images import load_stack

    get_backend().kernel(ptm_model.KERNELS, "ptm_project", ("-DSAMPLE_T=uchar",))  # compile outside the timing
    baseline = peak_rss_mb()
    start = time.perf_counter()
    stack = load_stack(Path(lp))
    read = time.perf_counter()
    ptm_model.fit_ptm(stack, variant)
    end = time.perf_counter()
    return {"read_s": read - start, "fit_s": end - read, "total_s": end - start,
            "peak_rss_mb": peak_rss_mb(), "baseline_rss_mb": baseline}


def bench_ptm(args) -> dict:
    from btforge.backend import get_backend
    from btforge.plugins.ptm.model import fit_ptm
    from btforge.plugins.stackio.images import load_stack

    with tempfile.TemporaryDirectory(prefix="btforge-bench-") as tmp:
        if args.synthetic:
            print(f"rendering a {args.synthetic}x{args.synthetic}, {args.lights}-light JPEG capture ...", file=sys.stderr)
            lp = make_synthetic_capture(Path(tmp), args.synthetic, args.lights)
        else:
            lp = Path(args.stack)
        stack = load_stack(lp)  # a bad capture stops here with its own message, not inside a child process
        runs = []
        for _ in range(args.repeat):
            out = subprocess.run([sys.executable, "-m", "btforge.bench", "_read_fit", str(lp), args.variant],
                                 capture_output=True, text=True)
            if out.returncode != 0:
                raise BtforgeError(f"the read+fit process failed on {lp}:\n{out.stderr.strip()[-2000:]}")
            runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        samples = stack.height * stack.width * stack.n_light
        timings = {}
        for engine in ("opencl", "numpy"):
            fit_ptm(stack, args.variant, engine=engine)  # warm-up (kernel build, caches)
            times = []
            for _ in range(args.repeat):
                start = time.perf_counter()
                fit_ptm(stack, args.variant, engine=engine)
                times.append(time.perf_counter() - start)
            timings[engine] = statistics.median(times)
    figures = {
        "stack": str(args.stack or f"synthetic {args.synthetic}x{args.synthetic}"),
        "size": [stack.height, stack.width], "lights": stack.n_light, "variant": args.variant,
        "device": get_backend().description, "repeat": args.repeat,
        "fit_seconds_opencl": timings["opencl"], "fit_seconds_numpy": timings["numpy"],
        "throughput_opencl_texel_lights_per_s": samples / timings["opencl"],
        "throughput_numpy_texel_lights_per_s": samples / timings["numpy"],
        "speedup_opencl_over_numpy": timings["numpy"] / timings["opencl"],
        "read_fit_median_s": statistics.median(r["total_s"] for r in runs),
        "read_median_s": statistics.median(r["read_s"] for r in runs),
        "fit_in_pipeline_median_s": statistics.median(r["fit_s"] for r in runs),
        "peak_rss_median_mb": statistics.median(r["peak_rss_mb"] for r in runs),
        "baseline_rss_median_mb": statistics.median(r["baseline_rss_mb"] for r in runs),
    }
    return figures


# (family, stage, params) of every configuration the representations bench compares.
REPRESENTATIONS = (
    [("ptm", "ptm.fit", {"variant": v}) for v in ("lrgb", "rgb")]
    + [("lafortune", "lafortune.fit", {"lobes": k}) for k in (1, 2, 3, 4)]
    + [("sh", "sh.fit", {"light_order": n}) for n in (2, 3, 4, 5, 6)]
)


def _label(stage: str, params: dict) -> str:
    return stage.split(".")[0] + " " + " ".join(f"{k}={v}" for k, v in params.items())


def _central_crop(stack, size: int):
    from btforge.buffers import SampleStack
    if not size or (stack.height <= size and stack.width <= size):
        return stack
    r0, c0 = max(0, (stack.height - size) // 2), max(0, (stack.width - size) // 2)
    part = stack.samples[:, :, r0:r0 + size, c0:c0 + size]
    return SampleStack(part, stack.lights, stack.views, stack.channels, stack.encoding, stack.names)


def bench_representations(args) -> list[dict]:
    import csv
    import io

    import numpy as np

    from btforge import stage as get_stage
    from btforge.buffers import SampleStack
    from btforge.plugins.relight import compare_stacks
    from btforge.plugins.stackio.images import load_stack
    from btforge.registry import default_registry

    from .atomic import atomic_write_text
    from .plot import scatter_png

    stack = _central_crop(load_stack(Path(args.stack)), args.crop)
    if args.test:
        fit, test = stack, _central_crop(load_stack(Path(args.test)), args.crop)
    else:
        held = np.zeros(stack.n_light, bool)
        held[::5] = True

        def part(mask):
            return SampleStack(stack.samples[:, mask], stack.lights[mask], stack.views, stack.channels, stack.encoding)
        fit, test = part(~held), part(held)
    registered = default_registry().stages
    rows = []
    for family, stage_name, params in REPRESENTATIONS:
        if args.only and family not in args.only:
            continue
        label = _label(stage_name, params)
        if stage_name not in registered:
            print(f"  {label:28s} skipped: stage '{stage_name}' is not installed", file=sys.stderr)
            continue
        if family == "ptm" and fit.n_view > 1:
            print(f"  {label:28s} skipped: a PTM models a single view", file=sys.stderr)
            continue
        if family == "sh" and fit.n_view > 1:  # a BTF: fit over views too, as far as the views can determine
            params = {**params, "view_order": max(1, min(params["light_order"], int(fit.n_view ** 0.5)))}
            label = _label(stage_name, params)
        fit_stage = get_stage(stage_name)
        try:
            fit_stage(stack=_central_crop(fit, 8), **params)  # build kernels outside the timing
        except BtforgeInputError as exc:  # e.g. too few fitting lights for 4 lobes: measure the others
            print(f"  {label:28s} skipped: {exc.problem}", file=sys.stderr)
            continue
        times = []
        for _ in range(max(1, args.repeat)):
            start = time.perf_counter()
            model = fit_stage(stack=fit, **params)["model"]
            times.append(time.perf_counter() - start)
        model.evaluate(test.lights, test.views)  # warm-up: kernel builds for these sizes
        start = time.perf_counter()
        values = model.evaluate(test.lights, test.views)
        relight_s = time.perf_counter() - start
        if values.shape[0] != test.n_view:
            values = np.broadcast_to(values, (test.n_view,) + values.shape[1:])
        predicted = SampleStack(np.ascontiguousarray(values), test.lights, test.views, model.channels)
        scores = compare_stacks(predicted, test)
        megapixels = test.n_view * test.n_light * test.height * test.width / 1e6
        row = {"representation": family, "params": " ".join(f"{k}={v}" for k, v in params.items()),
               "fit_seconds": round(statistics.median(times), 4),
               "relight_seconds_per_megapixel": round(relight_s / megapixels, 5),
               "bytes_per_texel": round(model.nbytes / (model.height * model.width), 2),
               "psnr_db": scores["psnr_db"], "psnr_db_worst_light": scores["psnr_db_worst_light"],
               "max_abs_error": scores["max_abs_error"], "domain": scores["domain"]}
        rows.append(row)
        print(f"  {label:28s} fit {row['fit_seconds']:8.3f} s  relight {row['relight_seconds_per_megapixel']:.4f} s/MP  "
              f"{row['bytes_per_texel']:7.1f} B/texel  PSNR {row['psnr_db']:6.2f} dB", file=sys.stderr)
    out = Path(args.out)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]) if rows else ["representation"])
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(out / "representations.csv", buffer.getvalue())
    scatter_png(out / "representations.png", [r["fit_seconds"] for r in rows], [r["psnr_db"] for r in rows],
                [f"{r['representation']} {r['params']}" for r in rows], [r["representation"] for r in rows],
                title=f"held-out PSNR vs fit time: {args.stack} ({test.width}x{test.height}, "
                      f"{fit.n_view * fit.n_light} fit / {test.n_view * test.n_light} test samples)",
                xlabel="fit seconds", ylabel=f"PSNR dB ({rows[0]['domain'] if rows else ''})")
    return rows


def _short(value):
    """Long per-step lists (e.g. the fraction rejected after each projection) at a few steps, for the screen."""
    if isinstance(value, list) and len(value) > 12 and all(isinstance(v, (int, float)) for v in value):
        steps = [k for k in (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024) if k <= len(value)] + [len(value)]
        return "after " + ", ".join(f"{k}: {value[k - 1]}" for k in dict.fromkeys(steps))
    return value


def _report_plugin_bench(figures: dict, json_path: str | None) -> None:
    for key, value in figures.items():
        print(f"  {key}: {_short(value)}")
    if json_path:
        from .atomic import atomic_write_text
        atomic_write_text(json_path, json.dumps(figures, indent=2, default=str))


def main(args) -> int:
    if args.bench == "render":
        from btforge.plugins.render.bench import benchmark_render
        _report_plugin_bench(benchmark_render(repeat=args.repeat), args.json)
        return 0
    if args.bench == "quilt":
        from btforge.plugins.synth.quilting import benchmark_quilt
        exemplar = None
        if args.ptm:
            from btforge import stage
            exemplar = stage("ptm.read")(path=args.ptm)["model"]
        figures = benchmark_quilt(repeat=args.repeat, exemplar=exemplar)
        _report_plugin_bench(figures, args.json)
        return 0
    if args.bench == "kcoherence":
        from btforge.plugins.synth.kcoherence import benchmark_kcoherence
        _report_plugin_bench(benchmark_kcoherence(args.exemplar_size, repeat=args.repeat), args.json)
        return 0
    if args.bench == "synthesis":
        from btforge.plugins.synth.bench import bench_synthesis
        rows = bench_synthesis(args.exemplar, args.out, crop=args.crop, size=args.size, repeat=args.repeat,
                               only=args.only)
        print(f"wrote {Path(args.out) / 'synthesis.csv'} and synthesis.png ({len(rows)} configurations)")
        return 0
    if args.bench == "representations":
        rows = bench_representations(args)
        print(f"wrote {Path(args.out) / 'representations.csv'} and representations.png ({len(rows)} representations)")
        return 0
    if args.bench == "ptm":
        figures = bench_ptm(args)
        print(f"PTM bench ({figures['variant']}) on {figures['stack']}: {figures['size'][0]}x{figures['size'][1]}, "
              f"{figures['lights']} lights, device {figures['device']}, medians of {figures['repeat']}")
        print(f"  fit throughput  OpenCL {figures['throughput_opencl_texel_lights_per_s'] / 1e6:8.1f} M texel-lights/s"
              f"  ({figures['fit_seconds_opencl']:.3f} s)")
        print(f"  fit throughput  NumPy  {figures['throughput_numpy_texel_lights_per_s'] / 1e6:8.1f} M texel-lights/s"
              f"  ({figures['fit_seconds_numpy']:.3f} s)   OpenCL/NumPy speed-up {figures['speedup_opencl_over_numpy']:.1f}x")
        print(f"  read + fit      {figures['read_fit_median_s']:.3f} s (read {figures['read_median_s']:.3f} s, "
              f"fit {figures['fit_in_pipeline_median_s']:.3f} s), peak RSS {figures['peak_rss_median_mb']:.0f} MB "
              f"(of which {figures['baseline_rss_median_mb']:.0f} MB is the interpreter and libraries)")
        if args.json:
            from .atomic import atomic_write_text
            atomic_write_text(args.json, json.dumps(figures, indent=2))
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "_read_fit":
        print(json.dumps(_child_read_fit(sys.argv[2], sys.argv[3])))
