"""Light calibration from mirror spheres: ``btforge calibrate`` and stage ``calibrate.lights``."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from btforge import REQUIRED, Param, SampleStack, declare_stage, hookimpl
from btforge.errors import BtforgeInputError

from .lights import (calibrate, image_list, parse_focal, parse_principal, parse_sphere, report_picture,
                     summary_lines, write_calibration)

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


def _stack_of(images, lights, names) -> SampleStack:
    from btforge.plugins.stackio.images import read_image
    frames = [read_image(p)[0] for p in images]
    odd = [p.name for p, f in zip(images, frames) if f.shape != frames[0].shape or f.dtype != frames[0].dtype]
    if odd:
        raise BtforgeInputError(", ".join(odd[:5]), f"expected the size and bit depth of {images[0].name}",
                                "the capture's images must come from one camera setting")
    channels = ("R", "G", "B") if frames[0].shape[2] == 3 else ("Y",)
    if frames[0].dtype == np.uint8:
        return SampleStack(np.stack(frames)[None], lights, [[0.0, 0.0, 1.0]], channels, "srgb8", names)
    # 16-bit and float images are linear radiance, as stackio.read takes them
    scale = np.float32(65535.0 if frames[0].dtype == np.uint16 else 1.0)
    data = np.stack([f.astype(np.float32) / scale for f in frames])[None]
    return SampleStack(data, lights, [[0.0, 0.0, 1.0]], channels, "linear", names)


def _calibrate_precheck(params, paths):
    """Before any stage runs: the photographs exist, and so do the later capture's; the spheres parse."""
    files, problems = [], []
    checks = [lambda: files.extend(image_list(params["images"], paths.graph_dir))]
    if params.get("apply_to"):
        checks.append(lambda: files.extend(image_list(params["apply_to"], paths.graph_dir)))
    spheres = [t for t in (params.get("sphere") or "").split(";") if t.strip()]
    checks += [lambda t=t: parse_sphere(t, "param 'sphere'") for t in spheres]
    if params.get("principal"):
        checks.append(lambda: _principal_of(params["principal"], params.get("focal") or params.get("estimate_focal"),
                                            "param 'principal'"))
    for check in checks:
        try:
            check()
        except BtforgeInputError as exc:
            problems.append(exc.one_line())
    if problems:
        raise BtforgeInputError("calibrate.lights", "; ".join(problems))
    return files


def _principal_of(text, focal, where):
    """The principal point given as 'X,Y', or None; one without a focal length is an error (it means nothing)."""
    if not text:
        return None
    if not focal:
        raise BtforgeInputError(f"{where} {text}", "a principal point needs a focal length",
                                "give the focal length in pixels too, or leave the principal point out")
    return parse_principal(text, where)


@declare_stage(
    "calibrate.lights", deprecated_names=("lights.calibrate",),
    outputs={"stack": "SampleStack"},
    params=[
        Param("images", "str", REQUIRED, "the photographs with the mirror sphere(s): a folder or a glob such as "
              "'capture/*.jpg' (relative to the graph file)"),
        Param("out", "outpath", "lights.lp", "the light file to write (relative to --out)"),
        Param("report", "outpath", "calibration.png", "the picture of the sphere(s) with every highlight numbered"),
        Param("sphere", "str", "", "the sphere as 'X,Y,R' in pixels (several: 'X,Y,R;X,Y,R'); empty: find them"),
        Param("focal", "float", 0.0, "focal length in pixels for a perspective camera; 0: orthographic", low=0.0),
        Param("estimate_focal", "bool", False, "with focal 0: estimate the focal length from the stretch of the "
              "spheres' outlines toward the principal point (a wide lens); orthographic when they show none"),
        Param("principal", "str", "", "the perspective camera's principal point as 'X,Y' in pixels (a cropped "
              "photograph's is not its centre); empty: the image centre"),
        Param("apply_to", "str", "", "a later capture (folder or glob) shot with the same lights in the same order: "
              "the light file and the stack then list its images"),
        Param("exclude", "str", "", "image file names to leave out (comma-separated): delete a wrong light"),
    ],
    side_effects=True,
    precheck=_calibrate_precheck,
)
def lights_calibrate(ctx, *, images, out, report, sphere, focal, estimate_focal, principal, apply_to, exclude):
    """Find the light direction of every photograph from the highlights on mirror spheres in view.

    The spheres are found automatically (a circle fitted to the outline in the capture's maximum and median
    images) unless given.  In every image the highlight is found with a brightness threshold that adapts until a
    small share of the sphere is lit and a weighted centroid refined in a shrinking window; highlights that are too
    dim or too large are rejected and the image is reported by name (it is left out of the light file: no light
    is ever shifted onto another image).  Directions follow from reflection on the sphere (orthographic, or
    perspective with ``focal`` and ``principal``, or a focal length estimated from the outlines' stretch toward the
    principal point) and are averaged over the spheres, weighted by their uncertainty.

    Outputs
    -------
    stack : SampleStack
        The images (or those of ``apply_to``) whose light was found, with the calibrated directions.

    Notes
    -----
    ``spheres`` (centre and radius), ``focal`` (pixels, None: orthographic), ``lights_found``, ``left_out`` (image
    names: no highlight, or excluded),
    ``uncertainty_deg_median`` and
    ``confidence_min``; the light file and the report picture are written.
    """
    base = ctx.paths.graph_dir
    files = image_list(images, base)
    spheres = [parse_sphere(s, "param 'sphere'") for s in sphere.split(";") if s.strip()] or None
    centre = _principal_of(principal, focal or estimate_focal, "param 'principal'")
    result = calibrate(files, spheres, focal or ("auto" if estimate_focal else None), centre)
    result = result.excluding(n.strip() for n in exclude.split(",") if n.strip())
    later = image_list(apply_to, base) if apply_to else None
    target = ctx.paths.output(out)
    target.parent.mkdir(parents=True, exist_ok=True)
    left_out = write_calibration(result, target, later)
    report_path = ctx.paths.output(report)
    report_path.parent.mkdir(parents=True, exist_ok=True)
    report_picture(result, report_path)
    for line in result.problems():
        ctx.warn(line)
    ctx.note("spheres", [[round(c.x, 2), round(c.y, 2), round(c.r, 2)] for c in result.spheres])
    ctx.note("focal", None if result.focal is None else round(result.focal, 1))
    for line in result.focal_notes:
        ctx.note("focal_estimate", line)
    ctx.note("lights_found", int(result.found.sum()))
    ctx.note("left_out", left_out)
    ctx.note("uncertainty_deg_median", round(float(np.nanmedian(result.uncertainty_deg)), 3))
    ctx.note("confidence_min", round(float(result.confidence[result.found].min()), 3))
    keep = np.flatnonzero(result.found)
    chosen = [(later or files)[i] for i in keep]
    return {"stack": _stack_of(chosen, result.lights[keep], tuple(p.name for p in chosen))}


