"""``btforge bench liu``: each step of geometry-guided BTF synthesis, timed on built-in procedural data."""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import sys
import time

import numpy as np


_CPU: list[float] = []  # CPU seconds (all threads, OpenCL's included) of the last measurement


def _median_seconds(fn, repeat: int):
    """Median wall seconds of ``repeat`` calls and the last result; the median CPU seconds go to ``_CPU`` (on a
    shared machine CPU time is the steadier figure: wall time also counts the waits for other processes)."""
    times, cpu, result = [], [], None
    for _ in range(repeat):
        start, start_cpu = time.perf_counter(), time.process_time()
        result = fn()
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    _CPU[:] = [statistics.median(cpu)]
    return statistics.median(times), result


def height_statistics(field) -> dict:
    """Height spread, slope RMS and 1/e correlation length (texels) of a height field, for comparing
    synthesized fields with their exemplar."""
    z = field.heights.astype(np.float64)
    z = z - z.mean()
    p, q = field.slopes()
    spectrum = np.abs(np.fft.fft2(z)) ** 2
    corr = np.real(np.fft.ifft2(spectrum))[0] / max(float(spectrum.sum() / z.size), 1e-12)
    below = np.flatnonzero(corr[: z.shape[1] // 2] < np.exp(-1))
    return {"height_std": float(z.std()), "slope_rms": float(np.sqrt((p * p + q * q).mean())),
            "correlation_length": float(below[0]) if below.size else float(z.shape[1] // 2)}


def _row(table, step, size, seconds, extra=""):
    cpu = _CPU[0] if _CPU else float("nan")
    _CPU.clear()
    table.append({"step": step, "size": size, "seconds": round(seconds, 4), "cpu_seconds": round(cpu, 4),
                  "notes": extra})
    print(f"{step:<40} {size:<30} {seconds:>8.3f} s wall {cpu:>8.3f} s cpu  {extra}")


def bench_liu(args: list[str]) -> int:
    """Time each step of Liu et al.'s BTF synthesis: height from shading and synthesis, templates, images, IoU, grid."""
    from btforge import SampleStack
    from btforge.plugins.height.testing import known_capture
    from btforge.plugins.liu import settings

    parser = argparse.ArgumentParser(prog="btforge bench liu", description=bench_liu.__doc__)
    parser.add_argument("--size", type=int, default=256, help="side of the height field and images (default 256)")
    parser.add_argument("--lights", type=int, default=48, help="images for height from shading (default 48)")
    parser.add_argument("--repeat", type=int, default=3, help="repetitions; medians are reported (default 3)")
    parser.add_argument("--grid", action="store_true", help="also synthesize the paper's 5 x 12 x 5 x 12 grid")
    parser.add_argument("--grid-size", type=int, default=128, help="image side for --grid (default 128)")
    parser.add_argument("--grid-views", type=int, default=60, help="synthesize only N of the grid's 60 views, "
                        "spread over it (the time is also given scaled to the whole grid; default 60)")
    parser.add_argument("--grid-out", metavar="DIR", help="folder for --grid's memory-mapped output (a temporary "
                        "folder inside it, removed afterwards; default: the system's temporary folder)")
    parser.add_argument("--skip-steps", action="store_true", help="with --grid: time only the grid")
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    opts = parser.parse_args(args)
    if opts.repeat < 1 or opts.size < 64 or opts.lights < 3:
        print("btforge bench liu: expected --repeat >= 1, --size >= 64 (k-coherence needs a 32^2 exemplar) and "
              "--lights >= 3", file=sys.stderr)
        return 2
    n, table = opts.size, []
    capture = known_capture(size=n, lights=opts.lights, specular=0.6, bump_height=6.0, bumps=n * n // 300)
    ref_lights = np.array([settings.direction(t, a) for t in (45, 65) for a in range(0, 360, 45)], np.float32)
    refs = SampleStack(_render_refs(capture, ref_lights)[None], ref_lights, [[0.0, 0.0, 1.0]])
    if not opts.skip_steps:
        _steps(table, opts, capture, refs)
    if opts.grid:
        _grid(table, opts, capture, refs)
    if opts.json:
        from btforge.atomic import atomic_write_text
        atomic_write_text(opts.json, json.dumps(table, indent=2))
    return 0


def _steps(table, opts, capture, refs):
    """Every step but the grid: height from shading, height synthesis, templates, one image, shadow IoU."""
    from btforge import SampleStack, stage
    from btforge.plugins.height.field import HeightField
    from btforge.plugins.height.sfs import photometric_stereo_ls
    from btforge.plugins.height.testing import angular_error_degrees
    from btforge.plugins.liu import settings, synthesis, template
    from btforge.plugins.liu import testing as consistency
    n = opts.size
    stack = SampleStack(capture.images[None], capture.lights, [[0.0, 0.0, 1.0]])
    seconds, out = _median_seconds(lambda: stage("height.from_shading")(stack=stack), opts.repeat)
    error = angular_error_degrees(out["height"].normals, capture.normals)
    ls_error = angular_error_degrees(photometric_stereo_ls(capture.images.mean(3), capture.lights)[0], capture.normals)
    _row(table, "height.from_shading (glossy, shadowed)", f"{n}^2 x {opts.lights} images", seconds,
         f"normal error mean {error.mean():.2f} / median {np.median(error):.2f} deg; least-squares PS "
         f"{ls_error.mean():.2f} / {np.median(ls_error):.2f}")
    recovered = out["height"]

    exemplar = stage("synth.crop")(input=recovered, origin=[0, 0], size=[n // 2, n // 2])["output"]
    reference_stats = height_statistics(exemplar)
    for name, params in (("synth.quilt", {"block": max(8, n // 8), "wrap": True}),
                         ("synth.kcoherence", {"wrap": True}), ("synth.jumpmap", {})):
        seconds, field = _median_seconds(lambda: stage("synth.materialize")(
            coords=stage(name)(exemplar=exemplar, size=[n, n], seed=1, **params)["coords"], source=exemplar)["output"], 1)
        s = height_statistics(field)
        ratios = ", ".join(f"{k} x{s[k] / max(reference_stats[k], 1e-12):.2f}" for k in s)
        _row(table, f"height synthesis 2x: {name}", f"{n // 2}^2 -> {n}^2", seconds, ratios)

    truth = HeightField.from_height(capture.heights, capture.images.max(0), wrap=True)
    view, light = np.float32([[0.34, 0.0, 0.94]]), np.float32([settings.direction(65, 30)])
    args_t = (truth.heights, synthesis.grey_albedo(truth), truth.normals, view, light)
    template.render(*args_t)
    seconds, _ = _median_seconds(lambda: template.render(*args_t), opts.repeat)
    _row(table, "template (OpenCL)", f"{n}^2, 1 setting", seconds)
    seconds, _ = _median_seconds(lambda: template.render_numpy(*args_t), 1)
    _row(table, "template (NumPy twin)", f"{n}^2, 1 setting", seconds)

    for m in (1, 3):
        def one_image(m=m):
            images, _ = template.render(truth.heights, synthesis.grey_albedo(truth), truth.normals, view, light)
            views, lights, pairs = synthesis.reference_table(refs)
            choice = synthesis.choose_references(view[0], light[0], views, lights, m, True)
            return synthesis.synthesize_image(images[0], refs, choice, pairs, (3, 5, 9), 0)
        seconds, _ = _median_seconds(one_image, opts.repeat)
        _row(table, f"one BTF image, M = {m} references", f"{n}^2 (template + warp + copy)", seconds)

    for tilts in ((70, 75), (45, 60)):
        start, start_cpu = time.perf_counter(), time.process_time()
        result = consistency.measure(tilts=tilts, baseline=tilts == (70, 75))
        seconds, _CPU[:] = time.perf_counter() - start, [time.process_time() - start_cpu]
        base = f", per-light 2D quilting {result.per_light_2d.mean():.3f}" if result.per_light_2d.size else ""
        _row(table, f"shadow IoU, lights at tilts {tilts[0]}, {tilts[1]}",
             f"112^2, {len(result.liu)} lights (2 tilts x 6 az.)", seconds,
             f"IoU mean {result.liu.mean():.3f} (min {result.liu.min():.3f}) over {len(result.liu)} lights, "
             f"shadowed {100 * result.shadow_fraction.mean():.1f} % of the template{base}")


def _grid(table, opts, capture, refs):
    """The paper's 5 x 12 x 5 x 12 grid of ``--grid-size`` images, streamed into memory-mapped ``.npy`` files."""
    import tempfile

    from btforge.plugins.height.field import HeightField
    from btforge.plugins.liu import settings, synthesis
    g = opts.grid_size
    small = HeightField.from_height(capture.heights[:g, :g], capture.images.max(0)[:g, :g], wrap=False)
    grid = {"view_tilts": [0, 15, 30, 45, 60], "view_azimuths": list(range(0, 360, 30)),
            "light_tilts": [0, 15, 30, 45, 60], "light_azimuths": list(range(0, 360, 30))}
    views, lights = settings.parse_grid(grid)
    unique_total = len(set(synthesis.first_equal(views))) * len(set(synthesis.first_equal(lights)))
    pick = np.unique(np.linspace(0, len(views) - 1, max(1, min(opts.grid_views, len(views)))).round().astype(int))
    views = views[pick]                        # views spread over the grid (its tilt-0 rows are all one view)
    synthesized, marks = [], []

    def progress(v, l):
        synthesized.append((v, l))
        if l == len(lights) - 1:
            marks.append(_rss_mb())
    with tempfile.TemporaryDirectory(dir=opts.grid_out) as folder:
        # the output streams to disk: memory-mapped .npy files the size of the whole grid
        out_stack = np.lib.format.open_memmap(f"{folder}/stack.npy", "w+", np.float32,
                                              (len(views), len(lights), g, g, 3))
        out_templates = np.lib.format.open_memmap(f"{folder}/templates.npy", "w+", np.float32,
                                                  (len(views), len(lights), g, g, 1))
        rss_before = _rss_mb()
        start, start_cpu = time.perf_counter(), time.process_time()
        synthesis.synthesize(small, refs, views, lights, count=1, out=out_stack, templates_out=out_templates,
                             progress=progress)
        out_stack.flush()
        out_templates.flush()
        seconds = time.perf_counter() - start
        _CPU[:] = [time.process_time() - start_cpu]
        gigabytes = (out_stack.nbytes + out_templates.nbytes) / 1e9
        del out_stack, out_templates
    done = len(synthesized)
    whole = "" if done == unique_total else f"{seconds * unique_total / done / 60:.1f} min scaled to the whole grid; "
    _row(table, "grid 5 x 12 x 5 x 12, M = 1", f"{done} of its {unique_total} distinct images of {g}^2", seconds,
         f"{seconds / 60:.1f} min; {whole}{1000 * seconds / done:.0f} ms per image; output {gigabytes:.2f} GB "
         f"memory-mapped; anonymous resident memory {rss_before:.0f} MB before, after each view "
         f"{min(marks):.0f}-{max(marks):.0f} MB (first {marks[0]:.0f}, last {marks[-1]:.0f})")


def _rss_mb() -> float:
    """The process's anonymous resident memory now (not its peak, and without memory-mapped files), in MB."""
    try:
        with open("/proc/self/status") as status:
            return next(int(line.split()[1]) for line in status if line.startswith("RssAnon")) / 1024
    except (OSError, StopIteration):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _render_refs(capture, lights):
    """The capture's material (albedo = its brightest observation, roughly) re-rendered at ``lights``."""
    from btforge.plugins.demo.procedural import ProceduralMaterial, render_lights
    albedo = np.clip(capture.images.max(0), 0.02, 1.0).astype(np.float32)
    material = ProceduralMaterial(capture.heights.astype(np.float32), albedo, capture.normals.astype(np.float32))
    return render_lights(material, lights)
