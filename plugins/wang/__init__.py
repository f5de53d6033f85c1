"""Tileable BTFs after Leung et al. 2007: Wang-tile sets by graph cuts in the compressed domain, BTFel tables,
stochastic tilings of planes and of meshes' UV grids.

Stages: ``wang.tiles`` (exemplar -> ``TileSet``), ``wang.tiling`` (``TileSet`` -> ``CoordMap`` of a plane tiling,
replayed by ``synth.materialize`` and ``render.image``'s ``coord_map``), ``wang.write_tiles`` / ``wang.read_tiles`` (the ``.wang``
archive, see :mod:`.tileset`).  ``synth.score`` measures a ``TileSet`` wired to its ``tiles`` port through
:meth:`TileSet.seam_scores` (seam ratios over every valid adjacency and 2 x 2 configuration, colour mismatches
and tile use of a tiling).  The renderer dresses meshes with a ``TileSet`` directly (scene key
``tiles: true``).
"""
from __future__ import annotations

import time

import numpy as np

from btforge import REQUIRED, Param, declare_stage, hookimpl
from btforge.buffers import CoordMap
from btforge.errors import BtforgeInputError
from btforge.plugins.synth.feather import FEATHER, by_grain, feathered, grain, local_steps, records_mix
from btforge.plugins.synth.refine import APPEARANCE_CLASSES
from btforge.plugins.synth.synthesizer import feather_param, seam_weight_param

from .optimise import BALANCE, CONTRAST, ITERATIONS, OCCURRENCE, PIN, POLISH, SEAM_WEIGHT
from .tileset import TileSet

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for

SEARCH_DIMS = 16  # principal components of the appearance features the placement search compares
#: The seams inside the tiles are feathered where their step is over this many times the exemplar's own steps
#: around the two sources (the synthesizers: 1.5) on a grainy exemplar ...  The tiles' interiors are cut into
#: smaller pieces than the synthesizers' outputs: at 1.5 a tenth of plaster's texels blended, against a twentieth
#: for k-coherence, and the cross-fades softened its grain (SWD over the shuffled blocks over seeds 0-3 1.41 -> 1.57,
#: a miss); at 2 the share is comparable.
TILE_FEATHER_STEP = 2.0
#: ... and this many times on a smooth one, where a cut through soft shading is a step the eye finds and a
#: cross-fade blends two ramps, not two grains: at 2 the bumps' and two leaves' seams missed (1.31-1.34 x the
#: exemplar's neighbour jump at seeds 0-1), at 1.5 the leaves pass (1.22-1.24) and the bumps reach 1.31 (Benchmarks).
SMOOTH_FEATHER_STEP = 1.5


def tile_feather_step(grain_ratio: float) -> float:
    """The step factor over which the seams inside the tiles are feathered, for an exemplar of ``grain_ratio``
    (:func:`~btforge.plugins.synth.feather.grain`): :data:`SMOOTH_FEATHER_STEP` on a smooth exemplar,
    :data:`TILE_FEATHER_STEP` on a grainy one (:func:`~btforge.plugins.synth.feather.by_grain`)."""
    return by_grain(grain_ratio, SMOOTH_FEATHER_STEP, TILE_FEATHER_STEP)


