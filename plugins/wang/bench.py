"""``btforge bench wang``: time per synthesis step and per tile, BTFel share and memory of a complete tile set."""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np


def procedural_exemplar(size: int, lights: int = 24, seed: int = 1, pattern: str = "bumps"):
    """A built-in procedural material (``demo.material``'s bumps, or a kind of :mod:`demo.patterns`) as a stack
    of ``size x size``."""
    from btforge.buffers import SampleStack
    from btforge.plugins.demo.patterns import make_pattern
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights
    material = (make_material(size, size, seed=seed) if pattern == "bumps"
                else make_pattern(pattern, size, size, seed=seed))
    directions = hemisphere_lights(lights)
    return SampleStack(render_lights(material, directions)[None], directions, np.array([[0.0, 0.0, 1.0]]))


def capture_exemplar(path: str, size: int, origin=(150, 100)):
    """A ``size x size`` crop of a real capture's light file, fitted as an orthonormal RGB PTM."""
    from btforge.context import StageContext
    from btforge.registry import default_registry
    registry = default_registry()
    stack = registry.stage("stackio.read")(ctx=StageContext(node="read"), path=path)["stack"]
    rows, cols = np.meshgrid(np.arange(origin[0], origin[0] + size), np.arange(origin[1], origin[1] + size),
                             indexing="ij")
    crop = stack.remap(rows, cols)
    return registry.stage("ptm.fit")(ctx=StageContext(node="fit"), stack=crop, variant="rgb",
                                     basis="orthonormal")["model"]


