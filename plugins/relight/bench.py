"""``btforge bench representations``: fit time, relight time, size and held-out error of every representation.

The representations are the installed stages that declare ``role="fit"`` (a third-party fit shows up without
any change here), each at the parameter settings its ``sweep`` lists.  They are fitted on a capture's lights
but every fifth (or on one capture, scored on another) and scored on the held-out lights by :func:`compare_stacks`.
"""
from __future__ import annotations

import argparse
import csv
import io
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from btforge.bench import counted_warnings, positive_count
from btforge.buffers import central_crop
from btforge.errors import BtforgeInputError

DEFAULT_CROP = 128  # central texels: every fit of a full 1024^2 capture would take tens of minutes


def _label(family: str, params: dict) -> str:
    return family + " " + " ".join(f"{k}={v}" for k, v in params.items())


def _configurations(registry, only, overrides: dict):
    """(family, stage, params) of every fit to compare: each ``role="fit"`` stage at each of its sweep's settings,
    with ``--set`` overrides applied to the stages that have such a parameter."""
    for st in registry.stages_with_role("fit"):
        family = st.name.split(".")[0]
        if only and family not in only:
            continue
        for setting in st.sweep or ({},):
            params = {**setting, **{k: v for k, v in overrides.items() if st.param(k) is not None}}
            yield family, st, params


def _split(stack, test_path, crop):
    from btforge.buffers import SampleStack
    from btforge.plugins.stackio.images import load_stack
    if test_path:
        return stack, central_crop(load_stack(Path(test_path)), crop)
    held = np.zeros(stack.n_light, bool)
    held[::5] = True

    def part(mask):
        return SampleStack(stack.samples[:, mask], stack.lights[mask], stack.views, stack.channels, stack.encoding)
    return part(~held), part(held)


def _measure(st, params, fit, test, repeat: int) -> dict:
    from btforge.buffers import SampleStack

    from . import compare_stacks
    times = []
    for _ in range(max(1, repeat)):
        start = time.perf_counter()
        model = st(stack=fit, **params)["model"]
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
    return {"fit_seconds": round(statistics.median(times), 4),
            "relight_seconds_per_megapixel": round(relight_s / megapixels, 5),
            "bytes_per_texel": round(model.nbytes / (model.height * model.width), 2),
            "psnr_db": scores["psnr_db"], "psnr_db_worst_light": scores["psnr_db_worst_light"],
            "max_abs_error": scores["max_abs_error"], "domain": scores["domain"]}


def bench_representations(args, registry=None) -> list[dict]:
    """Measure every configuration; write ``representations.csv`` and ``representations.png`` into ``args.out``."""
    from btforge.atomic import atomic_write_text
    from btforge.plot import scatter_png
    from btforge.plugins.stackio.images import load_stack
    from btforge.registry import default_registry

    registry = registry or default_registry()
    full = load_stack(Path(args.stack))
    stack = central_crop(full, args.crop)
    print(f"capture {full.height} x {full.width}, {full.n_view} view(s) x {full.n_light} lights; measuring on "
          + (f"its central {stack.height} x {stack.width} texels (--crop {args.crop}; --crop 0 for all)"
             if stack is not full else f"all {stack.height} x {stack.width} texels"), file=sys.stderr)
    fit, test = _split(stack, args.test, args.crop)
    rows = []
    for family, st, params in _configurations(registry, args.only, getattr(args, "set", None) or {}):
        label = _label(family, params)
        try:
            st(stack=central_crop(fit, 8), **params)  # build kernels outside the timing
        except BtforgeInputError as exc:  # e.g. too few fitting lights for 4 lobes, or a PTM of a BTF
            print(f"  {label:28s} skipped: {exc.problem}", file=sys.stderr)
            continue
        row = {"representation": family, "params": " ".join(f"{k}={v}" for k, v in params.items()),
               **_measure(st, params, fit, test, args.repeat)}
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


def _setting(text: str) -> tuple[str, object]:
    import yaml
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected PARAM=VALUE, found {text!r}")
    return key, yaml.safe_load(value)


def bench_representations_command(argv: list[str]) -> int:
    """Fit time, relight time, size and held-out error of every representation (stages with role 'fit')."""
    p = argparse.ArgumentParser(prog="btforge bench representations", description=bench_representations_command.__doc__)
    p.add_argument("--stack", required=True, help="the capture to fit (.lp or .lvp)")
    p.add_argument("--test", help="held-out capture at other lights (default: every fifth light of --stack)")
    p.add_argument("--out", required=True, help="folder for representations.csv and representations.png")
    p.add_argument("--crop", type=int, default=DEFAULT_CROP,
                   help=f"use only the central CROP x CROP texels (default {DEFAULT_CROP}; 0: all)")
    p.add_argument("--repeat", type=positive_count, default=1, help="fits per representation; the median time is reported")
    p.add_argument("--only", action="append", help="only these representation families (e.g. ptm, sh)")
    p.add_argument("--set", action="append", type=_setting, default=[], metavar="PARAM=VALUE",
                   help="set a parameter of every fit that has it (e.g. view_order=3 for a BTF)")
    args = p.parse_args(argv)
    args.set = dict(args.set)
    with counted_warnings():
        rows = bench_representations(args)
    print(f"wrote {Path(args.out) / 'representations.csv'} and representations.png ({len(rows)} representations)")
    return 0
