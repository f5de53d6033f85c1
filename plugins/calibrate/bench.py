"""``btforge bench calibrate``: angular error of the calibrated lights against known ones, and the time taken."""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from .lights import calibrate, image_list
from .synthetic import fibonacci_lights, render_capture


def _angles(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def bench_calibrate(args: list[str]) -> int:
    """Light calibration accuracy (degrees against known lights) and time, on a capture or rendered spheres."""
    parser = argparse.ArgumentParser(prog="btforge bench calibrate")
    parser.add_argument("images", nargs="?", help="folder or glob of the sphere photographs")
    parser.add_argument("--truth", help="known lights: a text file with a count line, then one 'x y z' row per image")
    parser.add_argument("--synthetic", type=int, metavar="N", help="render N lights on two spheres (JPEG q80)")
    parser.add_argument("--width", type=int, default=320, help="rendered image width (height: 3/4 of it)")
    parser.add_argument("--focal", type=float)
    opts = parser.parse_args(args)
    with tempfile.TemporaryDirectory() as scratch:
        if opts.synthetic:
            truth = fibonacci_lights(opts.synthetic)
            k = opts.width / 320.0
            render_capture(Path(scratch), truth, [(110 * k, 90 * k, 42 * k), (230 * k, 100 * k, 36 * k)],
                           size=(opts.width * 3 // 4, opts.width))
            files = image_list(scratch)
        else:
            files = image_list(opts.images)
            truth = np.loadtxt(opts.truth, skiprows=1) if opts.truth else None
        start = time.perf_counter()
        result = calibrate(files, focal=opts.focal)
        seconds = time.perf_counter() - start
    size = f"{len(files)} images of {result.shape[1]} x {result.shape[0]}"
    print(f"spheres: " + "; ".join(f"({c.x:.1f}, {c.y:.1f}) r {c.r:.1f}" for c in result.spheres))
    print(f"{size}: {seconds:.2f} s, {int(result.found.sum())} lights found")
    if truth is not None:
        error = _angles(result.lights, truth / np.linalg.norm(truth, axis=1, keepdims=True))
        print("error per image (deg): " + " ".join(f"{e:.2f}" for e in error))
        print(f"mean {np.nanmean(error):.2f} deg, worst {np.nanmax(error):.2f} deg")
    return 0
