"""Render benchmark: ``python -m btforge.plugins.render.bench`` prints the figures of :func:`benchmark_render`."""
from __future__ import annotations

import json
import statistics
import time

import numpy as np


def bench_material(size: int = 256):
    """A PTM fitted to the procedural demo material (``size`` x ``size``, 36 lights)."""
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights
    from btforge.buffers import SampleStack
    from btforge.plugins.ptm.model import fit_ptm

    material = make_material(size, size, bumps=60, seed=1)
    lights = hemisphere_lights(36, min_elevation_deg=15.0)
    stack = SampleStack(render_lights(material, lights)[None], lights, np.array([[0.0, 0.0, 1.0]]))
    return fit_ptm(stack, "rgb")[0]


def bench_scene(environment: bool, width: int = 640, height: int = 480, samples: int = 64) -> dict:
    """A PTM sphere resting on a grey ground plane (which receives its shadow), seen in perspective."""
    lights = [{"type": "directional", "direction": [0.5, 0.4, 0.77], "intensity": 1.0}]
    effects = ["shadows", "tonemap"]
    if environment:
        lights = [{"type": "environment", "sky": {"sun": [0.5, 0.4, 0.77], "sun_intensity": 30.0}, "samples": samples}]
        effects.append("environment")
    return {
        "camera": {"type": "perspective", "width": width, "height": height, "position": [0, -4.2, 2.2],
                   "look_at": [0, 0, 0.6], "up": [0, 0, 1], "fov": 45},
        "meshes": {
            "ball": {"primitive": "sphere", "radius": 1.0, "position": [0, 0, 1.0], "rotate": [90, 0, 0],
                     "material": "stone", "uv_scale": [2, 1]},
            "ground": {"primitive": "plane", "size": 8.0, "color": [0.5, 0.5, 0.5]},
        },
        "lights": lights,
        "effects": effects,
    }


def benchmark_render(repeat: int = 5) -> dict:
    """Median wall time of one 640 x 480 frame: a PTM sphere (on a ground plane) under one directional light with
    shadows, and under a 64-light importance-sampled environment with shadows.  Also the counts of one run."""
    from btforge.backend import get_backend
    from btforge.stages import RunPaths
    from pathlib import Path

    from .renderer import Counters, render
    from .loader import load_scene

    model = bench_material()
    paths = RunPaths(Path.cwd(), Path.cwd())
    figures: dict = {"device": get_backend().description, "repeat": repeat, "size": [480, 640]}
    for label, env in (("directional_shadows", False), ("environment64_shadows", True)):
        scene = load_scene(bench_scene(env), paths)
        render(scene, {"stone": model})  # warm-up: kernel build, open3d import
        times = []
        for _ in range(repeat):
            counters = Counters()
            start = time.perf_counter()
            render(scene, {"stone": model}, counters)
            times.append(time.perf_counter() - start)
        figures[f"{label}_median_s"] = round(statistics.median(times), 4)
        figures[f"{label}_passes"] = counters.passes
    return figures



def bench_render(argv: list[str]) -> int:
    """One 640 x 480 frame: PTM sphere, directional light + shadows; 64-light environment."""
    import argparse

    from btforge.bench import positive_count, print_figures
    p = argparse.ArgumentParser(prog="btforge bench render", description=bench_render.__doc__)
    p.add_argument("--repeat", type=positive_count, default=5)
    p.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = p.parse_args(argv)
    print_figures(benchmark_render(repeat=args.repeat), args.json)
    return 0


if __name__ == "__main__":
    print(json.dumps(benchmark_render(), indent=2))
