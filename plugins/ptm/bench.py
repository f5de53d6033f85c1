"""``btforge bench ptm``: PTM fit throughput (OpenCL kernel vs NumPy twin) and read + fit time and peak memory.

The end-to-end read + fit is measured in a fresh child process, so its peak memory is that of the work and not
of the benchmark harness.
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

from btforge.bench import peak_rss_mb, positive_count, write_json
from btforge.errors import BtforgeError


def make_synthetic_capture(folder: Path, size: int, n_lights: int, quality: int = 95) -> Path:
    """Write a JPEG capture of the procedural demo material with its ``.lp`` file; return the ``.lp`` path."""
    from PIL import Image

    from btforge.buffers import linear_to_srgb8
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights
    from btforge.plugins.stackio.lightfile import write_light_file

    folder.mkdir(parents=True, exist_ok=True)
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


def measure_ptm(args) -> dict:
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
            out = subprocess.run([sys.executable, "-m", "btforge.plugins.ptm.bench", "_read_fit", str(lp), args.variant],
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


def bench_ptm(argv: list[str]) -> int:
    """PTM fit throughput (OpenCL vs NumPy) and read+fit time and peak memory."""
    p = argparse.ArgumentParser(prog="btforge bench ptm", description=bench_ptm.__doc__)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--stack", help="a .lp capture to measure on")
    src.add_argument("--synthetic", type=int, metavar="SIZE",
                     help="render a SIZE x SIZE JPEG capture of the demo material first and measure on it")
    p.add_argument("--lights", type=int, default=49, help="lights of the synthetic capture (default 49)")
    p.add_argument("--variant", default="rgb", choices=("rgb", "lrgb"))
    p.add_argument("--repeat", type=positive_count, default=5, help="repetitions; medians are reported")
    p.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = p.parse_args(argv)
    figures = measure_ptm(args)
    print(f"PTM bench ({figures['variant']}) on {figures['stack']}: {figures['size'][0]}x{figures['size'][1]}, "
          f"{figures['lights']} lights, device {figures['device']}, medians of {figures['repeat']}")
    print(f"  fit throughput  OpenCL {figures['throughput_opencl_texel_lights_per_s'] / 1e6:8.1f} M texel-lights/s"
          f"  ({figures['fit_seconds_opencl']:.3f} s)")
    print(f"  fit throughput  NumPy  {figures['throughput_numpy_texel_lights_per_s'] / 1e6:8.1f} M texel-lights/s"
          f"  ({figures['fit_seconds_numpy']:.3f} s)   OpenCL/NumPy speed-up {figures['speedup_opencl_over_numpy']:.1f}x")
    print(f"  read + fit      {figures['read_fit_median_s']:.3f} s (read {figures['read_median_s']:.3f} s, "
          f"fit {figures['fit_in_pipeline_median_s']:.3f} s), peak RSS {figures['peak_rss_median_mb']:.0f} MB "
          f"(of which {figures['baseline_rss_median_mb']:.0f} MB is the interpreter and libraries)")
    write_json(figures, args.json)
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "_read_fit":
        print(json.dumps(_child_read_fit(sys.argv[2], sys.argv[3])))
