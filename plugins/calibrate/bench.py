"""``btforge bench calibrate``: angular error of the calibrated lights against known ones, and the time taken."""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from .lights import calibrate, image_list, load_luminance, parse_focal, parse_principal
from .sphere import Circle, _axis_toward, measure_stretch, outline_stretch, reflect
from .testing import fibonacci_lights, render_capture


def _angles(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def implied_sphere(highlights_xy: np.ndarray, lights: np.ndarray) -> tuple[Circle, float]:
    """The orthographic mirror sphere that best places known ``lights`` [N, 3] at the highlights [N, 2] (column,
    row), and the RMS distance in pixels of the highlights from where that sphere puts them.

    A light ``l`` shines at the normal ``n = (l + v) / |l + v|`` (view ``v = (0, 0, 1)``), seen at column
    ``x + r n_x`` and row ``y - r n_y``: linear in the centre and radius.  Comparing this circle with the one the
    outline gives separates the error of the highlights from that of the sphere's circle (or of the lights' frame).
    """
    normal = lights / np.linalg.norm(lights, axis=1, keepdims=True) + [0.0, 0.0, 1.0]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    n = len(normal)
    design = np.block([[np.ones((n, 1)), np.zeros((n, 1)), normal[:, :1]],
                       [np.zeros((n, 1)), np.ones((n, 1)), -normal[:, 1:2]]])
    target = np.concatenate([highlights_xy[:, 0], highlights_xy[:, 1]])
    (x, y, r), *_ = np.linalg.lstsq(design, target, rcond=None)
    rms = float(np.sqrt(np.mean((design @ [x, y, r] - target) ** 2)))
    return Circle(float(x), float(y), float(r)), rms


def implied_camera(highlights_xy: np.ndarray, lights: np.ndarray, circle: Circle, shape) -> tuple[float, tuple]:
    """The pinhole camera (focal length and principal point, pixels) that best turns the highlights on ``circle``
    into the known ``lights`` [N, 3], from several starting focal lengths."""
    from scipy.optimize import least_squares

    def mismatch(p):
        return (reflect(highlights_xy, circle, shape, p[0], (p[1], p[2])) - lights).ravel()

    centre = ((shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0)
    fits = [least_squares(mismatch, [f, *centre], bounds=([20.0, -5e3, -5e3], [1e6, 5e3, 5e3]))
            for f in (0.5 * max(shape), 2.0 * max(shape), 8.0 * max(shape))]
    best = min(fits, key=lambda fit: fit.cost)
    return float(best.x[0]), (float(best.x[1]), float(best.x[2]))


def bench_calibrate(args: list[str]) -> int:
    """Light calibration accuracy (degrees against known lights) and time, on a capture or rendered spheres."""
    parser = argparse.ArgumentParser(prog="btforge bench calibrate")
    parser.add_argument("images", nargs="?", help="folder or glob of the sphere photographs")
    parser.add_argument("--truth", help="known lights: a text file with a count line, then one 'x y z' row per image")
    parser.add_argument("--synthetic", type=int, metavar="N", help="render N lights on two spheres (JPEG q80)")
    parser.add_argument("--width", type=int, default=320, help="rendered image width (height: 3/4 of it)")
    parser.add_argument("--render-focal", type=float, metavar="PIXELS",
                        help="render through a pinhole of this focal length (principal point at the centre)")
    parser.add_argument("--focal", type=parse_focal, help="perspective camera focal length in pixels, or 'auto'")
    parser.add_argument("--principal", metavar="X,Y", help="its principal point (default: the image centre)")
    opts = parser.parse_args(args)
    with tempfile.TemporaryDirectory() as scratch:
        if opts.synthetic:
            truth = fibonacci_lights(opts.synthetic)
            k = opts.width / 320.0
            render_capture(Path(scratch), truth, [(110 * k, 90 * k, 42 * k), (230 * k, 100 * k, 36 * k)],
                           size=(opts.width * 3 // 4, opts.width), focal=opts.render_focal)
            files = image_list(scratch)
        else:
            files = image_list(opts.images)
            truth = np.loadtxt(opts.truth, skiprows=1) if opts.truth else None
        start = time.perf_counter()
        principal = parse_principal(opts.principal) if opts.principal else None
        result = calibrate(files, focal=opts.focal, principal=principal)
        seconds = time.perf_counter() - start
    size = f"{len(files)} images of {result.shape[1]} x {result.shape[0]}"
    print("spheres: " + "; ".join(f"({c.x:.1f}, {c.y:.1f}) r {c.r:.1f}" for c in result.spheres))
    print(f"{size}: {seconds:.2f} s, {int(result.found.sum())} lights found; camera: "
          + ("orthographic" if result.focal is None else f"pinhole, focal length {result.focal:.1f} px"))
    if truth is not None:
        error = _angles(result.lights, truth / np.linalg.norm(truth, axis=1, keepdims=True))
        print("error per image (deg): " + " ".join(f"{e:.2f}" for e in error))
        print(f"mean {np.nanmean(error):.2f} deg, worst {np.nanmax(error):.2f} deg")
        _print_implied_spheres(result, truth)
        if not opts.synthetic and opts.focal is None:
            _print_implied_camera(result, truth, files)
    return 0


def _print_implied_spheres(result, truth) -> None:
    """Per sphere: the circle the known lights imply for the highlights found, and the error that circle gives."""
    truth = truth / np.linalg.norm(truth, axis=1, keepdims=True)
    for s, (circle, highlights) in enumerate(zip(result.spheres, result.highlights)):
        found = np.array([h.found for h in highlights])
        if found.sum() < 3:
            continue
        xy = np.array([[h.x, h.y] for h in highlights])[found]
        implied, rms = implied_sphere(xy, truth[found])
        error = _angles(reflect(xy, implied, result.shape), truth[found])
        print(f"sphere {s + 1}: the known lights imply ({implied.x:.1f}, {implied.y:.1f}) r {implied.r:.1f} "
              f"(found ({circle.x:.1f}, {circle.y:.1f}) r {circle.r:.1f}); highlights {rms:.2f} px RMS from it; "
              f"with it: mean {error.mean():.2f} deg, worst {error.max():.2f} deg")


def _print_implied_camera(result, truth, files) -> None:
    """The pinhole camera the known lights imply for the first sphere, and whether its outline could show it."""
    truth = truth / np.linalg.norm(truth, axis=1, keepdims=True)
    circle, highlights = result.spheres[0], result.highlights[0]
    found = np.array([h.found for h in highlights])
    if found.sum() < 4:
        return
    xy = np.array([[h.x, h.y] for h in highlights])[found]
    focal, principal = implied_camera(xy, truth[found], circle, result.shape)
    error = _angles(reflect(xy, circle, result.shape, focal, principal), truth[found])
    median = np.median(load_luminance(files), axis=0)
    seen, se, direction = measure_stretch(circle, median)
    toward = _axis_toward(circle, principal)
    print(f"sphere 1: the known lights imply a pinhole camera of focal {focal:.0f} px, principal point "
          f"({principal[0]:.1f}, {principal[1]:.1f}): mean {error.mean():.2f} deg, worst {error.max():.2f} deg; its "
          f"outline would be {outline_stretch(circle, focal, principal):.2f} px longer along {toward:.0f} deg than "
          f"across; the median image's outline is {seen:.2f} +- {se:.2f} px longer along {direction:.0f} deg")
