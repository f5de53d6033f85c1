"""Wang tiles (Leung et al. 2007): placement kernel, cuts, tile sets, BTFel tables, tilings, seams, rendering."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from btforge.buffers import CoordMap
from btforge.context import StageContext
from btforge.errors import BtforgeInputError
from btforge.plugins.synth.scoring import score
from btforge.plugins.wang import build_tile_set, wang_tiles, wang_tiling
from btforge.plugins.wang.bench import procedural_exemplar
from btforge.plugins.wang.cuts import min_cut
from btforge.plugins.wang.placement import placement_errors_numpy, placement_errors_opencl
from btforge.plugins.wang.seams import corner_configurations, tiling_ids, tiling_report
from btforge.plugins.wang.synthesis import quadrant_ties, synthesize_tiles
from btforge.plugins.wang.tileset import TileSet, describe, read_tile_set
from btforge.plugins.wang.tiling import glue_mismatches, is_periodic, mesh_tiling, plane_tiling

SIZE, TILE, EDGE = 64, 32, 8


@pytest.fixture(scope="module")
def procedural():
    stack = procedural_exemplar(SIZE, lights=16)
    tiles, synthesis, ratios = build_tile_set(stack, tile=TILE, edge=EDGE, seed=0)
    return stack, tiles, synthesis, ratios


# ----------------------------------------------------------------------------------------------- kernels


def _placement_case(rng, kind: str, h=20, w=23, d=5, window=(6, 7)):
    feats = rng.normal(size=(h, w, d)).astype(np.float32)
    if kind == "constant":
        feats[:] = 0.25
    elif kind == "black":
        feats[:] = 0.0
    elif kind == "huge":
        feats *= 1e4
    elif kind == "tiny":
        feats *= 1e-6
    known = rng.random(window) < 0.5
    known[0, 0] = True
    offsets = np.argwhere(known)
    target = feats[3 + offsets[:, 0], 4 + offsets[:, 1]] + rng.normal(size=(len(offsets), d)).astype(np.float32) * (
        0 if kind in ("constant", "black") else 0.1 * np.abs(feats).max())
    return feats, offsets, target.astype(np.float32), window


@pytest.mark.parametrize("kind", ["random", "constant", "black", "huge", "tiny"])
@pytest.mark.parametrize("stride", [1, 2])
def test_placement_kernel_matches_its_numpy_twin(kind, stride):
    feats, offsets, target, window = _placement_case(np.random.default_rng(4), kind)
    ref = placement_errors_numpy(feats, offsets, target, window, stride)
    out = placement_errors_opencl(feats, offsets, target, window, stride)
    assert out.shape == ref.shape and np.isfinite(out).all()
    np.testing.assert_allclose(out, ref, rtol=2e-5, atol=1e-6 * max(1.0, float(np.abs(ref).max())))
    if kind in ("constant", "black"):
        assert np.all(out == 0)


@settings(max_examples=8, deadline=None)
@given(st.integers(1, 6), st.integers(1, 6), st.integers(1, 9), st.integers(0, 2 ** 31 - 1))
def test_placement_kernel_on_random_windows(ph, pw, d, seed):
    rng = np.random.default_rng(seed)
    feats = rng.normal(size=(ph + 4, pw + 3, d)).astype(np.float32)
    offsets = np.argwhere(rng.random((ph, pw)) < 0.6)
    target = rng.normal(size=(len(offsets), d)).astype(np.float32)
    ref = placement_errors_numpy(feats, offsets, target, (ph, pw))
    np.testing.assert_allclose(placement_errors_opencl(feats, offsets, target, (ph, pw)), ref, rtol=2e-5, atol=1e-5)
    if len(offsets):  # the exact placement of a copied window costs nothing
        exact = feats[2 + offsets[:, 0], 1 + offsets[:, 1]]
        assert placement_errors_numpy(feats, offsets, exact, (ph, pw))[2, 1] == 0


@pytest.mark.parametrize("kind", ["random", "constant", "black", "huge", "tiny"])
@pytest.mark.parametrize("stride", [1, 2])
def test_placement_twin_gives_the_same_errors_whatever_it_gathers_at_once(kind, stride, monkeypatch):
    """The twin sums over the offsets in their order however many it gathers per step: one offset at a time gives
    the same float32 errors, bit for bit."""
    from btforge.plugins.wang import placement
    feats, offsets, target, window = _placement_case(np.random.default_rng(5), kind)
    gathered = placement_errors_numpy(feats, offsets, target, window, stride)
    monkeypatch.setattr(placement, "GATHER_CAP", 1)
    assert np.array_equal(placement_errors_numpy(feats, offsets, target, window, stride), gathered)


@settings(max_examples=12, deadline=None)
@given(st.integers(1, 6), st.integers(1, 6), st.integers(1, 9), st.floats(1e-6, 1e6), st.integers(1, 64),
       st.integers(0, 2 ** 31 - 1))
def test_placement_twin_on_random_windows_and_gather_sizes(ph, pw, d, scale, cap, seed):
    from btforge.plugins.wang import placement
    rng = np.random.default_rng(seed)
    feats = (rng.normal(size=(ph + 2, pw + 2, d)) * scale).astype(np.float32)
    offsets = np.argwhere(rng.random((ph, pw)) < 0.6)
    target = (rng.normal(size=(len(offsets), d)) * scale).astype(np.float32)
    out = placement_errors_numpy(feats, offsets, target, (ph, pw))
    assert np.isfinite(out).all() and (out >= 0).all()
    default, placement.GATHER_CAP = placement.GATHER_CAP, cap
    try:
        assert np.array_equal(placement_errors_numpy(feats, offsets, target, (ph, pw)), out)
    finally:
        placement.GATHER_CAP = default


def test_min_cut_follows_the_valley_and_respects_ties():
    diff = np.ones((6, 9))
    diff[:, 5] = 0.0
    keep = np.zeros((6, 9), bool)
    keep[:, 0] = True
    take = np.zeros((6, 9), bool)
    take[:, -1] = True
    new, cost = min_cut(diff, keep, take)
    assert not new[:, :5].any() and new[:, 6:].all() and cost == pytest.approx(6.0)
    h, v = quadrant_ties(4, (0, 0))
    new, _ = min_cut(np.random.default_rng(0).random((4, 4)), h, v)
    assert not new[h].any() and new[v].all()


# ----------------------------------------------------------------------------------------------- tile sets


def test_complete_set_with_colours_and_btfel_replay(procedural):
    stack, tiles, synthesis, _ = procedural
    assert tiles.n_tiles == 16 and tiles.tile == TILE and tiles.edge == EDGE
    assert sorted(map(tuple, tiles.tile_colors.tolist())) == sorted(
        (n, e, s, w) for n in range(2) for e in range(2) for s in range(2) for w in range(2))
    # the BTFel table replays the synthesized tiles bit for bit, and so do their texels
    assert np.array_equal(tiles.tile_coords, synthesis.tile_coords)
    assert len(np.unique(tiles.table, axis=0)) == len(tiles.table)
    table_texels = stack.remap(tiles.table[None, :, 0], tiles.table[None, :, 1]).samples
    for t in (0, 7, 15):
        direct = stack.remap(synthesis.tile_coords[t, ..., 0], synthesis.tile_coords[t, ..., 1]).samples
        assert np.array_equal(table_texels[:, :, 0][:, :, tiles.indices[t]], direct)
    stats = tiles.statistics()
    assert 0 < stats["referenced_share"] <= 1 and stats["btfels"] == len(tiles.table)
    assert stats["total_bytes"] == stats["table_bytes"] + stats["index_bytes"]
    assert stats["table_bytes"] == len(tiles.table) * 16 * 3 * 4


def test_tile_set_file_round_trip_and_info(procedural, tmp_path):
    _, tiles, _, _ = procedural
    path = tmp_path / "set.wang"
    tiles.write(path)
    back = read_tile_set(path)
    assert back.content_key == tiles.content_key
    for name in ("table", "indices", "tile_colors", "edge_seams"):
        assert np.array_equal(getattr(back, name), getattr(tiles, name), equal_nan=True)
    info = describe(path)
    assert info["tiles"] == 16 and info["btfels"] == len(tiles.table)
    bad = tmp_path / "bad.wang"
    bad.write_bytes(b"not a zip")
    with pytest.raises(BtforgeInputError, match="not a tile-set archive"):
        read_tile_set(bad)


def test_tileset_validation_names_the_field():
    with pytest.raises(BtforgeInputError, match="indices"):
        TileSet(np.zeros((2, 2), np.int32), np.full((1, 4, 4), 5, np.int32), np.zeros((1, 4), np.int32),
                np.zeros((1, 4), np.float32), 2, 2, (8, 8), 2)


def test_bad_parameters_are_reported_together():
    stack = procedural_exemplar(24, lights=4)
    with pytest.raises(BtforgeInputError) as err:
        wang_tiles(ctx=StageContext(node="t"), exemplar=stack, tile=8, edge=5)
    assert "even" in str(err.value) and "twice" in str(err.value)


# ----------------------------------------------------------------------------------------------- seams


def test_seams_of_the_procedural_set_are_like_the_exemplar(procedural):
    _, _, _, ratios = procedural
    assert ratios["worst_mean_ratio"] <= 1.2 and ratios["worst_p99_ratio"] <= 1.2, ratios
    # top-left: any tile; top-right and bottom-left: half of them; bottom-right: a quarter
    assert len(corner_configurations(procedural[1].tile_colors)) == 16 * 8 * 8 * 4


def test_straight_cuts_fail_where_graph_cuts_pass():
    from btforge.plugins.synth.bench import smooth_fields
    from btforge.plugins.wang import seams
    feats = smooth_fields(SIZE, 6, 3, sigma=2.0)
    reference = seams.exemplar_reference(feats)
    worst = {}
    for cut in ("graph", "straight"):
        syn = synthesize_tiles(feats, TILE, EDGE, (2, 2), 1, 0, cut=cut)
        r = seams.seam_ratios(seams.tile_set_seams(syn.tile_coords, syn.tile_colors, feats, EDGE), reference)
        worst[cut] = max(r["worst_mean_ratio"], r["worst_p99_ratio"])
    assert worst["graph"] <= 1.2 < worst["straight"], worst


@pytest.mark.parametrize("colors, edge", [((2, 2), 4), ((3, 2), 6), ((1, 1), 2)])
def test_tile_set_seams_gather_every_border_and_vertex_pair(colors, edge):
    """The set's seam report, pair by pair: each valid adjacency's facing texels, and around each valid vertex the
    pairs within edge / 2 of it, in the order of the configurations (a loop over them is the reference)."""
    from btforge.plugins.wang import seams
    rng = np.random.default_rng(sum(colors) + edge)
    tile_colors = np.array([(n, e, s, w) for n in range(colors[0]) for e in range(colors[1])
                            for s in range(colors[0]) for w in range(colors[1])], np.int32)
    feats = rng.normal(size=(17, 19, 4)).astype(np.float32)
    tile_coords = rng.integers(0, (17, 19), size=(len(tile_colors), 12, 12, 2)).astype(np.int32)
    got = seams.tile_set_seams(tile_coords, tile_colors, feats, edge)

    def gap(a, b):
        return np.linalg.norm(feats[a[..., 0], a[..., 1]].astype(np.float64)
                              - feats[b[..., 0], b[..., 1]].astype(np.float64), axis=-1).ravel()

    horizontal, vertical = seams.adjacency_distances(tile_coords, tile_colors)
    expected_h = np.concatenate([gap(tile_coords[a, :, -1], tile_coords[b, :, 0]) for a, b in horizontal])
    expected_v = np.concatenate([gap(tile_coords[a, -1, :], tile_coords[b, 0, :]) for a, b in vertical])
    q, corner_h, corner_v = edge // 2, [], []
    for tl, tr, bl, br in seams.corner_configurations(tile_colors):
        corner_h += [gap(tile_coords[tl, -q:, -1], tile_coords[tr, -q:, 0]), gap(tile_coords[bl, :q, -1], tile_coords[br, :q, 0])]
        corner_v += [gap(tile_coords[tl, -1, -q:], tile_coords[bl, 0, -q:]), gap(tile_coords[tr, -1, :q], tile_coords[br, 0, :q])]
    assert np.array_equal(got["h"], expected_h) and np.array_equal(got["v"], expected_v)
    assert np.array_equal(got["corner_h"], np.concatenate(corner_h))
    assert np.array_equal(got["corner_v"], np.concatenate(corner_v))
    assert got["adjacencies"] == len(horizontal) + len(vertical)
    assert all(len(got["local"][k]) == len(got[k]) and np.isfinite(got["local"][k]).all() for k in got["local"])


@pytest.mark.shared_data
def test_seams_of_a_real_capture_set(shared_data):
    from btforge.plugins.wang.bench import capture_exemplar
    model = capture_exemplar(str(shared_data / "rti/icon_san_michele/dirs.lp"), SIZE)
    tiles, _, ratios = build_tile_set(model, tile=TILE, edge=EDGE, seed=0)
    assert tiles.n_tiles == 16
    assert ratios["worst_mean_ratio"] <= 1.2 and ratios["worst_p99_ratio"] <= 1.2, ratios


# ----------------------------------------------------------------------------------------------- tilings


def test_plane_tiling_is_valid_aperiodic_and_uses_every_tile(procedural):
    stack, tiles, _, _ = procedural
    ctx = StageContext(node="tiling")
    coords = wang_tiling(ctx=ctx, tiles=tiles, rows=8, cols=8, seed=3)["coords"]
    assert coords.coords.shape == (8 * TILE, 8 * TILE, 2)
    assert np.array_equal(coords.coords[TILE:2 * TILE, 2 * TILE:3 * TILE],
                          tiles.tile_coords[tiling_ids(tiles, coords)[1, 2]])
    ids = tiling_ids(tiles, coords)
    report = ctx.notes["tiling"]
    assert report["mismatches"] == 0 and report["tiles_used"] == 16
    assert not is_periodic(ids)
    scores = score(tiles=tiles, exemplar=stack, coords=coords)["scores"].values
    assert scores["tiling_mismatches"] == 0 and scores["tiling_periodic"] is False
    assert scores["tiling_tiles_used"] == 16 and scores["seam_worst_mean_ratio"] > 0
    periodic = plane_tiling(tiles, 6, 6, True, 1)
    assert tiling_report(periodic, tiles.tile_colors, 16, True)["mismatches"] == 0
    assert is_periodic(np.tile(np.arange(4).reshape(2, 2), (4, 4)))


def test_score_measures_a_tile_set_and_its_tiling_through_the_buffers_capability(procedural):
    stack, tiles, _, ratios = procedural
    alone = score(tiles=tiles, exemplar=stack)["scores"].values
    assert alone["seam_worst_p99_ratio"] == pytest.approx(ratios["worst_p99_ratio"])
    assert alone["tiles"] == 16 and 0 < alone["btfel_share"] <= 1 and "swd" not in alone
    coords = wang_tiling(tiles=tiles, rows=2, cols=2, seed=1)["coords"]
    both = score(output=coords.apply(stack), exemplar=stack, coords=coords, tiles=tiles, samples=64)["scores"].values
    assert {k: both[k] for k in alone} == alone and "swd" in both and both["tiling_mismatches"] == 0
    with pytest.raises(BtforgeInputError, match="has no seam scores"):
        score(tiles=stack, exemplar=stack)
    with pytest.raises(BtforgeInputError, match="found neither"):
        score(exemplar=stack)
    with pytest.raises(BtforgeInputError, match="whole 32 x 32 tiles"):
        score(tiles=tiles, exemplar=stack, coords=CoordMap(np.zeros((40, 40, 2), np.int32), tiles.source_size))


@pytest.mark.parametrize("primitive,cells", [("plane", (8, 8)), ("cube", (3, 3)), ("torus", (8, 4)),
                                             ("sphere", (8, 4))])
def test_mesh_tilings_match_colours_across_every_shared_edge(procedural, primitive, cells):
    from btforge.plugins.render.geometry import build_mesh
    from btforge.plugins.render.scene import parse_scene
    _, tiles, _, _ = procedural
    spec = parse_scene({"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0]},
                        "meshes": {"m": {"primitive": primitive, "material": "stone"}}}, "<test>", None)
    mesh = build_mesh(spec.meshes[0])
    tiling = mesh_tiling(mesh.positions, mesh.triangles, mesh.corner_uv, cells, tiles, seed=2)
    assert glue_mismatches(tiling) == 0
    expected_glues = {"plane": 2 * 8 * 7, "cube": 6 * 2 * 3 * 2 + 12 * 3, "torus": 2 * 8 * 4,
                      "sphere": 8 * 4 + 8 * 3}[primitive]
    assert len(tiling.glues) == expected_glues
    assert (tiling.rotated_glues > 0) == (primitive == "cube")
    used = np.unique(np.concatenate([g.ravel() for g in tiling.grids]))
    assert len(used) == 16 or tiling.cells < 16


# ----------------------------------------------------------------------------------------------- rendering


def _plane_scene(cells: int, pixels: int, light) -> dict:
    return {"camera": {"type": "orthographic", "width": pixels, "height": pixels, "position": [0, 0, 5],
                       "look_at": [0, 0, 0], "up": [0, 1, 0], "extent": 2.0},
            "meshes": {"ground": {"primitive": "plane", "size": 2.0, "material": "stone", "tiles": True,
                                  "uv_scale": [cells, cells]}},
            "lights": [{"type": "directional", "direction": light, "intensity": 1.0}], "effects": []}


@pytest.mark.parametrize("space", ["linear", "srgb"])
def test_tiled_plane_equals_relight_of_the_materialized_tiling(procedural, space):
    """The renderer reads a feathered set as materialize replays its tiling: records interpolated where they blend
    as radiance, mixed per corner before evaluation where they mix as display values (an sRGB PTM)."""
    from btforge.plugins.ptm.model import fit_ptm
    from btforge.plugins.render.geometry import build_mesh
    from btforge.plugins.render.renderer import Counters, render
    from btforge.plugins.render.loader import load_scene
    from btforge.plugins.synth import materialize
    from btforge.plugins.render.tiles import TILING_SEED
    from btforge.plugins.wang.tiling import tiling_map
    from btforge.stages import RunPaths
    stack, tiles, _, _ = procedural
    assert tiles.blends  # a linear stack blends, so the seams inside the tiles that stand out are feathered
    model = dataclasses.replace(fit_ptm(stack, "rgb")[0], space=space)
    light = [0.3, 0.2, 0.93]
    cells = 4
    scene = load_scene(_plane_scene(cells, cells * TILE, light), RunPaths(Path.cwd(), Path.cwd()))
    image = render(scene, {"stone": model, "stone_tiles": tiles}, Counters())
    mesh = build_mesh(scene.spec.meshes[0], scene)
    ids = mesh_tiling(mesh.positions, mesh.triangles, mesh.corner_uv, (cells, cells), tiles, TILING_SEED).grids[0]
    coords = tiling_map(tiles, ids)
    relit = materialize(coords=coords, source=model)["output"].evaluate(np.array([light]))[0, 0]
    # the blended records are summed in another order at lookup (float32): a few ulps
    np.testing.assert_allclose(image, relit, rtol=1e-5, atol=1e-6)


def test_tiled_scene_needs_its_tile_set():
    from btforge.plugins.render.scene import parse_scene
    spec = parse_scene(_plane_scene(2, 8, [0, 0, 1]), "<test>", None)
    assert spec.ports() == {"stone": "ReflectanceModel", "stone_tiles": "TileSet"}
    bad = _plane_scene(2, 8, [0, 0, 1])
    bad["meshes"]["ground"]["uv_scale"] = [2.5, 2]
    with pytest.raises(BtforgeInputError, match="whole tiles"):
        parse_scene(bad, "<test>", None)


def test_cube_face_edges_match_and_their_seams_are_reported(procedural):
    from btforge.plugins.render.geometry import build_mesh
    from btforge.plugins.render.scene import parse_scene
    from btforge.plugins.wang.features import appearance_features
    from btforge.plugins.wang.seams import mesh_seams
    stack, tiles, _, _ = procedural
    spec = parse_scene({"camera": {"position": [0, 0, 5]}, "meshes": {"m": {"primitive": "cube", "material": "s"}}},
                       "<test>", None)
    mesh = build_mesh(spec.meshes[0])
    tiling = mesh_tiling(mesh.positions, mesh.triangles, mesh.corner_uv, (2, 2), tiles, seed=0)
    assert glue_mismatches(tiling) == 0
    report = mesh_seams(tiling, tiles.tile_coords, appearance_features(stack))
    # the ring of side faces and the top and bottom to the front keep their orientation across 6 of the 12 face
    # edges (2 cells each); the other 6 turn it (no orientation field on a cube avoids that)
    assert report["consistent_edges"] == 6 * 2 and report["rotated_edges"] == 6 * 2
    assert report["consistent_mean_ratio"] <= 1.2, report
    print("cube face-edge seams", report)


def test_a_feathered_set_keeps_its_blend_layer_through_the_archive_and_the_tiling(procedural, tmp_path):
    from btforge.plugins.wang.tiling import tiling_map
    _, tiles, _, _ = procedural
    assert tiles.blends and 0 < (tiles.blend_weight > 0).mean() < 0.6 and tiles.blend_weight.max() < 0.5
    tiles.write(tmp_path / "set.wang")
    back = read_tile_set(tmp_path / "set.wang")
    for name in ("table", "indices", "blend_indices", "blend_weight"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tiles, name))
    ids = plane_tiling(tiles, 2, 3, False, 0)
    coords = tiling_map(tiles, ids)
    t = ids[1, 2]
    lower_right = (slice(TILE, None), slice(2 * TILE, None))
    np.testing.assert_array_equal(coords.blend_weight[lower_right], tiles.blend_weight[t])
    np.testing.assert_array_equal(coords.blend_coords[lower_right], tiles.tile_map(t).blend_coords)
    np.testing.assert_array_equal(coords.coords[lower_right], tiles.tile_coords[t])
    # The weights are those of the feathered tile maps: no seam inside a tile stays unblended where it stands out,
    # and a texel that blends keeps its own source as the heavier one.
    moved = tiles.blend_weight > 0
    assert (tiles.tile_blend_coords()[moved] != tiles.tile_coords[moved]).any(axis=-1).all()


def test_a_plain_set_has_no_blend_layer_and_version_1_archives_still_read(procedural, tmp_path):
    import json
    import zipfile
    stack, _, _, _ = procedural
    plain, _, _ = build_tile_set(stack, tile=TILE, edge=EDGE, seed=0, feather=0)
    assert not plain.blends and plain.tile_map(0).blend_weight.size == 0
    plain.write(tmp_path / "new.wang")
    with zipfile.ZipFile(tmp_path / "new.wang") as new, zipfile.ZipFile(tmp_path / "old.wang", "w") as old:
        for name in new.namelist():
            data = new.read(name)
            if name == "manifest.json":
                manifest = json.loads(data)
                assert manifest["version"] == 2 and manifest["blends"] is False
                manifest.pop("blends")
                data = json.dumps({**manifest, "version": 1})
            old.writestr(name, data)
    np.testing.assert_array_equal(read_tile_set(tmp_path / "old.wang").indices, plain.indices)


def test_tiles_are_feathered_only_where_the_exemplar_blends(procedural):
    from btforge.plugins.synth.feather import FEATHER
    from btforge.plugins.wang import TILE_FEATHER_STEP, feathered_tiles
    from btforge.plugins.wang.features import appearance_features
    stack, tiles, _, _ = procedural
    feats = appearance_features(stack)
    args = (tiles.tile_coords, tiles.source_size, FEATHER)
    assert feathered_tiles(*args, False, feats) == {}                 # an sRGB PTM, Lafortune lobes
    blend = feathered_tiles(*args, True, feats)
    np.testing.assert_array_equal(blend["blend_weight"], tiles.blend_weight)
    # a lower threshold feathers more of the seams inside the tiles, never fewer
    lower = feathered_tiles(*args, True, feats, TILE_FEATHER_STEP / 2)["blend_weight"] > 0
    assert lower.sum() > (tiles.blend_weight > 0).sum() and lower[tiles.blend_weight > 0].all()


def test_the_sheet_shows_each_tile_as_materialize_replays_it(procedural):
    from btforge.plugins.synth import materialize
    from btforge.plugins.wang.sheet import relit_exemplar, tile_radiance
    stack, tiles, _, _ = procedural
    light = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])
    shown = tile_radiance(tiles, stack, light, relit_exemplar(stack, light))
    for t in (0, tiles.n_tiles - 1):
        replayed = materialize(coords=tiles.tile_map(t), source=stack)["output"]
        np.testing.assert_allclose(shown[t], relit_exemplar(replayed, light), rtol=1e-5, atol=1e-6)


def test_a_bad_blend_layer_is_named(procedural):
    _, tiles, _, _ = procedural
    fields = dict(table=tiles.table, indices=tiles.indices, tile_colors=tiles.tile_colors, edge_seams=tiles.edge_seams,
                  colors_h=2, colors_v=2, source_size=tiles.source_size, edge=tiles.edge)
    with pytest.raises(BtforgeInputError, match="'blend_indices' .* must both be"):
        TileSet(**fields, blend_indices=tiles.blend_indices[:, :-1], blend_weight=tiles.blend_weight)
    with pytest.raises(BtforgeInputError, match="'blend_weight' must lie in") as info:
        TileSet(**fields, blend_indices=tiles.blend_indices + len(tiles.table), blend_weight=tiles.blend_weight + 1)
    assert "'blend_indices' must lie in" in str(info.value)  # both problems at once


def test_graph_runs_write_read_sheet_and_info(tmp_path):
    import yaml

    import btforge
    from btforge.cli import main
    graph = {"nodes": {
        "material": {"stage": "demo.material", "params": {"size": [40, 40], "lights": 8, "seed": 2}},
        "tiles": {"stage": "wang.tiles", "params": {"tile": 16, "edge": 4, "seed": 1},
                  "inputs": {"exemplar": "material.stack"}},
        "save": {"stage": "wang.write_tiles", "params": {"path": "set.wang"}, "inputs": {"tiles": "tiles.tiles"}},
        "picture": {"stage": "wang.sheet", "params": {"path": "set.png", "light": [[0.2, 0.1, 0.97]]},
                    "inputs": {"tiles": "tiles.tiles", "exemplar": "material.stack"}},
        "tiling": {"stage": "wang.tiling", "params": {"rows": 3, "cols": 5}, "inputs": {"tiles": "tiles.tiles"}},
        "texture": {"stage": "synth.materialize", "inputs": {"coords": "tiling.coords", "source": "material.stack"}},
    }}
    (tmp_path / "g.yaml").write_text(yaml.safe_dump(graph))
    result = btforge.run(tmp_path / "g.yaml", out_dir=tmp_path, cache_dir=tmp_path / "cache")
    assert result["texture"]["output"].samples.shape[2:4] == (48, 80)
    notes = next(r for r in result.report if r.node == "tiles").notes
    assert set(notes["seconds"]) == {"corners", "edges", "frames", "interiors", "refine"}
    back = read_tile_set(tmp_path / "set.wang")
    assert back.n_tiles == 16 and back.tile == 16 and notes["btfels"]["btfels"] == len(back.table)
    from PIL import Image
    assert Image.open(tmp_path / "set.png").size[0] > 4 * 16
    assert main(["info", str(tmp_path / "set.wang")]) == 0


def test_sh_gram_features_give_the_hemisphere_l2_distance_and_drive_a_tile_set():
    from btforge.plugins.sh.model import SHModel, real_sh
    from btforge.plugins.wang.features import appearance_features
    rng = np.random.default_rng(5)
    coeffs = rng.normal(size=(24, 24, 1, 4, 9)).astype(np.float32)          # view order 2, light order 3
    model = SHModel(coeffs, np.ones((4, 9), np.float32), np.zeros((4, 9), np.float32), light_order=3,
                    view_order=2, channel_names=("Y",))
    feats = appearance_features(model)
    # L2 over (upper hemisphere of views) x (upper hemisphere of lights): a latitude-longitude midpoint rule,
    # independent of the features' own quadrature
    theta, phi = np.meshgrid((np.arange(60) + 0.5) * (np.pi / 2) / 60, (np.arange(120) + 0.5) * 2 * np.pi / 120,
                             indexing="ij")
    dirs = np.column_stack([(np.sin(theta) * np.cos(phi)).ravel(), (np.sin(theta) * np.sin(phi)).ravel(),
                            np.cos(theta).ravel()])
    weight = (np.sin(theta) * (np.pi / 2 / 60) * (2 * np.pi / 120)).ravel()
    yl, yv = real_sh(3, dirs), real_sh(2, dirs)
    diff = coeffs[3, 4, 0].astype(np.float64) - coeffs[17, 9, 0]
    values = yv @ diff @ yl.T                                               # [views, lights]
    l2 = np.sqrt(weight @ (values ** 2) @ weight)
    assert np.linalg.norm(feats[3, 4] - feats[17, 9]) == pytest.approx(l2, rel=2e-2)
    # and not the full-sphere distance of the coefficients
    assert abs(np.linalg.norm(diff) - l2) > 0.1 * l2
    tiles, _, _ = build_tile_set(model, tile=12, edge=4, seed=0)
    assert tiles.n_tiles == 16 and tiles.texel_bytes == 4 * 9 * 4
