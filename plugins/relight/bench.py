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
    return family + " " + (" ".join(f"{k}={v}" for k, v in params.items()) or "(defaults)")


def crop_window(height: int, width: int, size: int) -> tuple[int, int, int, int] | None:
    """``(row, col, rows, cols)`` of the central ``size x size`` texels, or None for the whole capture."""
    if not size or (height <= size and width <= size):
        return None
    r0, c0 = max(0, (height - size) // 2), max(0, (width - size) // 2)
    return r0, c0, min(size, height - r0), min(size, width - c0)


def _configurations(registry, only, overrides: dict, defaults: bool = False):
    """(family, stage, params) of every fit to compare: each ``role="fit"`` stage at each of its sweep's settings
    (``defaults``: at its default settings alone), with ``--set`` overrides applied to the stages that have such
    a parameter."""
    for st in registry.stages_with_role("fit"):
        family = st.name.split(".")[0]
        if only and family not in only:
            continue
        for setting in ({},) if defaults else st.sweep or ({},):
            params = {**setting, **{k: v for k, v in overrides.items() if st.param(k) is not None}}
            yield family, st, params


def held_out_lights(n_light: int) -> np.ndarray:
    """The lights the bench holds out of a single capture: every fifth, from the first."""
    held = np.zeros(n_light, bool)
    held[::5] = True
    return held


def _split(stack, test_path, crop):
    from btforge.buffers import SampleStack
    from btforge.plugins.stackio.images import load_stack
    if test_path:
        return stack, central_crop(load_stack(Path(test_path)), crop)
    held = held_out_lights(stack.n_light)

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
    """Measure every configuration on every capture; write ``representations.csv``, a plot per capture and, with
    more than one capture or relight-cli, ``representations.md`` (held-out PSNR, capture by configuration)."""
    from btforge.atomic import atomic_write_text
    from btforge.registry import default_registry

    registry = registry or default_registry()
    stacks = [args.stack] if isinstance(args.stack, str) else list(args.stack)
    tests = args.test if isinstance(args.test, list) else [args.test] * len(stacks)
    rows = []
    for stack_path, test_path in zip(stacks, tests):
        name = capture_name(stack_path) if len(stacks) > 1 else ""
        found = measure_capture(args, registry, stack_path, test_path if test_path != "-" else None,
                                Path(args.out) / (f"representations-{name}.png" if name else "representations.png"))
        rows += [{**row, "capture": capture_name(stack_path)} for row in found]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]) if rows else ["representation", "capture"])
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(Path(args.out) / "representations.csv", buffer.getvalue())
    if len(stacks) > 1 or any(r["representation"].startswith("relight-cli") for r in rows):
        atomic_write_text(Path(args.out) / "representations.md", psnr_table(rows))
    return rows


def capture_name(path: str) -> str:
    """A short name for a capture: the last two folders above its light file (``realrti-item1``)."""
    return "-".join(Path(path).resolve().parent.parts[-2:])


def measure_capture(args, registry, stack_path: str, test_path: str | None, plot_path: Path) -> list[dict]:
    """Every configuration (and relight-cli's bases, when found) on one capture; its plot at ``plot_path``."""
    from btforge.plot import scatter_png
    from btforge.plugins.stackio.images import load_stack
    full = load_stack(Path(stack_path))
    stack = central_crop(full, args.crop)
    print(f"{stack_path}: capture {full.height} x {full.width}, {full.n_view} view(s) x {full.n_light} lights; "
          "measuring on " + (f"its central {stack.height} x {stack.width} texels (--crop {args.crop}; --crop 0 for "
                             "all)" if stack is not full else f"all {stack.height} x {stack.width} texels"),
          file=sys.stderr)
    fit, test = _split(stack, test_path, args.crop)
    rows = []
    for family, st, params in _configurations(registry, args.only, getattr(args, "set", None) or {},
                                              getattr(args, "defaults", False)):
        label = _label(family, params)
        try:
            st(stack=central_crop(fit, 8), **params)  # build kernels outside the timing
        except BtforgeInputError as exc:  # e.g. too few fitting lights for 4 lobes, or a PTM of a BTF
            print(f"  {label:28s} skipped: {exc.problem}", file=sys.stderr)
            continue
        rows.append({"representation": family, "params": " ".join(f"{k}={v}" for k, v in params.items()) or "defaults",
                     **_measure(st, params, fit, test, args.repeat)})
        _print_row(label, rows[-1])
    rows += _relight_rows(args, stack_path, test_path, full, test)
    scatter_png(plot_path, [r["fit_seconds"] for r in rows], [r["psnr_db"] for r in rows],
                [f"{r['representation']} {r['params']}" for r in rows], [r["representation"] for r in rows],
                title=f"held-out PSNR vs fit time: {stack_path} ({test.width}x{test.height}, "
                      f"{fit.n_view * fit.n_light} fit / {test.n_view * test.n_light} test samples)",
                xlabel="fit seconds", ylabel=f"PSNR dB ({rows[0]['domain'] if rows else ''})")
    return rows