def _calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("images", nargs="+", help="the photographs with the sphere: files, folders or globs")
    parser.add_argument("--out", required=True, metavar="FILE.lp", help="the light file to write")
    parser.add_argument("--sphere", action="append", metavar="X,Y,R",
                        help="a sphere's centre column, row and radius in pixels (repeatable); default: found")
    parser.add_argument("--focal", metavar="PIXELS", help="perspective camera focal length in pixels, or 'auto': "
                        "estimated from the stretch of the spheres' outlines toward the principal point")
    parser.add_argument("--principal", metavar="X,Y", help="the perspective camera's principal point in pixels "
                        "(default: the image centre; a cropped photograph's lies elsewhere)")
    parser.add_argument("--report", metavar="FILE.png", help="the picture of the highlights (default: beside --out)")
    parser.add_argument("--apply-to", nargs="+", metavar="IMAGE",
                        help="write the lights for a later capture's images (same lights, same order) instead")
    parser.add_argument("--exclude", action="append", default=[], metavar="NAME",
                        help="leave this image (file name) out: delete a wrong light (repeatable)")


def _calibrate_run(args) -> int:
    """Light directions (.lp) from the highlights on mirror spheres in the photographs.

    Exits with 0 when every image has a light, 1 when some were left out (they are named), 2 on bad input.
    Images excluded with ``--exclude`` are left out on request and do not count as missing.
    """
    focal = parse_focal(args.focal) if args.focal is not None else None
    files = image_list(args.images)
    spheres = [parse_sphere(s) for s in args.sphere] if args.sphere else None
    principal = _principal_of(args.principal, focal, "--principal")
    result = calibrate(files, spheres, focal, principal).excluding(args.exclude)
    out = Path(args.out)
    if out.suffix.lower() != ".lp":
        raise BtforgeInputError(f"--out {args.out}", "expected a .lp file name")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_calibration(result, out, image_list(args.apply_to) if args.apply_to else None)
    missing = [line for line in result.problems() if not line.endswith("left out on request")]
    report = Path(args.report) if args.report else out.with_name(out.stem + "_calibration.png")
    report_picture(result, report)
    for c in result.spheres:
        print(f"sphere: centre ({c.x:.2f}, {c.y:.2f}), radius {c.r:.2f} px, outline support {c.support:.2f}")
    for line in result.focal_notes:
        print(f"focal length estimate: {line}")
    print("camera: " + ("orthographic" if result.focal is None else f"pinhole, focal length {result.focal:.1f} px"))
    print("\n".join(summary_lines(result)))
    print(f"wrote {out} ({int(result.found.sum())} lights) and {report}")
    for line in result.problems():
        print(f"warning: {line}", file=sys.stderr)
    return 1 if missing else 0


@hookimpl
def btforge_stages():
    return [lights_calibrate]


@hookimpl
def btforge_cli_commands():
    return {"calibrate": (_calibrate_arguments, _calibrate_run)}


@hookimpl
def btforge_bench_commands():
    from .bench import bench_calibrate
    return {"calibrate": bench_calibrate}