def texel_bytes(buffer) -> int:
    """Bytes of one texel's record in a per-texel buffer (all its texel fields)."""
    n = buffer.height * buffer.width
    return int(sum(getattr(buffer, f).nbytes for f in buffer.texel_fields) // max(n, 1))


def build_tile_set(exemplar, *, tile=64, edge=0, colors=(2, 2), variants=1, seed=0, cut="graph",
                   engine="opencl", optimise=None, strip_refine=None, feather=FEATHER, **options):
    """``(TileSet, Synthesis, seam ratios)`` of an exemplar: the work of ``wang.tiles`` (``optimise``: keywords
    of :func:`.optimise.optimise_tiles`, its defaults when left out; ``{"iterations": 0}`` turns it off;
    ``strip_refine``: keywords of :func:`.synthesis.refined_strip`, by default the iterations, polish and seam
    weight of ``optimise``; ``feather``: the band of :func:`btforge.plugins.synth.feather.feathered` over each
    tile's interior seams)."""
    from . import seams
    from .features import appearance_features, search_features
    from .synthesis import synthesize_tiles
    full = appearance_features(exemplar)
    feats = search_features(full, SEARCH_DIMS, seed)
    h = tile // 4 if edge == 0 else edge
    if strip_refine is None:
        strip_refine = {key: (optimise or {}).get(key, default) for key, default in
                        (("iterations", ITERATIONS), ("polish", POLISH), ("seam_weight", SEAM_WEIGHT))}
    synthesis = synthesize_tiles(feats, tile, h, tuple(colors), variants, seed, cut=cut, engine=engine,
                                 strip_refine=strip_refine, **options)
    from .optimise import optimise_tiles   # texture optimisation of the interiors, borders held
    start = time.perf_counter()
    synthesis.tile_coords = optimise_tiles(full, synthesis.tile_coords, seed=seed, colors=synthesis.tile_colors,
                                           colour_counts=tuple(colors), **(optimise or {}))
    synthesis.timings["refine"] = time.perf_counter() - start
    measured = seams.tile_set_seams(synthesis.tile_coords, synthesis.tile_colors, full, h)
    reference = seams.exemplar_reference(full)
    ref_mean = np.array([np.mean(reference["v"]), np.mean(reference["h"])] * 2)
    edge_seams = (measured["edges"] / np.maximum(ref_mean, 1e-30)).astype(np.float32)
    source_size = (exemplar.height, exemplar.width)
    blend = feathered_tiles(synthesis.tile_coords, source_size, feather, records_mix(exemplar), full)
    tiles = TileSet.from_coords(synthesis.tile_coords, synthesis.tile_colors, edge_seams, colors_h=colors[0],
                                colors_v=colors[1], source_size=source_size, edge=h, variants=variants,
                                texel_bytes=texel_bytes(exemplar), **blend)
    return tiles, synthesis, seams.seam_ratios(measured, reference)


def feathered_tiles(tile_coords: np.ndarray, source_size, band: int, mixes: bool, feats: np.ndarray,
                    step: float | None = None) -> dict:
    """The blend layer (``blend_coords``, ``blend_weight``; empty where nothing blends) that feathers the seams
    inside each tile as the synthesizers feather theirs, over ``step`` x the exemplar's own steps (by default
    :func:`tile_feather_step` of its grain).  Each tile is feathered on its own: the seams across a tile border
    continue the shared edge strips, and the measure leaves the borders out."""
    if band <= 0 or not mixes:
        return {}
    steps = local_steps(np.asarray(feats, np.float32))   # the exemplar's, once for every tile
    if step is None:
        step = tile_feather_step(grain(feats, steps))
    partners, weights = tile_coords.copy(), np.zeros(tile_coords.shape[:3], np.float32)
    for t, coords in enumerate(tile_coords):
        tile_map = feathered(CoordMap(np.ascontiguousarray(coords), source_size), band, mixes, feats, step, steps)
        if tile_map.blend_weight.size:
            partners[t], weights[t] = tile_map.blend_coords, tile_map.blend_weight
    if not weights.any():
        return {}
    return {"blend_coords": partners, "blend_weight": weights}


@declare_stage(
    "wang.tiles",
    inputs={"exemplar": "PerTexel"},
    outputs={"tiles": "TileSet"},
    params=[
        Param("tile", "int", 64, "tile size w in texels", low=4, high=1024),
        Param("edge", "int", 0, "edge-strip thickness h in texels, even (0: tile / 4)", low=0, high=512),
        Param("colors", "ints", (2, 2), "edge colours [horizontal, vertical]", length=2, low=1, high=8),
        Param("variants", "int", 1, "tiles (interiors) per colour combination", low=1, high=16),
        Param("seed", "int", 0, "random seed"),
        Param("usage", "float", 4.0, "how strongly placements avoid exemplar texels earlier patches used, so the "
              "tiles spread over the whole exemplar (0: off; per known texel and earlier use, in usage_unit)",
              low=0.0, high=100.0),
        Param("usage_unit", "choice", "neighbour", "the usage term's unit: neighbour (the squared median distance "
              "between neighbouring texels) or match (the filling's match level: the median error per known texel "
              "of the placements a draw chooses among, so a weight means the same against matching on smooth and "
              "on grainy exemplars; try usage 1, refine 8)", choices=("neighbour", "match")),
        Param("interior", "int", 0, "side in texels of the windows that fill the tiles' interiors (0: 1.5 x edge, "
              "24 for tiles of 64); larger windows copy larger exemplar pieces, nearer the exemplar's patch "
              "statistics, but leave longer straight cuts (at most tile - edge)", low=0, high=1024),
        Param("centre", "float", 0.5, "side, as a share of the tile's, of an exemplar piece laid whole at each "
              "tile's centre before its interior is filled, from the place the tile set has used least so far, so "
              "the tiles spread over the exemplar and keep its larger structures (0: off; at most 1 - edge / tile)",
              low=0.0, high=1.0),
        Param("edge_centre", "float", 0.5, "length, as a share of the tile's side, of an exemplar piece laid whole at "
              "the middle of each edge strip before the strip is filled, from the place the tile set has used least "
              "so far, so the tile borders do not all continue the corner samples' few, similar areas (0: off; at "
              "most 1 - edge / tile)", low=0.0, high=1.0),
        Param("typical", "float", 1.0, "share of the exemplar's places the tiles' pieces (the centre pieces and the "
              "filling's patches) may come from, those whose most unusual texel is least unusual first (1: every "
              "place); below 1 a rare, conspicuous part (a patch of gold on a brown ground) stays out of the tiles, "
              "where it would repeat wherever its tile is laid, at some cost to a stationary exemplar's patch "
              "statistics (try 0.85)", low=0.01, high=1.0),
        Param("rare", "float", 5.0, "a texel is rare where its unusualness (its appearance's distance from the median "
              "texel's) exceeds the upper quartile by this many interquartile ranges; pieces holding a rare texel stay "
              "out of the tiles, unless that would leave out half the places or more (0: off)", low=0.0, high=1000.0),
        Param("relax", "int", 6, "sweeps of texel-level seam relaxation after filling each strip and interior "
              "(0: off)", low=0, high=64),
        Param("refine", "int", ITERATIONS, "rounds of texture optimisation (the shared refinement of synth: 8 x 8 "
              "windows matched to the exemplar, kept whole where they match best and cut where the appearance "
              "agrees), first over each finished edge strip with its corner halves held, then over the finished "
              "tiles' interiors with their border rings held, so the tiles stay valid (0: off)",
              low=0, high=20),
        Param("occurrence", "float", OCCURRENCE, "weight of that refinement's occurrence term: exemplar windows "
              "already used beyond their fair share over the whole tile set cost more (0: plain texture optimisation)",
              low=0.0, high=100.0),
        Param("contrast", "float", CONTRAST, "weight of that refinement's contrast term: a candidate window with "
              "less variation than the output window it would replace costs contrast x the shortfall, so the rounds "
              "do not drift towards the exemplar's flatter areas and the set keeps its patch statistics (0: off)",
              low=0.0, high=1000.0),
        Param("balance", "float", BALANCE, "weight of that refinement's balance term: exemplar windows of the "
              f"appearance classes ({APPEARANCE_CLASSES} k-means classes of the exemplar's texels) the set already "
              "holds beyond their share of the exemplar cost more, so the rounds do not drift towards the exemplar's commonest areas "
              "and leave its sparser features (bumps, shadows) out (0: off)", low=0.0, high=1000.0),
        Param("polish", "int", POLISH, "final rounds of that refinement with 8 x 8 windows matched for their fit "
              "alone (no occurrence term): the cuts the earlier rounds left move to where the content agrees, while "
              "the exemplar areas used stay (0: none)", low=0, high=10),
        Param("pin", "int", PIN, "texels along each tile border the refinement leaves as the edge strips laid them "
              "(the tiles are refined laid as one valid periodic tiling, so the texels beyond see their neighbours)",
              low=1, high=256),
        seam_weight_param(SEAM_WEIGHT),
        feather_param(FEATHER, f"{SMOOTH_FEATHER_STEP:g} (smooth exemplars) to {TILE_FEATHER_STEP:g} (grainy ones)"),
    ],
    version="24",  # 24: straight seams in the edge strips and the interiors re-cut in bands of 12 texels on either side (were 8); 23: the seams inside the tiles feathered over 1.5 x the exemplar's own steps on smooth exemplars (grain up to 0.25), 2 x on grainy ones (from 0.5), linearly between (was 2 on all); 22: the interiors' refinement has a balance term of weight 16 (param balance); 21: straight seams whose re-cut bands overlap are re-cut in separate groups, so a sliver's far piece is offered across it; 20: each edge strip refined before the frames are cut from it (its corner halves held); 19: the seams inside the tiles cross-faded over 3 texels on either side (feather 3, was 1); 18: linear exemplars (stacks, linear fits of light only) compared as a screen shows them, at 25 probe lights sRGB-encoded, 16 principal components; 17: sRGB PTM, SH and HSH exemplars feathered too, their records mixed as display values; 16: the seams inside the tiles feathered on exemplars that blend (param feather, as the synthesizers'); 15: the refinement's vote weighs seams 4 x (param seam_weight: seams lower on every crop measured); 14: eight refinement rounds (were four) with a contrast term of weight 8 (param contrast): the set keeps its patch statistics; 13: the refinement's occurrence weight 0.5 (was 0.1) and one polish round (param polish); 12: the straight seams left in the tiles are re-cut in up to six passes (were two); 11: the re-cut weighs a straight seam edge that stays 1.5 x its appearance difference (about half the straight seams); 10: the re-cut sees straight seams that cross the held border ring whole (they were split into runs too short to re-cut); 9: the refinement lays the set as one valid periodic tiling and holds one texel (pin 1, was 2); 8: a least-used exemplar piece at each edge strip's middle (edge_centre 0.5); 7: the filling stops once a region is covered (its later patches never changed it); param typical (was centre_typical) ranks places by their most unusual texel and holds the filling's patches too; pieces holding a rare texel (param rare) stay out; 6: a least-used exemplar piece at each tile's centre (centre 0.5); 5: the straight seams left in the tiles are re-cut with bridging pieces too; 4: straight seams inside the tiles re-cut by minimum cuts, the refinement's candidate distances summed in a fixed order (OpenCL kernels); 3: the refinement's windows jittered one by one
)
def wang_tiles(ctx, exemplar, *, tile, edge, colors, variants, seed, usage, usage_unit, interior, centre,
               edge_centre, typical, rare, relax, refine, occurrence, contrast, balance, polish, pin, seam_weight,
               feather):
    """Synthesize a complete Wang-tile set of an exemplar by graph cuts in its compressed domain.

    The four steps of Leung et al. 2007: corner sampling (cuts between corner samples cached), edge strips
    filled between their corners by graph-cut patch filling with per-pixel error bookkeeping (Kwatra et al.
    2003), frames from the strips' halves, interiors filled with the frame held.  Each interior starts from an
    exemplar piece laid whole at the tile's centre (``centre``), from the place the set has used least so far, as
    Cohen et al. 2003 give each tile a sample of its own: grown from its frame alone, every interior would continue
    the few exemplar areas the corner samples came from.  Each edge strip, likewise, starts from a least-used piece
    at its middle (``edge_centre``): grown from its two corner samples alone, every strip would continue their few,
    similar areas, and lanes of them would run along every tile border.  A usage term (``usage``) spreads the
    patches over the whole exemplar; a texel-level relaxation (``relax``) moves seams to where patches agree; the
    shared refinement joins each strip's middle to its corner halves where the two sides agree (``refine`` rounds,
    the corner halves held), since every tile of the strip's colour shows its cuts; a
    texture optimisation of every interior with the tile borders held (``refine``, ``occurrence``, ``contrast``,
    ``balance``, ``polish``, ``pin``, ``seam_weight``) hides the cuts the filling left, and the seams inside the tiles that
    still stand out are cross-faded (``feather``, as the synthesizers do, on exemplars that blend).  Distances are
    Euclidean in the exemplar's appearance features (a double-SH model weighted by its hemisphere Gram matrix, an orthonormal
    PTM's coefficients, a stack's radiance); the placement search runs on OpenCL.  Every one of the
    ``colors[0]^2 * colors[1]^2 * variants`` tiles is built.  The report gives the time per step, the BTFel
    statistics (referenced share, bytes of table and indices) and the seam ratios.

    Outputs
    -------
    tiles : TileSet
        Edge colours per tile and the tiles as index maps into a BTFel table of exemplar texels.
    """
    from .synthesis import check_sizes
    h = tile // 4 if edge == 0 else edge
    check_sizes((exemplar.height, exemplar.width), tile, h, colors)
    tiles, synthesis, ratios = build_tile_set(exemplar, tile=tile, edge=edge, colors=colors, variants=variants,
                                              seed=seed, feather=feather, usage_weight=usage, usage_unit=usage_unit,
                                              interior=interior, centre=centre, edge_centre=edge_centre,
                                              typical=typical, rare=rare,
                                              relax=relax,
                                              optimise={"iterations": refine, "occurrence": occurrence,
                                                        "contrast": contrast, "balance": balance,
                                                        "polish": polish, "pin": pin,
                                                        "seam_weight": seam_weight})
    ctx.note("seconds", {k: round(v, 3) for k, v in synthesis.timings.items()})
    ctx.note("patches", synthesis.counts)
    ctx.note("btfels", tiles.statistics())
    ctx.note("seams", {k: round(v, 4) for k, v in ratios.items()})
    ctx.note("pixels_over_threshold", synthesis.unresolved)
    return {"tiles": tiles}


@declare_stage(
    "wang.tiling",
    inputs={"tiles": "TileSet"},
    outputs={"coords": "CoordMap"},
    params=[
        Param("rows", "int", 8, "tiles down", low=1, high=4096),
        Param("cols", "int", 8, "tiles across", low=1, high=4096),
        Param("periodic", "bool", False, "match colours across the wrap too, so the result tiles"),
        Param("seed", "int", 0, "random seed"),
    ],
)
def wang_tiling(ctx, tiles, *, rows, cols, periodic, seed):
    """Lay a valid stochastic Wang tiling of rows x cols tiles and output its coordinate map into the exemplar.

    Tile (i, j) covers rows ``i*w .. (i+1)*w - 1`` and columns ``j*w .. (j+1)*w - 1``.  Edge colours are drawn at
    random, so the tiling is not periodic; among draws, one that uses every tile is kept where there is room.
    ``synth.materialize`` and ``render.image``'s ``coord_map`` replay the map on the exemplar (or any buffer of it).  The map
    carries the tile size (``CoordMap.tile``), so seam measures can leave the tile borders out.
    """
    from .seams import tiling_report
    from .tiling import plane_tiling, tiling_map
    ids = plane_tiling(tiles, rows, cols, periodic, seed)
    ctx.note("tiling", tiling_report(ids, tiles.tile_colors, tiles.n_tiles, periodic))
    return {"coords": tiling_map(tiles, ids, periodic)}


@declare_stage("wang.write_tiles", deprecated_names=("tiles.write",), inputs={"tiles": "TileSet"},
               params=[Param("path", "outpath", REQUIRED, "the .wang archive to write (relative to --out)")],
               side_effects=True)
def tiles_write(ctx, tiles, *, path):
    """Write a tile set losslessly: a ZIP of manifest.json and .npy arrays (format in README, Wang tiles)."""
    if not str(path).endswith(".wang"):
        raise BtforgeInputError("wang.write_tiles 'path'", f"expected a .wang file, found {path!r}", "name it NAME.wang")
    tiles.write(ctx.paths.output(path))
    return {}


def _read_precheck(params, paths):
    from .tileset import read_manifest
    _, archive = read_manifest(paths.input(params["path"]))
    archive.close()
    return []


@declare_stage("wang.read_tiles", deprecated_names=("tiles.read",), outputs={"tiles": "TileSet"},
               params=[Param("path", "path", REQUIRED, "a .wang archive written by wang.write_tiles")],
               precheck=_read_precheck)
def tiles_read(ctx, *, path):
    """Read a tile set written by ``wang.write_tiles``."""
    from .tileset import read_tile_set
    tiles = read_tile_set(ctx.paths.input(path))
    ctx.note("btfels", tiles.statistics())
    return {"tiles": tiles}


@declare_stage("wang.sheet", deprecated_names=("tiles.sheet",), inputs={"tiles": "TileSet", "exemplar": "PerTexel"},
               params=[Param("path", "outpath", REQUIRED, "the .png file to write (relative to --out)"),
                       Param("light", "lights", ((0.0, 0.0, 1.0),), "the one light [[x, y, z]] the tiles are shown at"),
                       Param("columns", "int", 0, "tiles per row (0: a square layout)", low=0, high=4096)],
               side_effects=True)
def tiles_sheet(ctx, tiles, exemplar, *, path, light, columns):
    """Write a picture of a tile set: each tile relit at one light, framed by bars in its edge colours.

    N and S bars show the horizontal-edge colours, E and W bars the vertical-edge ones (a palette shared by no
    two colours), so matching edges can be checked by eye.  Exposed so that the exemplar's 99.5th percentile is
    white, sRGB-encoded.
    """
    from PIL import Image as PILImage

    from btforge.atomic import atomic_output_path

    from .sheet import tile_sheet
    if isinstance(light, str) or len(light) != 1:
        raise BtforgeInputError("wang.sheet 'light'", f"expected one light [[x, y, z]], found {light!r}")
    if (exemplar.height, exemplar.width) != tiles.source_size:
        raise BtforgeInputError("wang.sheet 'exemplar'", f"expected the {tiles.source_size[0]} x "
                                f"{tiles.source_size[1]} exemplar of the tile set, found {exemplar.height} x "
                                f"{exemplar.width}", "wire the buffer the tile set was synthesized from")
    pixels = tile_sheet(tiles, exemplar, np.asarray(light[0], np.float64), columns)
    with atomic_output_path(ctx.paths.output(path)) as temporary:
        PILImage.fromarray(pixels).save(temporary, format="PNG")
    ctx.note("size", list(pixels.shape[:2]))
    return {}


@hookimpl
def btforge_stages():
    return [wang_tiles, wang_tiling, tiles_write, tiles_read, tiles_sheet]


@hookimpl
def btforge_buffer_types():
    return [TileSet]


@hookimpl
def btforge_info_readers():
    from .tileset import describe
    return {".wang": describe}


@hookimpl
def btforge_bench_commands():
    from .bench import bench_wang
    return {"wang": bench_wang}