def _print_row(label: str, row: dict) -> None:
    print(f"  {label:28s} fit {row['fit_seconds']:8.3f} s  relight {row['relight_seconds_per_megapixel']:.4f} s/MP  "
          f"{row['bytes_per_texel']:7.1f} B/texel  PSNR {row['psnr_db']:6.2f} dB", file=sys.stderr)


def _relight_rows(args, stack_path: str, test_path: str | None, full, test) -> list[dict]:
    """relight-cli's bases on the same split, when it is installed and can read the capture."""
    from btforge.plugins.stackio.lightfile import read_light_file

    from .relightcli import RELIGHT_ENV, find_relight_cli, measure_relight
    if getattr(args, "no_relight", False):
        return []
    exe = find_relight_cli(getattr(args, "relight_cli", None))
    if exe is None:
        print(f"  relight-cli: not found (set {RELIGHT_ENV} or put it on PATH); left out", file=sys.stderr)
        return []
    if full.n_view != 1 or full.encoding != "srgb8":
        print("  relight-cli: left out (it reads single-view 8-bit captures)", file=sys.stderr)
        return []
    entries = read_light_file(Path(stack_path))
    if test_path is None:
        entries = [e for e, held in zip(entries, held_out_lights(len(entries))) if not held]
    folder = Path(stack_path).resolve().parent
    fit_entries = [(folder / e.filename, e.light) for e in entries]
    rows = measure_relight(exe, fit_entries, test, crop_window(full.height, full.width, args.crop),
                           (full.height, full.width))
    for row in rows:
        _print_row(f"{row['representation']} {row['params']}", row)
    return rows


def psnr_table(rows: list[dict]) -> str:
    """Markdown: held-out PSNR (dB) of each configuration (rows) on each capture (columns), and their mean."""
    captures = list(dict.fromkeys(r["capture"] for r in rows))
    configs = list(dict.fromkeys(f"{r['representation']} {r['params']}".strip() for r in rows))
    psnr = {(r["capture"], f"{r['representation']} {r['params']}".strip()): r["psnr_db"] for r in rows}
    lines = ["| configuration | " + " | ".join(captures) + " | mean |", "|---" * (len(captures) + 2) + "|"]
    for config in configs:
        values = [psnr.get((capture, config)) for capture in captures]
        known = [v for v in values if v is not None]
        mean = f"{statistics.fmean(known):.2f}" if len(known) == len(values) else "-"
        lines.append(f"| {config} | " + " | ".join("-" if v is None else f"{v:.2f}" for v in values) + f" | {mean} |")
    return "\n".join(lines) + "\n"


def _setting(text: str) -> tuple[str, object]:
    import yaml
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected PARAM=VALUE, found {text!r}")
    return key, yaml.safe_load(value)


def bench_representations_command(argv: list[str]) -> int:
    """Fit time, relight time, size and held-out error of every representation (stages with role 'fit')."""
    p = argparse.ArgumentParser(prog="btforge bench representations", description=bench_representations_command.__doc__)
    p.add_argument("--stack", required=True, action="append",
                   help="a capture to fit (.lp or .lvp); repeat for several, each measured on its own")
    p.add_argument("--test", action="append",
                   help="held-out capture at other lights, one per --stack in order ('-': every fifth light of that "
                        "--stack; default: every fifth light of each)")
    p.add_argument("--out", required=True, help="folder for representations.csv, the plots and representations.md")
    p.add_argument("--crop", type=int, default=DEFAULT_CROP,
                   help=f"use only the central CROP x CROP texels (default {DEFAULT_CROP}; 0: all)")
    p.add_argument("--repeat", type=positive_count, default=1, help="fits per representation; the median time is reported")
    p.add_argument("--only", action="append", help="only these representation families (e.g. ptm, sh)")
    p.add_argument("--set", action="append", type=_setting, default=[], metavar="PARAM=VALUE",
                   help="set a parameter of every fit that has it (e.g. view_order=3 for a BTF)")
    p.add_argument("--defaults", action="store_true",
                   help="each fit once, at its default settings, instead of at its sweep's settings")
    p.add_argument("--relight-cli", metavar="PATH", help="relight-cli's executable, run on the same split as a "
                   "reference (default: $BTFORGE_RELIGHT_CLI, else relight-cli on PATH; left out when absent)")
    p.add_argument("--no-relight", action="store_true", help="leave relight-cli out even when it is installed")
    args = p.parse_args(argv)
    args.set = dict(args.set)
    if args.test is None:
        args.test = [None] * len(args.stack)
    elif len(args.test) != len(args.stack):
        raise BtforgeInputError("bench representations --test", f"expected one --test per --stack ({len(args.stack)}),"
                                f" found {len(args.test)}", "give '-' for a capture split by every fifth light")
    with counted_warnings():
        rows = bench_representations(args)
    print(f"wrote {Path(args.out) / 'representations.csv'} and the plots ({len(rows)} rows)")
    return 0
