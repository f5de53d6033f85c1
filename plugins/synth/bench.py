"""``btforge bench synthesis``: what synthesis quality costs in time, per synthesizer and exemplar size.

Every stage declared with ``role="synthesizer"`` (a third-party one too) runs with its defaults on central crops
of a real capture, fitted as orthonormal LRGB PTMs (9-D texels).  For each it reports the analysis seconds (its
first run on an exemplar) and the synthesis seconds (a second run with another seed, which reuses a cached
analysis), and the ``synth.score`` metrics of the result; a shuffled-block baseline is scored beside them.  The shared
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

from btforge.backend import get_backend
from btforge.buffers import PerTexel, central_crop
from btforge.errors import BtforgeInputError

from . import visibility
from .features import texel_features
from .kcoherence import CAUSAL_ORDER, KSET_EXCLUDE, analyse_exemplar, kcoherence
from .quilt_search import SEARCHES
from .quilting import quilt_features
from .textons import normalise_features

SIZES = (64, 128, 192, 256)
SCORE_KEYS = ("texture_statistics", "swd", "coherence", "completeness", "verbatim_share", "seam_ratio",
              "seam_visibility", "straight_seam_visibility", "straight_seam_share", "straight_step_visibility",
              "evenness", "swd_vs_shuffled_blocks", "lattice_share")
#: The measures of what the eye sees, with the column titles of the sheets.
EYE_KEYS = {"seam_visibility": "seams", "straight_seam_visibility": "straight", "straight_step_visibility": "steps",
            "evenness": "even", "swd_vs_shuffled_blocks": "swd/shuffled", "lattice_share": "lattice"}
#: Measures only a tiling has (the sheets leave them out of the other panels).
TILING_KEYS = ("lattice_share",)
RECALL_QUERIES = 2000   # queries whose exact neighbours are computed for the recall
PROCEDURAL = "procedural"
#: Lights of the sheets: from the upper left and from the right, both fairly low (relief shows).
SHEET_LIGHTS = ((-0.5, 0.5, 0.707), (0.8, -0.1, 0.59))


#: How ``btforge bench synthesis --fit`` fits the crops: an LRGB PTM (the default) or a linear RGB one, which
#: blends (synthesizers then feather their seams, :mod:`.feather`).
FITS = {"lrgb": {"variant": "lrgb"}, "rgb": {"variant": "rgb", "space": "linear"}}


def exemplar_model(path: str, crop: int, fit: str = "lrgb"):
    """The exemplar as an orthonormal PTM (``fit``: a key of :data:`FITS`) of the central ``synth.crop`` x
    ``synth.crop`` texels of a capture (``procedural``: the demo material rendered under 16 lights, a held-out real-like
    exemplar; ``procedural:PATTERN``: the demo material's pattern, e.g. ``procedural:stones``; a ``.ptm`` file or a PTM
    in relight's web layout (its ``info.json``): that model, cropped; ``FILE@ROW,COL``: the crop of a capture or
    ``.ptm`` file with its upper-left texel there instead of the central one; a ``.ptm`` file keeps its own variant)."""
    from btforge import stage
    fitted = FITS[fit]
    if path == PROCEDURAL:
        stack = benchmark_exemplar(crop, lights=16, seed=7)
        return stage("ptm.fit")(stack=stack, basis="orthonormal", **fitted)["model"]
    if str(path).startswith(PROCEDURAL + ":"):
        pattern = str(path).split(":", 1)[1]
        stack = stage("demo.material")(size=[crop, crop], lights=16, pattern=pattern, seed=7)["stack"]
        return stage("ptm.fit")(stack=stack, basis="orthonormal", **fitted)["model"]
    path, origin = crop_origin(str(path))
    if path.endswith(".ptm") or Path(path).name == "info.json":   # a PTM file, or one in relight's web layout
        return _cropped(stage("ptm.read")(path=path)["model"], crop, origin)
    from btforge.plugins.stackio.images import load_stack
    patch = _cropped(load_stack(Path(path)), crop, origin)
    return stage("ptm.fit")(stack=patch, basis="orthonormal", **fitted)["model"]


def crop_origin(exemplar: str) -> tuple[str, tuple[int, int] | None]:
    """``FILE@ROW,COL`` split into the file and the crop's upper-left texel (None without ``@``)."""
    if "@" not in exemplar:
        return exemplar, None
    path, _, origin = exemplar.rpartition("@")
    parts = origin.split(",")
    if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
        raise BtforgeInputError(f"--exemplar {exemplar}", f"expected FILE@ROW,COL with two whole numbers after '@', "
                                f"found {origin!r}", "give the crop's upper-left texel, e.g. tablet1.ptm@170,275")
    return path, (int(parts[0]), int(parts[1]))


