"""``btforge bench neural``: relighting time of ``neural.fit`` models per megapixel of relit images (texels x
lights, as ``btforge bench representations`` counts), OpenCL kernel against its NumPy twin, for the harmonics
decoder (the default) and NeuralRTI's light decoder."""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from btforge.bench import positive_count, write_json

DECODERS = {"harmonics": {}, "light": {"decoder": "light", "light_order": 0}}   # as the representations bench


def _time(model, lights, engine: str, repeat: int) -> tuple[float, float, np.ndarray]:
    """Median CPU and wall seconds of ``repeat`` relightings, after one untimed (kernel builds)."""
    out = model.evaluate(lights, engine=engine)
    cpu, wall = [], []
    for _ in range(repeat):
        c, w = time.process_time(), time.perf_counter()
        model.evaluate(lights, engine=engine)
        cpu.append(time.process_time() - c)
        wall.append(time.perf_counter() - w)
    return statistics.median(cpu), statistics.median(wall), out


def bench_neural(args: list[str]) -> int:
    """Relight time per megapixel of neural.fit models (both decoders), OpenCL against NumPy."""
    import btforge
    from btforge.plugins.stackio.images import load_stack
    parser = argparse.ArgumentParser(prog="btforge bench neural")
    parser.add_argument("capture", help="a capture's light file (.lp): its models are fitted, then relit")
    parser.add_argument("--lights", type=positive_count, default=10, help="lights per relighting (default 10)")
    parser.add_argument("--repeat", type=positive_count, default=5, help="timed relightings per engine (median)")
    parser.add_argument("--epochs", type=positive_count, default=2,
                        help="training epochs (default 2: the time of a relighting depends on the network's "
                        "sizes, not on how well it was trained)")
    parser.add_argument("--json", help="also write the figures to this file")
    opts = parser.parse_args(args)
    stack = load_stack(opts.capture)
    rng = np.random.default_rng(0)
    z = rng.uniform(0.2, 1.0, opts.lights)
    phi = rng.uniform(0, 2 * np.pi, opts.lights)
    lights = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    megapixels = opts.lights * stack.height * stack.width / 1e6   # of relit images
    figures = {"size": [stack.height, stack.width], "lights": opts.lights}
    for name, params in DECODERS.items():
        model = btforge.stage("neural.fit")(stack=stack, epochs=opts.epochs, **params)["model"]
        row = {}
        for engine in ("numpy", "opencl"):
            cpu, wall, row[engine + "_out"] = _time(model, lights, engine, opts.repeat)
            row[engine] = {"cpu_s_per_mp": cpu / megapixels, "wall_s_per_mp": wall / megapixels}
        diff = float(np.abs(row.pop("numpy_out") - row.pop("opencl_out")).max())
        figures[name] = {**row, "max_abs_difference": diff}
        print(f"{name} decoder, layers {model.layer_sizes}, {stack.height} x {stack.width} at {opts.lights} lights: "
              f"NumPy {row['numpy']['cpu_s_per_mp']:.3f} s CPU / {row['numpy']['wall_s_per_mp']:.3f} s wall per "
              f"relit megapixel, OpenCL {row['opencl']['cpu_s_per_mp']:.3f} s CPU / {row['opencl']['wall_s_per_mp']:.3f} "
              f"s wall (medians of {opts.repeat}); largest difference {diff:.1e}")
    write_json(figures, opts.json)
    return 0