def bench_wang(args: list[str]) -> int:
    """Time a complete Wang-tile set per step and per tile, with its BTFel share and memory."""
    from . import build_tile_set
    parser = argparse.ArgumentParser(prog="btforge bench wang", description=bench_wang.__doc__)
    parser.add_argument("--exemplar", type=int, default=192, help="exemplar size (square), default 192")
    parser.add_argument("--tile", type=int, default=64, help="tile size w, default 64")
    parser.add_argument("--edge", type=int, default=0, help="edge thickness h (0: w / 4)")
    parser.add_argument("--colors", type=int, nargs=2, default=[2, 2], help="horizontal and vertical colours")
    parser.add_argument("--capture", default=None, help="a .lp light file: crop and fit it instead of the "
                        "procedural material")
    parser.add_argument("--repeat", type=int, default=1, help="runs (median reported), default 1")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--usage", type=float, default=None, help="the usage term's weight (default: wang.tiles')")
    parser.add_argument("--usage-unit", choices=("neighbour", "match"), default=None, help="the usage term's unit "
                        "(default: wang.tiles')")
    parser.add_argument("--interior", type=int, default=0, help="side of the windows that fill the interiors "
                        "(0: wang.tiles' default, 1.5 x edge)")
    parser.add_argument("--refine", type=int, default=None, help="texture-optimisation rounds of the interiors "
                        "(default: wang.tiles')")
    parser.add_argument("--pattern", default="bumps", choices=("bumps", "stones", "plaster", "fibres"),
                        help="the procedural material (without --capture), default bumps; made with seed 3")
    parser.add_argument("--score", action="store_true", help="also score a 4 x 4 tiling (seed 0) with synth.score: "
                        "seam and straight-seam visibility, evenness, SWD over the shuffled-block baseline")
    opts = parser.parse_args(args)
    if opts.repeat < 1:
        parser.error("--repeat must be at least 1")
    start = time.perf_counter()
    exemplar = (capture_exemplar(opts.capture, opts.exemplar) if opts.capture
                else procedural_exemplar(opts.exemplar, seed=1 if opts.pattern == "bumps" else 3, pattern=opts.pattern))
    prepare = time.perf_counter() - start
    options = {"interior": opts.interior}
    if opts.usage is not None:
        options["usage_weight"] = opts.usage
    if opts.usage_unit is not None:
        options["usage_unit"] = opts.usage_unit
    if opts.refine is not None:
        options["optimise"] = {"iterations": opts.refine}
    runs = []
    for r in range(opts.repeat):
        begin = time.perf_counter()
        tiles, synthesis, ratios = build_tile_set(exemplar, tile=opts.tile, edge=opts.edge, colors=opts.colors,
                                                  seed=opts.seed + r, **options)
        runs.append((time.perf_counter() - begin, tiles, synthesis, ratios))
    runs.sort(key=lambda run: run[0])
    total, tiles, synthesis, ratios = runs[len(runs) // 2]
    stats = tiles.statistics()
    kind = f"capture {opts.capture} (rgb PTM)" if opts.capture else "procedural stack"
    print(f"wang tiles: {kind}, exemplar {opts.exemplar}^2, tiles {opts.tile}^2, edge {tiles.edge}, colours "
          f"{opts.colors[0]}+{opts.colors[1]} -> {stats['tiles']} tiles; median of {opts.repeat}")
    print(f"  {'step':<12}{'seconds':>10}{'patches':>10}{'kept':>8}")
    for step, seconds in synthesis.timings.items():
        count = synthesis.counts.get(step, {})
        print(f"  {step:<12}{seconds:>10.2f}{count.get('placed', ''):>10}{count.get('kept', ''):>8}")
    print(f"  {'total':<12}{total:>10.2f}   ({total / stats['tiles']:.2f} s per tile; exemplar prepared in "
          f"{prepare:.2f} s)")
    print(f"  BTFels: {stats['btfels']} = {100 * stats['referenced_share']:.2f}% of the exemplar; table "
          f"{stats['table_bytes'] / 1e6:.3f} MB + indices {stats['index_bytes'] / 1e6:.3f} MB = "
          f"{stats['total_bytes'] / 1e6:.3f} MB (tiles as copies: {stats['texels_as_copies_bytes'] / 1e6:.3f} MB)")
    print("  filling time by activity (edges + interiors): " + ", ".join(
        f"{k} {v:.2f} s" for k, v in synthesis.counts["filling_seconds"].items()))
    print("  seam ratios: " + ", ".join(f"{k} {v:.3f}" for k, v in ratios.items()))
    print(f"  seams: worst mean ratio {ratios['worst_mean_ratio']:.3f}, worst p99 ratio "
          f"{ratios['worst_p99_ratio']:.3f}; pixels over threshold {synthesis.unresolved}")
    print("  " + interior_report(tiles, exemplar, synthesis))
    if opts.score:
        print("  " + tiling_report(tiles, exemplar))
    print(f"  peak resident memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    return 0


def tiling_report(tiles, exemplar) -> str:
    """The measures of what the eye sees of a 4 x 4 tiling (tiling seed 0), scored by ``synth.score``."""
    from btforge import stage
    coords = stage("wang.tiling")(tiles=tiles, rows=4, cols=4, seed=0)["coords"]
    output = stage("synth.materialize")(coords=coords, source=exemplar)["output"]
    v = stage("synth.score")(exemplar=exemplar, output=output, coords=coords)["scores"].values
    return (f"4 x 4 tiling: seam visibility {v['seam_visibility']:.3f}, straight-seam visibility "
            f"{v['straight_seam_visibility']:.3f}, evenness {v['evenness']:.3f}, SWD / shuffled blocks "
            f"{v['swd_vs_shuffled_blocks']:.3f}")


def interior_report(tiles, exemplar, synthesis) -> str:
    """How visible the tiles' inner patch seams are, and how far apart in the exemplar the corner samples lie."""
    from .features import appearance_features
    from .seams import cut_distances
    from .synthesis import neighbour_distances
    full = appearance_features(exemplar)
    cuts = cut_distances(tiles.tile_coords, full)
    reference = float(np.mean(neighbour_distances(full)))
    inner = np.concatenate([cuts["cut_h"], cuts["cut_v"]])
    local = np.concatenate([cuts["cut_h_local"], cuts["cut_v_local"]])
    corners = np.array(list(synthesis.corner_positions.values()), np.int64).reshape(-1, 2)
    spread = corner_variety(full, corners, tiles.edge)
    return (f"interior cuts: mean distance {inner.mean() / reference:.3f}x the exemplar's mean neighbour distance, "
            f"{inner.mean() / max(local.mean(), 1e-30):.3f}x the same texels' own ({100 * cuts['cut_share']:.1f}% "
            f"of neighbour pairs); corner samples' variety {spread:.3f}")


def corner_variety(feats: np.ndarray, origins: np.ndarray, h: int, seed: int = 0) -> float:
    """How unlike each other the corner samples (``h x h`` patches at ``origins``) look: their mean pairwise
    texel distance over that of random pairs of ``h x h`` exemplar patches (1: as varied as the exemplar)."""
    def mean_pair_distance(a: np.ndarray, b: np.ndarray) -> float:
        dy, dx = np.mgrid[0:h, 0:h]
        pa, pb = feats[a[:, None, None, 0] + dy, a[:, None, None, 1] + dx], feats[b[:, None, None, 0] + dy,
                                                                                   b[:, None, None, 1] + dx]
        return float(np.linalg.norm(pa.astype(np.float64) - pb, axis=-1).mean())
    i, j = np.triu_indices(len(origins), 1)
    rng = np.random.default_rng(seed)
    random = rng.integers(0, np.array(feats.shape[:2]) - h + 1, size=(2, 512, 2))
    return mean_pair_distance(origins[i], origins[j]) / max(mean_pair_distance(random[0], random[1]), 1e-30)