def _cropped(buffer: PerTexel, crop: int, origin: tuple[int, int] | None) -> PerTexel:
    """The ``crop`` x ``crop`` texels of ``buffer`` from ``origin`` (None: the central ones; ``synth.crop`` names a
    crop that does not fit)."""
    if origin is None:
        return central_crop(buffer, crop)
    from btforge import stage
    return stage("synth.crop")(input=buffer, origin=list(origin), size=[crop, crop])["output"]


def shuffled_blocks(exemplar_size: tuple[int, int], size: tuple[int, int], block: int | None = None,
                    seed: int = 0):
    """The shuffled-block baseline of ``synth.score`` (:func:`.visibility.shuffled_blocks`), by default with its
    block side for this exemplar."""
    return visibility.shuffled_blocks(exemplar_size, size, block or visibility.baseline_block(exemplar_size), seed)


def synthesizers() -> dict:
    """The registered stages whose role is ``synthesizer``, by name."""
    from btforge.registry import default_registry
    return {name: st for name, st in sorted(default_registry().stages.items())
            if getattr(st, "role", "") == "synthesizer"}


class WangTiling:
    """Wang tiles as one synthesizer of the bench: ``wang.tiles`` at its defaults (64 x 64 tiles, 2 + 2 colours)
    with the seed as tile-set seed, then ``wang.tiling`` of enough tiles to cover the output, cropped from its
    upper-left corner, with the same seed.  Both stages are looked up by name, so the synth family does not import
    the wang family (which imports synth).  A tile set is kept per exemplar and seed, so scoring a seed that was
    timed reuses it; every new seed builds a new set, so a re-synthesis is timed as a whole tile set."""

    name = "wang.tiles"
    warm_up = False   # building a set to compile its kernels would cost as much as the timed run

    def __init__(self, tile: int = 64):
        self.tile = tile
        self._sets: dict = {}

    def __call__(self, *, exemplar, size, seed, ctx=None, **params):
        """The map of a tiling of ``size``; ``params`` go to ``wang.tiles``."""
        from btforge import stage
        from btforge.buffers import CoordMap
        key = (id(exemplar), seed, tuple(sorted(params.items())))
        if key not in self._sets:
            tiles = stage("wang.tiles")(exemplar=exemplar, seed=seed, tile=self.tile, **params,
                                        **({"ctx": ctx} if ctx else {}))["tiles"]
            self._sets[key] = (exemplar, tiles)   # the exemplar is kept so that its id is not reused
        tiles = self._sets[key][1]
        rows, cols = (-(-int(side) // tiles.tile) for side in size)
        laid = stage("wang.tiling")(tiles=tiles, rows=rows, cols=cols, seed=seed)["coords"]
        h, w = (int(side) for side in size)
        return {"coords": CoordMap(_top_left(laid.coords, h, w), laid.source_size, _top_left(laid.blend_coords, h, w),
                                   _top_left(laid.blend_weight, h, w), wrap=False, tile=laid.tile)}


def _top_left(array: np.ndarray, height: int, width: int) -> np.ndarray:
    """The first ``height`` rows and ``width`` columns of a map's layer (an empty blend layer as it is)."""
    return np.ascontiguousarray(array[:height, :width]) if array.size else array


def bench_synthesizers(only: set[str]) -> dict:
    """The synthesizers the bench runs, by name: every registered synthesizer and, where the wang family is
    registered, :class:`WangTiling`; with ``only``, those named there."""
    from btforge.registry import default_registry
    chosen = dict(synthesizers())
    if WangTiling.name in default_registry().stages:
        chosen[WangTiling.name] = WangTiling()
    return {name: st for name, st in chosen.items() if not only or name in only}


def score_map(model, coords, lights) -> dict:
    from btforge import stage
    output = stage("synth.materialize")(coords=coords, source=model)["output"]
    values = stage("synth.score")(output=output, exemplar=model, coords=coords, lights=lights)["scores"].values
    return {k: values.get(k) for k in SCORE_KEYS}


def time_synthesizer(st, model, size: int, repeat: int, params: dict | None = None) -> dict:
    """First run (analysis + synthesis), then ``repeat`` runs with other seeds (cached analysis): seconds.
    ``params``: the synthesizer's params other than its defaults."""
    params = params or {}
    from btforge.context import StageContext
    if getattr(st, "warm_up", True):  # kernel builds outside the timing (the analysis is per exemplar)
        try:
            st(exemplar=model, size=[32, 32], seed=99, **params)
        except BtforgeInputError:   # params that need a larger output (a quilt block over 32): warm up at its size
            st(exemplar=model, size=[size, size], seed=99, **params)
    from .search import clear_caches
    clear_caches()
    ctx = StageContext(node="bench", quiet=True)
    start = time.perf_counter()
    coords = st(ctx=ctx, exemplar=model, size=[size, size], seed=0, **params)["coords"]
    first = time.perf_counter() - start
    again = []
    for seed in range(1, repeat + 1):
        start = time.perf_counter()
        st(exemplar=model, size=[size, size], seed=seed, **params)
        again.append(time.perf_counter() - start)
    synthesis = statistics.median(again)
    return {"coords": coords, "first_s": first, "analysis_s": max(0.0, first - synthesis), "synthesis_s": synthesis,
            "notes": dict(ctx.notes)}


def measure_search(model, queries: int = RECALL_QUERIES, k: int = 6) -> dict:
    """The shared search on the exemplar's 5 x 5 neighbourhoods: fast build/query, exact query, recall at k; the
    self-join of every texel (itself left out) and its recall."""
    from . import search
    from .selfjoin import self_join
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
    p.add_argument("--exemplar", required=True, help="the capture (.lp), PTM file (.ptm) or PTM in relight's web "
                   "layout (its info.json) whose central crops are the exemplars (FILE@ROW,COL: the crops with "
                   "their upper-left texel there), 'procedural' for the demo material, or 'procedural:PATTERN' for "
                   "one of its patterns (stones, plaster, fibres, cobbles, gravel, strands, stucco, cracks)")
    p.add_argument("--out", required=True, help="folder for synthesis.csv, seeds.csv, search.csv, synthesis.png and "
                   "one sheet per exemplar size (sheet_NAME_HxW.png: the exemplar and every output at two lights, "
                   "with the measures of what the eye sees)")
    p.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="exemplar sides (default 64 128 192 256)")
    p.add_argument("--size", type=int, default=256, help="output side in texels (default 256)")
    p.add_argument("--fit", choices=sorted(FITS), default="lrgb", help="the PTM the crops are fitted as: lrgb "
                   "(default) or rgb, a linear RGB PTM, which blends, so the synthesizers feather their seams "
                   "(a .ptm file keeps its own variant)")
    p.add_argument("--repeat", type=int, default=1, help="re-syntheses with cached analysis; the median is reported")
    p.add_argument("--only", action="append", help="only these synthesizers (stage names)")
    p.add_argument("--lights", type=int, default=8, help="probe lights of the scores (default 8)")
    p.add_argument("--no-search", action="store_true", help="leave out the shared search's figures (search.csv)")
    p.add_argument("--seeds", type=int, default=1, help="score seeds 0 .. N-1 (and N baselines) and report "
                   "each score's median (seeds.csv: every seed's): one seed's sliced-Wasserstein distance varies by "
                   "up to 2x (default 1)")
    p.add_argument("--set", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                   help="run a synthesizer with a param other than its default, e.g. --set synth.quilt.block=24 or "
                   "--set wang.tiles.typical=0.85 (repeatable)")
    return p


def synthesizer_params(sets: dict, chosen: dict) -> dict[str, dict]:
    """``{'STAGE.PARAM': value}`` as params per chosen synthesizer; every unknown stage or param named at once."""
    from btforge.registry import default_registry
    params: dict[str, dict] = {name: {} for name in chosen}
    problems = []
    for key, value in sets.items():
        name, _, param = key.rpartition(".")
        if name not in chosen:
            problems.append(f"--set {key}: '{name}' is not a synthesizer this bench runs ({', '.join(chosen)})")
            continue
        declared = [p.name for p in default_registry().stage(name).params]
        if param not in declared:
            problems.append(f"--set {key}: {name} has no param '{param}' (its params: {', '.join(declared)})")
            continue
        params[name][param] = value
    if problems:
        raise BtforgeInputError("btforge bench synthesis", "; ".join(problems),
                                "name a synthesizer of --only (or of the bench's list) and one of its params")
    return params


def bench_synthesis(args: list[str]) -> int:
    """Synthesis quality (scores) against analysis and synthesis time, per synthesizer and exemplar size."""
    from .features import probe_lights
    opts = _parser().parse_args(args)
    lights = [list(map(float, light)) for light in probe_lights(opts.lights)]
    from btforge.registry import default_registry
    only = {default_registry().aliases.get(n, n) for n in opts.only or ()}  # old stage names still select
    chosen = bench_synthesizers(only)
    from btforge.cli import parse_sets
    params = synthesizer_params(parse_sets(opts.set), chosen)
    target = Path(opts.out)
    rows, search_rows, seed_rows = [], [], []
    for crop in opts.sizes:
        model = exemplar_model(opts.exemplar, crop, opts.fit)
        label = f"{model.height}x{model.width}"
        if not opts.no_search:
            search_rows.append({"exemplar": label, **_search_figures(model)})
        per_seed = [score_map(model, shuffled_blocks((model.height, model.width), (opts.size, opts.size), seed=seed),
                              lights) for seed in range(opts.seeds)]
        baseline = median_scores(per_seed)
        rows.append({"synthesizer": "shuffled blocks", "exemplar": label, "analysis_s": 0.0, "synthesis_s": 0.0,
                     **{k: _round(v) for k, v in baseline.items()}, "targets_missed": _missed(baseline)})
        seed_rows += seed_table("shuffled blocks", label, per_seed)
        outputs = {}
        for name, st in chosen.items():
            try:
                row, outputs[name], per_seed = _synthesizer_row(st, name, model, label, opts, lights, params[name])
            except BtforgeInputError as refused:   # e.g. an exemplar smaller than Wang tiles need
                print(f"{label} {name}: skipped, {refused}", file=sys.stderr)
                continue
            rows.append(row)
            seed_rows += seed_table(name, label, per_seed)
        write_sheet(target / f"sheet_{_slug(opts.exemplar)}_{label}.png", model, outputs,
                    {r["synthesizer"]: r for r in rows if r["exemplar"] == label},
                    f"{opts.size}x{opts.size} from {label} of {_slug(opts.exemplar)}  (!: a target missed)")
    _write_tables(target, opts, rows, search_rows, seed_rows)
    print(_table(rows))
    if search_rows:
        print(_table(search_rows))
    return 0


def _slug(exemplar: str) -> str:
    """A short name of an exemplar argument: the capture's folder, the .ptm file's stem, or the pattern."""
    if exemplar.startswith(PROCEDURAL):
        return exemplar.replace(":", "_")
    file, origin = crop_origin(exemplar)
    path = Path(file)
    name = path.stem if path.suffix == ".ptm" else path.parent.name or path.stem
    return name if origin is None else f"{name}_at_{origin[0]}_{origin[1]}"


def _search_figures(model) -> dict:
    found = measure_search(model)
    print(f"{model.height}x{model.width} search: recall {found['recall']:.3f}, distance ratio "
          f"{found['distance_ratio']:.4f}, fast build {found['fast_build_s']:.2f} s + "
          f"{found['fast_query_s_per_1000']:.3f} s / 1000 queries, exact {found['exact_query_s_per_1000']:.3f} s / "
          f"1000 queries; self-join {found['self_join_s']:.2f} s, recall {found['self_join_recall']:.3f}",
          file=sys.stderr)
    return {k: _round(v) for k, v in found.items()}


def _synthesizer_row(st, name: str, model, label: str, opts, lights, params: dict) -> tuple[dict, object, list]:
    """One synthesizer's timings and median scores on one exemplar (at ``params``), its first map, and every seed's
    scores."""
    timed = time_synthesizer(st, model, opts.size, opts.repeat, params)
    per_seed = [score_map(model, timed["coords"], lights)] + [
        score_map(model, st(exemplar=model, size=[opts.size, opts.size], seed=seed, **params)["coords"], lights)
        for seed in range(1, opts.seeds)]
    scores = median_scores(per_seed)
    row = {"synthesizer": name, "exemplar": label, "analysis_s": _round(timed["analysis_s"]),
           "synthesis_s": _round(timed["synthesis_s"]), **{k: _round(v) for k, v in scores.items()},
           "targets_missed": _missed(scores)}
    eye = "  ".join(f"{title} {_short(scores[key])}" for key, title in EYE_KEYS.items())
    print(f"{label} {name:12s} analysis {timed['analysis_s']:7.3f} s  synthesis {timed['synthesis_s']:7.3f} s  "
          f"{eye}{_swd_range(per_seed)}  missed: {row['targets_missed']}", file=sys.stderr)
    return row, timed["coords"], per_seed


def seed_table(name: str, label: str, per_seed: list[dict]) -> list[dict]:
    """One row per seed of a synthesizer's (or the baseline's) scores on one exemplar: what the medians of
    ``synthesis.csv`` hide, for ``seeds.csv``."""
    return [{"synthesizer": name, "exemplar": label, "seed": seed, **{k: _round(v) for k, v in scores.items()},
             "targets_missed": _missed(scores)} for seed, scores in enumerate(per_seed)]


def _swd_range(per_seed: list[dict]) -> str:
    """`` (seeds a-b)``: the range of SWD over the shuffled blocks over more than one seed, else nothing."""
    values = [r["swd_vs_shuffled_blocks"] for r in per_seed if r.get("swd_vs_shuffled_blocks") is not None]
    return f" (seeds {min(values):.2f}-{max(values):.2f})" if len(values) > 1 else ""


def _short(value) -> str:
    return "-" if value is None else f"{value:.2f}"


#: The measure behind each target of :func:`.visibility.missed_targets`.
TARGET_KEYS = {"seams": "seam_visibility", "straight": "straight_seam_visibility", "evenness": "evenness",
               "swd": "swd_vs_shuffled_blocks"}
#: Each measure's bound, to show a missed value that rounds to its bound with the digits that tell them apart.
TARGET_BOUNDS = {"seam_visibility": visibility.SEAM_TARGET, "straight_seam_visibility": visibility.STRAIGHT_TARGET,
                 "evenness": visibility.EVENNESS_TARGET, "swd_vs_shuffled_blocks": visibility.SWD_TARGET}


def _missed(scores: dict) -> str:
    """The targets ``scores`` miss, space-separated, or ``none``: the ``targets_missed`` column."""
    return " ".join(visibility.missed_targets(scores)) or "none"


def _write_tables(target: Path, opts, rows: list[dict], search_rows: list[dict], seed_rows: list[dict]) -> None:
    from btforge.atomic import atomic_write_text
    from btforge.plot import scatter_png
    for filename, table in (("synthesis.csv", rows), ("search.csv", search_rows), ("seeds.csv", seed_rows)):
        if not table:
            continue
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows(table)
        atomic_write_text(target / filename, buffer.getvalue())
    timed_rows = [r for r in rows if r["synthesizer"] != "shuffled blocks"]
    scatter_png(target / "synthesis.png", [r["analysis_s"] + r["synthesis_s"] for r in timed_rows],
                [r["texture_statistics"] for r in timed_rows],
                [f"{r['synthesizer']} {r['exemplar']}" for r in timed_rows], [r["synthesizer"] for r in timed_rows],
                title=f"{opts.size}x{opts.size} outputs from crops of {_slug(opts.exemplar)}",
                xlabel="analysis + synthesis seconds", ylabel="texture statistics ratio (1 = exemplar vs itself)",
                higher_is_better=False)


def write_sheet(path: Path, model, outputs: dict, rows: dict, header: str) -> None:
    """One labelled PNG: the exemplar and each synthesizer's output at the same scale (one texel, one pixel),
    each under the two :data:`SHEET_LIGHTS` (rows), shown alike (:func:`display_levels` of the exemplar)."""
    from btforge.atomic import atomic_write_bytes
    from btforge.plot import labelled_grid, light_label

    from .scoring import _relight
    lights = np.array(SHEET_LIGHTS, np.float64)
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    exemplar = _relight(model, lights, "exemplar")
    levels = [display_levels(frame) for frame in exemplar]
    images = {"exemplar": exemplar}
    for name, coords in outputs.items():
        images[name] = _relight(coords.apply(model), lights, "output")
    h = max(im.shape[1] for im in images.values())
    w = max(im.shape[2] for im in images.values())
    tiles, labels = [], []
    for li, light in enumerate(lights):
        for name, im in images.items():
            tile = np.zeros((h, w, 3), np.uint8)
            tile[:im.shape[1], :im.shape[2]] = shown(_rgb(im[li]), levels[li])
            tiles.append(tile)
            labels.append(_sheet_label(name, rows.get(name), light_label(light), im.shape[1:3]))
    sheet = labelled_grid(tiles, labels, columns=len(images), header=header, strip=40)
    buffer = io.BytesIO()
    sheet.save(buffer, format="PNG", optimize=True)
    atomic_write_bytes(path, buffer.getvalue())


#: Percentile of the exemplar's display values (its radiance over the white point, sRGB-encoded) a sheet shows as
#: black; white is the scores' white point (the 99.5th percentile of radiance).
BLACK_PERCENTILE = 0.5
#: Highest black level, a stretch of at most 50: an exemplar of (near) constant radiance is not divided by zero.
BLACK_CAP = 0.98


def display_levels(exemplar: np.ndarray) -> tuple[float, float]:
    """``(white, black)`` for one light's exemplar radiance ``[H, W, C]``: ``white`` the linear radiance shown as
    white (the scores' white point), ``black`` the display value (0..1, after ``/ white`` and the sRGB curve)
    shown as black (:data:`BLACK_PERCENTILE`).  Levels, as an image editor sets them: a relief of low contrast on
    a grey ground (radiance within a few per cent of its white) would otherwise fill its tile with one near-white
    grey in which no shape shows.  Where the darkest texels are black already, the picture is as exposed by its
    white alone."""
    from btforge.buffers import linear_to_srgb

    from .features import white_points
    white = float(white_points(exemplar[None])[0])
    black = float(np.percentile(linear_to_srgb(_rgb(exemplar) / white), BLACK_PERCENTILE))
    return white, min(black, BLACK_CAP)


def shown(image: np.ndarray, levels: tuple[float, float]) -> np.ndarray:
    """8-bit sRGB of linear radiance ``image [H, W, 3]`` at :func:`display_levels` ``levels``."""
    from btforge.buffers import linear_to_srgb
    white, black = levels
    encoded = (linear_to_srgb(image / white) - black) / (1.0 - black)
    return np.round(np.clip(encoded, 0.0, 1.0) * 255).astype(np.uint8)


def _rgb(image: np.ndarray) -> np.ndarray:
    return image if image.shape[-1] == 3 else np.repeat(image[..., :1], 3, axis=-1)


def _sheet_label(name: str, row: dict | None, light: str, size) -> str:
    first = f"{name} {size[0]}x{size[1]}, {light}"
    if row is None:
        return first
    missed = {TARGET_KEYS[target] for target in row.get("targets_missed", "").split() if target in TARGET_KEYS}
    measures = [f"{title} {_marked(row.get(key), key in missed, TARGET_BOUNDS.get(key))}"
                for key, title in EYE_KEYS.items() if key not in TILING_KEYS or row.get(key) is not None]
    # three a line: a 256-texel tile holds about 45 characters of the default font
    return "\n".join([first] + ["  ".join(measures[i:i + 3]) for i in range(0, len(measures), 3)])


def _marked(value, missed: bool, bound: float | None) -> str:
    """A measure as a sheet shows it: two decimals, four where a missed value would show as its bound (1.3003
    against 1.3), and "!" when its target is missed."""
    if not missed:
        return _short(value)
    exact = value is not None and bound is not None and f"{value:.2f}" == f"{bound:.2f}"
    return (f"{value:.4f}" if exact else _short(value)) + "!"


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


# ----------------------------------------------------------------------------------------------- quilting benchmark


def smooth_fields(size: int, channels: int, seed: int = 0, sigma: float = 3.0) -> np.ndarray:
    """``[size, size, channels]`` float32 periodic random fields, Gaussian-smoothed, zero mean, unit variance."""
    from scipy.ndimage import gaussian_filter
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((channels, size, size))
    fields = np.stack([gaussian_filter(n, sigma, mode="wrap") + 0.35 * gaussian_filter(n, sigma / 3, mode="wrap")
                       for n in noise], axis=-1)
    fields -= fields.mean(axis=(0, 1))
    fields /= fields.std(axis=(0, 1)) + 1e-12
    return fields.astype(np.float32)


def smooth_ptm_exemplar(size: int = 128, seed: int = 0, sigma: float = 3.0):
    """An lrgb PTM (orthonormal basis) whose 6 coefficients and 3 colours are random smooth fields (``sigma``: their
    smoothing, :func:`smooth_fields`)."""
    from btforge.plugins.ptm.model import PTMModel
    f = smooth_fields(size, 9, seed, sigma)
    scale = np.array([0.15, 0.08, 0.08, 0.05, 0.04, 0.04], np.float32)
    coeffs = f[..., :6] * scale
    coeffs[..., 0] += 0.8  # the constant term: mean brightness
    albedo = np.clip(0.55 + 0.15 * f[..., 6:], 0.0, 1.0)
    return PTMModel(coeffs[:, :, None, :].astype(np.float32), albedo.astype(np.float32), "lrgb", "linear",
                    basis="orthonormal")


def benchmark_quilt(exemplar_size: int = 128, output_size: int = 512, block: int = 32, seed: int = 0,
                    repeat: int = 3, *, exemplar: PerTexel | None = None, overlap: int = 6,
                    tolerance: float = 0.1) -> dict:
    """Time brute-force and rejection quilting on the same exemplar and check their picks are identical.

    The exemplar is the central ``exemplar_size`` crop of ``exemplar`` when given, else a linear lrgb PTM of random
    smooth fields (compared by its perceptual vectors: 25 lights' display values reduced to 16 principal
    components).  Kernels are compiled by a warm-up run first; each search then runs ``repeat`` times and medians
    are reported (seconds), with the speed-up, the mean fraction of candidates rejected after each projection, and
    the fraction whose full distance was computed.
    """
    if exemplar is not None:
        source = central_crop(exemplar, exemplar_size)
    else:
        source = smooth_ptm_exemplar(exemplar_size, seed)
    feats = texel_features(source)
    size = (output_size, output_size)
    small = feats[:min(feats.shape[0], 2 * block), :min(feats.shape[1], 2 * block)]
    for method in SEARCHES:  # compile the kernels outside the timings
        quilt_features(small, (block * 2, block * 2), block, overlap, search=method, seed=seed)
    times: dict[str, list[float]] = {m: [] for m in SEARCHES}
    cpu: dict[str, list[float]] = {m: [] for m in SEARCHES}
    results = {}
    for _ in range(repeat):  # interleaved, so both searches see the same machine load
        for method in ("brute", "rejection"):
            t0, c0 = time.perf_counter(), time.process_time()
            res = quilt_features(feats, size, block, overlap, search=method, tolerance=tolerance, seed=seed)
            times[method].append(time.perf_counter() - t0)
            cpu[method].append(time.process_time() - c0)
            if method in results and not np.array_equal(results[method].coords.coords, res.coords.coords):
                raise AssertionError(f"{method} quilting is not deterministic")
            results[method] = res
    identical = bool(np.array_equal(results["brute"].coords.coords, results["rejection"].coords.coords))
    rej = results["rejection"].stats
    brute_s, rejection_s = statistics.median(times["brute"]), statistics.median(times["rejection"])
    return {
        "device": get_backend().description,
        "exemplar": "given (central crop)" if exemplar is not None else "random smooth fields (lrgb PTM)",
        "exemplar_size": list(feats.shape[:2]),
        "features": int(feats.shape[2]),
        "output_size": list(size),
        "block": block,
        "overlap": overlap,
        "tolerance": tolerance,
        "blocks": rej["blocks"],
        "candidates": rej["candidates"],
        "brute_s": round(brute_s, 3),
        "rejection_s": round(rejection_s, 3),
        "speedup": round(brute_s / rejection_s, 2),
        "brute_cpu_s": round(statistics.median(cpu["brute"]), 3),
        "rejection_cpu_s": round(statistics.median(cpu["rejection"]), 3),
        "speedup_cpu": round(statistics.median(cpu["brute"]) / statistics.median(cpu["rejection"]), 2),
        "brute_search_s": results["brute"].stats["search_s"],
        "rejection_search_s": rej["search_s"],
        "rejection_precompute_s": rej["precompute_s"],
        "rejected_after_projection": rej["rejected_after_projection"],
        "full_distance_fraction": rej["full_distance_fraction"],
        "identical_picks": identical,
        "times": {m: [round(t, 3) for t in v] for m, v in times.items()},
    }


# ----------------------------------------------------------------------------------------------- k-coherence benchmark


def benchmark_exemplar(size: int = 64, lights: int = 16, seed: int = 1) -> PerTexel:
    """A ``size x size`` single-view stack of the procedural demo material under ``lights`` lights."""
    from btforge.buffers import SampleStack
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights

    material = make_material(size, size, bumps=max(8, size * size // 200), seed=seed)
    dirs = hemisphere_lights(lights, min_elevation_deg=20.0)
    images = render_lights(material, dirs)                      # [L, H, W, 3]
    return SampleStack(np.ascontiguousarray(images[None], np.float32), dirs, [[0.0, 0.0, 1.0]])


def benchmark_kcoherence(exemplar_size: int = 64, size: int = 256, *, k: int = 6, neighborhood: int = 5,
                         levels: int = 3, wrap: bool = False, repeat: int = 3, seed: int = 0,
                         search: str = "fast", cold: bool = True, texels: str = "stack",
                         recall_samples: int = 0, blocks: int = 0) -> dict:
    """Median wall time of the ``synth.kcoherence`` stage (kernels compiled beforehand; with ``cold`` every repeat
    analyses the exemplar again, else the cached analysis is reused).  ``blocks`` is the stage's param: 0 (the
    default here) times the hierarchical synthesis over ``levels`` levels, as in Tong et al. 2002;
    the stage's own default (-1) starts from stratified blocks and analyses the finest level only.

    ``texels``: ``stack`` (the demo material under 16 lights: 48 values a texel, 32-D appearance vectors),
    ``ptm`` (the same fitted as an orthonormal LRGB PTM: 9-D, the headline benchmark's texels) or the path of a
    ``.ptm`` file (its central ``exemplar_size`` square).  ``recall_samples`` > 0 also measures the finest
    level's coherence sets against the exact search at that many texels.

    Returns the figures as a dict: ``median_s`` (the whole stage call), ``analysis_median_s`` (textons and
    coherence sets of every level), ``synthesis_median_s`` (all passes), ``other_median_s`` (appearance vectors,
    building the CoordMap), ``cpu_median_s`` (process CPU time, all threads), the configuration and the device.
    """
    from btforge.context import StageContext

    from .search import clear_caches
    exemplar = _bench_texels(texels, exemplar_size)
    exemplar_size = exemplar.height
    params = dict(size=[size, size], k=k, neighborhood=neighborhood, levels=levels, wrap=wrap, seed=seed,
                  search=search, blocks=blocks)
    kcoherence(exemplar=exemplar, **{**params, "size": [16, 16]})  # warm-up: kernel builds
    totals, analysis, synthesis, cpu = [], [], [], []
    for _ in range(repeat):
        if cold:
            clear_caches()
        ctx = StageContext(node="bench", quiet=True)
        start, start_cpu = time.perf_counter(), time.process_time()
        kcoherence(ctx=ctx, exemplar=exemplar, **params)
        totals.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
        analysis.append(ctx.notes["seconds_analysis"])
        synthesis.append(ctx.notes["seconds_synthesis"])
    total = statistics.median(totals)
    return {
        "exemplar": [exemplar_size, exemplar_size], "size": [size, size], "k": k, "neighborhood": neighborhood,
        "levels": levels, "blocks": blocks, "wrap": wrap, "repeat": repeat, "search": search, "cold": cold,
        "device": get_backend().description,
        "median_s": total, "analysis_median_s": statistics.median(analysis),
        "synthesis_median_s": statistics.median(synthesis),
        "other_median_s": total - statistics.median(analysis) - statistics.median(synthesis),
        "cpu_median_s": statistics.median(cpu), "coherent_fraction": ctx.notes["coherent_fraction"],
        "causal_order": CAUSAL_ORDER, "texels": texels,
        **(kset_recall(texel_features(exemplar), k=k, neighborhood=neighborhood, levels=levels, search=search,
                       samples=recall_samples) if recall_samples and k > 1 else {}),
    }


def _bench_texels(texels: str, size: int) -> PerTexel:
    from btforge import stage
    if texels == "stack":
        return benchmark_exemplar(size)
    if texels == "ptm":
        return stage("ptm.fit")(stack=benchmark_exemplar(size), variant="lrgb", basis="orthonormal")["model"]
    return central_crop(stage("ptm.read")(path=texels)["model"], size)


def kset_recall(features: np.ndarray, *, k: int, neighborhood: int, levels: int, search: str,
                samples: int) -> dict:
    """The finest level's coherence sets (from the cached analysis) against the exact search at ``samples``
    texels: share of the true k - 1 most similar texels found, and the distance ratio (found over true)."""
    from .search import distance_ratio, knn, neighbourhood_vectors, recall, square_window
    level = analyse_exemplar(features, k=k, neighborhood=neighborhood, levels=levels, search=search)[0]
    h, w = level.height, level.width
    rows = np.sort(np.random.default_rng(0).choice(h * w, min(samples, h * w), replace=False))
    vectors = neighbourhood_vectors(normalise_features(features), square_window(neighborhood))
    ask = k - 1 + (2 * KSET_EXCLUDE + 1) ** 2
    idx, dist = knn(vectors, vectors[rows], ask, engine="exact")
    ys, xs = np.divmod(rows, w)
    ty, tx = np.divmod(idx, w)
    far = np.maximum(np.abs(ty - ys[:, None]), np.abs(tx - xs[:, None])) > KSET_EXCLUDE
    order = np.argsort(~far, axis=1, kind="stable")[:, :k - 1]   # the first k - 1 far entries, in list order
    true_idx, true_d = np.take_along_axis(idx, order, 1), np.take_along_axis(dist, order, 1)
    return {"kset_recall": round(recall(level.ksets[rows, 1:], true_idx), 4),
            "kset_distance_ratio": round(distance_ratio(level.kset_cost[rows], true_d), 4),
            "kset_recall_samples": len(rows)}
