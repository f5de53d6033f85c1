"""``btforge bench synthesis``: what synthesis quality costs in time, per synthesizer and exemplar size.

Every stage declared with ``role="synthesizer"`` (a third-party one too) runs with its defaults on central crops
of a real capture, fitted as orthonormal LRGB PTMs (9-D texels).  For each it reports the analysis seconds (its
first run on an exemplar) and the synthesis seconds (a second run with another seed, which reuses a cached
analysis), and the ``score`` metrics of the result; a shuffled-block baseline is scored beside them.  The shared
neighbourhood search is measured on the same exemplars: the fast engine's build and query time, the exact
engine's query time, and the fast engine's recall and distance ratio at k = 6.
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

from btforge.buffers import central_crop

SIZES = (64, 128, 192, 256)
SCORE_KEYS = ("texture_statistics", "swd", "coherence", "completeness", "verbatim_share", "seam_ratio")
BASELINE_BLOCK = 16
RECALL_QUERIES = 2000   # queries whose exact neighbours are computed for the recall
PROCEDURAL = "procedural"


def exemplar_model(path: str, crop: int):
    """The exemplar as an orthonormal LRGB PTM of the central ``crop`` x ``crop`` texels of a capture
    (``procedural``: the demo material rendered under 16 lights, a held-out real-like exemplar; a ``.ptm`` file:
    that model, cropped)."""
    from btforge import stage
    if path == PROCEDURAL:
        from .kcoherence import benchmark_exemplar
        stack = benchmark_exemplar(crop, lights=16, seed=7)
        return stage("ptm.fit")(stack=stack, variant="lrgb", basis="orthonormal")["model"]
    if str(path).endswith(".ptm"):
        return central_crop(stage("ptm.read")(path=str(path))["model"], crop)
    from btforge.plugins.stackio.images import load_stack
    patch = central_crop(load_stack(Path(path)), crop)
    return stage("ptm.fit")(stack=patch, variant="lrgb", basis="orthonormal")["model"]


def shuffled_blocks(exemplar_size: tuple[int, int], size: tuple[int, int], block: int = BASELINE_BLOCK,
                    seed: int = 0):
    """The baseline a synthesizer must beat: ``block x block`` exemplar blocks laid at random, without matching."""
    from btforge.buffers import CoordMap
    (eh, ew), (h, w) = exemplar_size, size
    rng = np.random.default_rng(seed)
    by, bx = -(-h // block), -(-w // block)
    oy = rng.integers(0, eh - block + 1, (by, bx))
    ox = rng.integers(0, ew - block + 1, (by, bx))
    rows, cols = np.mgrid[0:h, 0:w]
    coords = np.stack([oy[rows // block, cols // block] + rows % block,
                       ox[rows // block, cols // block] + cols % block], axis=-1).astype(np.int32)
    return CoordMap(coords, (eh, ew), wrap=False)


def synthesizers() -> dict:
    """The registered stages whose role is ``synthesizer``, by name."""
    from btforge.registry import default_registry
    return {name: st for name, st in sorted(default_registry().stages.items())
            if getattr(st, "role", "") == "synthesizer"}


def score_map(model, coords, lights) -> dict:
    from btforge import stage
    output = stage("synth.materialize")(coords=coords, source=model)["output"]
    values = stage("synth.score")(output=output, exemplar=model, coords=coords, lights=lights)["scores"].values
    return {k: values.get(k) for k in SCORE_KEYS}


def time_synthesizer(st, model, size: int, repeat: int) -> dict:
    """First run (analysis + synthesis), then ``repeat`` runs with other seeds (cached analysis): seconds."""
    from btforge.context import StageContext
    st(exemplar=model, size=[32, 32], seed=99)  # kernel builds outside the timing (the analysis is per exemplar)
    from .search import clear_caches
    clear_caches()
    ctx = StageContext(node="bench", quiet=True)
    start = time.perf_counter()
    coords = st(ctx=ctx, exemplar=model, size=[size, size], seed=0)["coords"]
    first = time.perf_counter() - start
    again = []
    for seed in range(1, repeat + 1):
        start = time.perf_counter()
        st(exemplar=model, size=[size, size], seed=seed)
        again.append(time.perf_counter() - start)
    synthesis = statistics.median(again)
    return {"coords": coords, "first_s": first, "analysis_s": max(0.0, first - synthesis), "synthesis_s": synthesis,
            "notes": dict(ctx.notes)}


def measure_search(model, queries: int = RECALL_QUERIES, k: int = 6) -> dict:
    """The shared search on the exemplar's 5 x 5 neighbourhoods: fast build/query, exact query, recall at k; the
    self-join of every texel (itself left out) and its recall."""
    from . import search
    from .selfjoin import self_join
    from .features import texel_features
    from .textons import normalise_features
    features = normalise_features(texel_features(model))
    vectors = search.neighbourhood_vectors(features, search.square_window(5))
    rng = np.random.default_rng(0)
    rows = np.sort(rng.choice(len(vectors), min(queries, len(vectors)), replace=False))
    sample = vectors[rows]
    search.knn(vectors[:64], vectors[:4], k, engine="exact")  # kernel build
    search.clear_caches()
    start = time.perf_counter()
    index = search.FastIndex(vectors)
    build = time.perf_counter() - start
    start = time.perf_counter()
    fast_idx, fast_d = index.query(sample, k)
    fast_query = time.perf_counter() - start
    start = time.perf_counter()
    true_idx, true_d = search.knn(vectors, sample, k + 1, engine="exact")
    exact_query = time.perf_counter() - start
    start = time.perf_counter()
    join_idx, join_d = self_join(features, 2, k, exclude=0)
    join = time.perf_counter() - start
    # the self-join leaves each texel itself out: its truth is the exact list without the query's own row
    others = true_idx != rows[:, None]
    order = np.argsort(~others, axis=1, kind="stable")[:, :k]
    per = 1000.0 / len(sample)
    return {"vectors": list(vectors.shape), "reduced_dims": index.projection.axes.shape[1],
            "fast_build_s": build, "fast_query_s_per_1000": fast_query * per,
            "exact_query_s_per_1000": exact_query * per,
            "recall": search.recall(fast_idx, true_idx[:, :k]),
            "distance_ratio": search.distance_ratio(fast_d, true_d[:, :k]),
            "self_join_s": join, "self_join_recall": search.recall(join_idx[rows], np.take_along_axis(true_idx, order, 1)),
            "self_join_distance_ratio": search.distance_ratio(join_d[rows], np.take_along_axis(true_d, order, 1))}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="btforge bench synthesis", description=bench_synthesis.__doc__.splitlines()[0])
    p.add_argument("--exemplar", required=True, help="the capture (.lp) or PTM file (.ptm) whose central "
                   "crops are the exemplars, or 'procedural' for the demo material")
    p.add_argument("--out", required=True, help="folder for synthesis.csv, search.csv and synthesis.png")
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="exemplar sides (default 64 128 192 256)")
    p.add_argument("--size", type=int, default=256, help="output side in texels (default 256)")
    p.add_argument("--repeat", type=int, default=1, help="re-syntheses with cached analysis; the median is reported")
    p.add_argument("--only", action="append", help="only these synthesizers (stage names)")
    p.add_argument("--lights", type=int, default=8, help="probe lights of the scores (default 8)")
    p.add_argument("--seeds", type=int, default=1, help="score seeds 0 .. N-1 (and N baselines) and report "
                   "each score's median: one seed's sliced-Wasserstein distance varies by up to 2x (default 1)")
    return p


def bench_synthesis(args: list[str]) -> int:
    """Synthesis quality (scores) against analysis and synthesis time, per synthesizer and exemplar size."""
    from btforge.atomic import atomic_write_text
    from btforge.plot import scatter_png

    from .features import probe_lights
    opts = _parser().parse_args(args)
    lights = [list(map(float, light)) for light in probe_lights(opts.lights)]
    from btforge.registry import default_registry
    only = {default_registry().aliases.get(n, n) for n in opts.only or ()}  # old stage names still select
    chosen = {n: st for n, st in synthesizers().items() if not only or n in only}
    rows, search_rows = [], []
    for crop in opts.sizes:
        model = exemplar_model(opts.exemplar, crop)
        label = f"{model.height}x{model.width}"
        found = measure_search(model)
        search_rows.append({"exemplar": label, **{k: _round(v) for k, v in found.items()}})
        print(f"{label} search: recall {found['recall']:.3f}, distance ratio {found['distance_ratio']:.4f}, "
              f"fast build {found['fast_build_s']:.2f} s + {found['fast_query_s_per_1000']:.3f} s / 1000 queries, "
              f"exact {found['exact_query_s_per_1000']:.3f} s / 1000 queries; self-join {found['self_join_s']:.2f} s, "
              f"recall {found['self_join_recall']:.3f}", file=sys.stderr)
        baseline = median_scores([score_map(model, shuffled_blocks((model.height, model.width), (opts.size, opts.size),
                                                                   seed=seed), lights) for seed in range(opts.seeds)])
        rows.append({"synthesizer": "shuffled blocks", "exemplar": label, "analysis_s": 0.0, "synthesis_s": 0.0,
                     **{k: _round(v) for k, v in baseline.items()}})
        for name, st in chosen.items():
            timed = time_synthesizer(st, model, opts.size, opts.repeat)
            scores = median_scores([score_map(model, timed["coords"], lights)] + [
                score_map(model, st(exemplar=model, size=[opts.size, opts.size], seed=seed)["coords"], lights)
                for seed in range(1, opts.seeds)])
            rows.append({"synthesizer": name, "exemplar": label, "analysis_s": _round(timed["analysis_s"]),
                         "synthesis_s": _round(timed["synthesis_s"]), **{k: _round(v) for k, v in scores.items()}})
            print(f"{label} {name:12s} analysis {timed['analysis_s']:7.3f} s  synthesis {timed['synthesis_s']:7.3f} s  "
                  f"texture stats {scores['texture_statistics']:.3f}  swd {scores['swd']:.4f}", file=sys.stderr)
    target = Path(opts.out)
    for filename, table in (("synthesis.csv", rows), ("search.csv", search_rows)):
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows(table)
        atomic_write_text(target / filename, buffer.getvalue())
    timed_rows = [r for r in rows if r["synthesizer"] != "shuffled blocks"]
    scatter_png(target / "synthesis.png", [r["analysis_s"] + r["synthesis_s"] for r in timed_rows],
                [r["texture_statistics"] for r in timed_rows],
                [f"{r['synthesizer']} {r['exemplar']}" for r in timed_rows], [r["synthesizer"] for r in timed_rows],
                title=f"{opts.size}x{opts.size} outputs from crops of {Path(opts.exemplar).parent.name or opts.exemplar}",
                xlabel="analysis + synthesis seconds", ylabel="texture statistics ratio (1 = exemplar vs itself)",
                higher_is_better=False)
    print(_table(rows))
    print(_table(search_rows))
    return 0


def median_scores(runs: list[dict]) -> dict:
    """Each score's median over runs (None where a run has none)."""
    return {k: statistics.median(r[k] for r in runs) if all(r[k] is not None for r in runs) else None
            for k in runs[0]}


def _round(value):
    return round(value, 4) if isinstance(value, float) else value


def _table(rows: list[dict]) -> str:
    keys = list(rows[0])
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join("-" if r[k] is None else str(r[k]) for k in keys) + " |" for r in rows]
    return "\n".join(lines)
