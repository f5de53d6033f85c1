"""What synthesis quality costs in time: ``btforge bench synthesis`` sweeps the synthesizers' main knobs."""
from __future__ import annotations

import csv
import io
import statistics
import sys
import time
from pathlib import Path

import numpy as np

# (synthesizer stage, params) swept by the bench; sizes are added at run time.
CONFIGURATIONS = (
    [("quilt", {"block": b, "search": "rejection"}) for b in (16, 24, 32)]
    + [("quilt", {"block": 32, "search": "brute"}), ("quilt", {"block": 24, "seam": "blend"})]
    + [("kcoherence", {"k": k, "neighborhood": n, "levels": lv})
       for k, n, lv in ((1, 5, 3), (6, 3, 3), (6, 5, 1), (6, 5, 3), (6, 7, 3))]
    + [("jumpmap", {})]
)
SCORE_KEYS = ("swd", "coherence", "completeness", "verbatim_share", "seam_ratio", "consistency")


def exemplar_model(path: str, crop: int):
    """The exemplar as an orthonormal LRGB PTM of the central ``crop`` x ``crop`` texels of a capture."""
    from btforge import stage
    from btforge.plugins.stackio.images import load_stack
    stack = load_stack(Path(path))
    h, w = min(crop, stack.height), min(crop, stack.width)
    patch = stage("crop")(input=stack, origin=[(stack.height - h) // 2, (stack.width - w) // 2], size=[h, w])["output"]
    return stage("ptm.fit")(stack=patch, variant="lrgb", basis="orthonormal")["model"]


def bench_synthesis(exemplar: str, out: str, *, crop: int = 64, size: int = 256, repeat: int = 1,
                    only: list[str] | None = None) -> list[dict]:
    from btforge import stage
    from btforge.atomic import atomic_write_text
    from btforge.plot import scatter_png
    from btforge.registry import default_registry

    from .features import probe_lights

    model = exemplar_model(exemplar, crop)
    lights = [list(map(float, l)) for l in probe_lights(8)]
    registered = default_registry().stages
    rows = []
    for name, params in CONFIGURATIONS:
        if only and name not in only:
            continue
        label = f"{name} " + " ".join(f"{k}={v}" for k, v in params.items())
        if name not in registered:
            print(f"  {label:40s} skipped: stage '{name}' is not installed", file=sys.stderr)
            continue
        synthesize = stage(name)
        synthesize(exemplar=model, size=[32, 32], **params)  # kernel builds outside the timing
        times, coords = [], None
        for _ in range(max(1, repeat)):
            start = time.perf_counter()
            coords = synthesize(exemplar=model, size=[size, size], **params)["coords"]
            times.append(time.perf_counter() - start)
        output = stage("materialize")(coords=coords, source=model)["output"]
        scores = stage("score")(output=output, exemplar=model, coords=coords, lights=lights)["scores"].values
        row = {"synthesizer": name, "params": " ".join(f"{k}={v}" for k, v in params.items()) or "-",
               "seconds": round(statistics.median(times), 4)}
        row.update({k: (round(scores[k], 5) if isinstance(scores.get(k), float) else scores.get(k)) for k in SCORE_KEYS})
        rows.append(row)
        print(f"  {label:40s} {row['seconds']:8.3f} s  swd {row['swd']:.4f}  coherence {row['coherence']:.4f}  "
              f"completeness {row['completeness']:.4f}  seams {row['seam_ratio']}", file=sys.stderr)
    target = Path(out)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=["synthesizer", "params", "seconds", *SCORE_KEYS])
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(target / "synthesis.csv", buffer.getvalue())
    scatter_png(target / "synthesis.png", [r["seconds"] for r in rows], [r["swd"] for r in rows],
                [f"{r['synthesizer']} {r['params']}" for r in rows], [r["synthesizer"] for r in rows],
                title=f"synthesis quality vs time: {size}x{size} from a {model.height}x{model.width} exemplar of {exemplar}",
                xlabel="seconds", ylabel="sliced Wasserstein distance (lower is better)", higher_is_better=False)
    return rows
