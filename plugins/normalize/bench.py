"""``btforge bench normalize``: held-out RGB PTM PSNR of captures without and with exposure correction."""
from __future__ import annotations

import argparse
import time


def bench_normalize(args: list[str]) -> int:
    """Held-out PSNR of an RGB PTM (every 5th light) without, with scale-only and with fall-off correction."""
    import btforge
    from btforge.plugins.relight import compare_stacks
    from btforge.plugins.stackio.images import load_stack
    from .exposure import corrected, estimate_exposure
    parser = argparse.ArgumentParser(prog="btforge bench normalize")
    parser.add_argument("captures", nargs="+", metavar="LIGHTS.lp")
    parser.add_argument("--every", type=int, default=5, help="hold out every N-th light")
    opts = parser.parse_args(args)
    split, fit, relight = btforge.stage("stackio.split"), btforge.stage("ptm.fit"), btforge.stage("relight.images")

    def heldout(stack):
        parts = split(stack=stack, every=opts.every)
        model = fit(stack=parts["fit"], variant="rgb")["model"]
        return compare_stacks(relight(model=model, at=parts["test"])["stack"], parts["test"])["psnr_db"]

    print("| capture | size, lights | uncorrected | normalize | s | normalize, falloff | s |")
    print("|---|---|---|---|---|---|---|")
    for path in opts.captures:
        stack = load_stack(path)
        row = [path, f"{stack.width} x {stack.height}, {stack.n_light}", f"{heldout(stack):.2f} dB"]
        for falloff in (False, True):
            start = time.perf_counter()
            exposure = estimate_exposure(stack, None, falloff)
            seconds = time.perf_counter() - start
            row += [f"{heldout(corrected(stack, exposure)):.2f} dB", f"{seconds:.1f}"]
        print("| " + " | ".join(row) + " |", flush=True)
    return 0
