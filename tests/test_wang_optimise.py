"""Wang tiles: the texture optimisation of the interiors holds the borders and hides the filling's cuts."""
from __future__ import annotations

import numpy as np
import pytest

from btforge.plugins.wang.optimise import border_ring, mosaic, unmosaic


@pytest.fixture(scope="module")
def exemplar96():
    """A 96 x 96 procedural exemplar (8 lights) and its appearance features: small enough for whole tile sets."""
    from btforge.plugins.wang.bench import procedural_exemplar
    from btforge.plugins.wang.features import appearance_features
    stack = procedural_exemplar(96, lights=8)
    return stack, appearance_features(stack)


@pytest.mark.parametrize("t, columns", [(16, 4), (5, 3), (1, 1), (7, 7)])
def test_mosaic_round_trips(t, columns):
    tiles = np.random.default_rng(t).integers(0, 100, (t, 6, 6, 2))
    laid = mosaic(tiles, columns)
    assert laid.shape == (-(-t // columns) * 6, columns * 6, 2)
    np.testing.assert_array_equal(unmosaic(laid, t, 6), tiles)
    np.testing.assert_array_equal(laid[:6, :6], tiles[0])


def test_border_ring_marks_the_outer_texels_only():
    ring = border_ring(8, 2)
    assert ring.sum() == 64 - 16 and not ring[2:6, 2:6].any() and ring[:2].all() and ring[:, -2:].all()
    assert border_ring(4, 2).all()   # nothing left inside


def _feature_seam_ratio(tile_coords, feats):
    """Mean feature jump across the tiles' seam edges over the exemplar's mean neighbour jump."""
    jumps, seams = [], 0
    for tile in tile_coords:
        for axis, step in ((0, (1, 0)), (1, (0, 1))):
            a, b = (tile[:-1], tile[1:]) if axis == 0 else (tile[:, :-1], tile[:, 1:])
            cut = np.any(b != a + np.array(step), axis=-1)
            jumps.append(np.linalg.norm(feats[a[cut][:, 0], a[cut][:, 1]] - feats[b[cut][:, 0], b[cut][:, 1]], axis=-1))
            seams += int(cut.sum())
    reference = np.mean(np.concatenate([np.linalg.norm(np.diff(feats, axis=0), axis=-1).ravel(),
                                        np.linalg.norm(np.diff(feats, axis=1), axis=-1).ravel()]))
    return float(np.concatenate(jumps).mean() / reference), seams


def test_optimisation_holds_the_borders_and_hides_the_cuts():
    from btforge.plugins.wang import build_tile_set
    from btforge.plugins.wang.bench import procedural_exemplar
    from btforge.plugins.wang.features import appearance_features
    from btforge.plugins.wang.tiling import plane_tiling
    stack = procedural_exemplar(64, lights=16)
    feats = appearance_features(stack)
    strips = {"iterations": 4, "polish": 1, "seam_weight": 4.0}   # the same strips for both sets
    plain, _, _ = build_tile_set(stack, tile=32, edge=8, seed=0, optimise={"iterations": 0}, strip_refine=strips)
    refined, _, _ = build_tile_set(stack, tile=32, edge=8, seed=0, optimise={"iterations": 4, "pin": 2},
                                   strip_refine=strips)
    ring = border_ring(32, 2)
    np.testing.assert_array_equal(refined.tile_coords[:, ring], plain.tile_coords[:, ring])
    assert (refined.tile_coords[:, ~ring] != plain.tile_coords[:, ~ring]).any()
    np.testing.assert_array_equal(refined.tile_colors, plain.tile_colors)
    ids = plane_tiling(refined, 4, 4, False, 0)
    for (a, b) in ((ids[:, :-1], ids[:, 1:]),):   # colours still match: east of one is west of the next
        assert (refined.tile_colors[a][..., 1] == refined.tile_colors[b][..., 3]).all()
    before, _ = _feature_seam_ratio(plain.tile_coords, feats)
    after, _ = _feature_seam_ratio(refined.tile_coords, feats)
    assert np.isfinite(after) and after < before


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_refined_edge_strip_keeps_its_corner_halves_and_shows_less_seam(exemplar96, seed):
    """Every tile of a colour lays half of its strip, so the strip is refined before the frames are cut from it;
    the corner halves, which the vertex squares share with three other strips, must stay as the corners laid them."""
    from btforge.plugins.wang.synthesis import pixel_errors, refined_strip
    _, feats = exemplar96
    rng = np.random.default_rng(seed)
    h, w = 8, 32
    coords = np.zeros((h, w, 2), np.int32)
    for x0 in range(0, w, 8):     # four unrelated exemplar pieces side by side: three straight cuts
        py, px = rng.integers(0, 96 - 8, 2)
        coords[:, x0:x0 + 8] = np.stack(np.mgrid[py:py + h, px:px + 8], -1)
    region = np.ones((h, w), bool)
    region[:, :4] = region[:, -4:] = False   # the corner halves
    refined = refined_strip(feats, coords, region, seed, iterations=4, polish=1, seam_weight=4.0)
    assert refined.shape == coords.shape and refined.dtype == coords.dtype
    np.testing.assert_array_equal(refined[~region], coords[~region])
    assert (refined >= 0).all() and (refined < 96).all()
    # each texel's worst seam: the distance between each side and the other side's own continuation
    before, after = pixel_errors(coords, feats), pixel_errors(refined, feats)
    assert np.isfinite(after).all() and after.sum() < 0.9 * before.sum()


@pytest.mark.parametrize("k", [1, 2, 3, 4, 5])
def test_de_bruijn_pairs_hold_every_ordered_pair_once(k):
    from btforge.plugins.wang.optimise import de_bruijn_pairs
    sequence = de_bruijn_pairs(k)
    pairs = [(sequence[i], sequence[(i + 1) % len(sequence)]) for i in range(len(sequence))]
    assert len(sequence) == k * k and sorted(pairs) == [(a, b) for a in range(k) for b in range(k)]


@pytest.mark.parametrize("n_h, n_v, variants", [(2, 2, 1), (1, 3, 1), (3, 2, 2), (2, 1, 3)])
def test_packing_lays_a_complete_set_once_as_a_valid_periodic_tiling(n_h, n_v, variants):
    from btforge.plugins.wang.optimise import packing
    from btforge.plugins.wang.synthesis import tile_index
    combos = [(n, e, s, w) for n in range(n_h) for e in range(n_v) for s in range(n_h) for w in range(n_v)]
    colors = np.zeros((len(combos) * variants, 4), int)
    for combo in combos:
        for v in range(variants):
            colors[tile_index(*combo, v, n_h, n_v, variants)] = combo
    grid = packing(colors, n_h, n_v)
    assert sorted(grid.ravel().tolist()) == list(range(len(colors)))
    laid = colors[grid]                                                   # [rows, cols, 4]
    assert (laid[..., 2] == np.roll(laid, -1, axis=0)[..., 0]).all()      # south meets the north below, wrapping
    assert (laid[..., 1] == np.roll(laid, -1, axis=1)[..., 3]).all()      # east meets the west to the right
    assert packing(colors[1:], n_h, n_v) is None                          # a set with a tile missing: no packing


def test_the_interiors_straight_seams_are_re_cut_with_more_passes_than_the_shared_default(monkeypatch, exemplar96):
    """The held ring leaves straight runs that one pass only shortens: the Wang tiles re-cut with
    RECUT_PASSES passes (more than the shared default), and on a small set those passes leave fewer straight seam
    edges inside the tiles than the default's two."""
    import btforge.plugins.synth.refine as refine
    from btforge.buffers import CoordMap
    from btforge.plugins.synth.recut import PASSES
    from btforge.plugins.synth.visibility import seam_edges
    from btforge.plugins.wang import build_tile_set, optimise
    chosen = optimise.RECUT_PASSES
    assert chosen > PASSES
    asked = []
    original = refine.refine_map

    def recorded(*args, **kwargs):
        if "recut_passes" in kwargs:   # the tiles' refinement (each edge strip's leaves the passes at the default)
            asked.append(kwargs["recut_passes"])
        return original(*args, **kwargs)

    monkeypatch.setattr(refine, "refine_map", recorded)
    stack = exemplar96[0]

    def straight_edges(passes):
        monkeypatch.setattr(optimise, "RECUT_PASSES", passes)
        tiles, _, _ = build_tile_set(stack, tile=48, edge=12, seed=1)
        w = tiles.tile_coords.shape[1]
        laid = CoordMap(optimise.mosaic(tiles.tile_coords, 4), (stack.height, stack.width), tile=w)
        return seam_edges(laid).straight_count

    default, more = straight_edges(PASSES), straight_edges(chosen)
    assert asked == [PASSES, chosen]
    assert more < default


def test_the_polish_round_holds_the_borders_and_lowers_the_seams_the_weighted_rounds_leave(exemplar96):
    """The refinement's rounds weigh the occurrence term; the polish round after them matches windows for their
    fit alone, so on a small set it leaves the held ring as it was and the tiles' seams lower than without it."""
    from btforge.plugins.wang import build_tile_set
    from btforge.plugins.wang.optimise import ITERATIONS, OCCURRENCE, POLISH, SEAM_WEIGHT
    assert POLISH >= 1
    stack, feats = exemplar96
    strips = {"iterations": ITERATIONS, "polish": POLISH, "seam_weight": SEAM_WEIGHT}   # the same strips for both
    ratios = {}
    for polish in (0, POLISH):
        tiles, _, _ = build_tile_set(stack, tile=48, edge=12, seed=1, strip_refine=strips,
                                     optimise={"occurrence": OCCURRENCE, "polish": polish})
        ratios[polish], _ = _feature_seam_ratio(tiles.tile_coords, feats)
        held = tiles.tile_coords[:, border_ring(48, 1)]
        if polish == 0:
            ring = held
    np.testing.assert_array_equal(held, ring)
    assert np.isfinite(ratios[POLISH]) and ratios[POLISH] < ratios[0]


def test_the_contrast_term_keeps_the_tiles_as_varied_as_the_exemplar(exemplar96):
    """Nearest windows under a squared distance favour flatter ones, so the rounds drift towards the exemplar's
    flatter areas; with the contrast term the tiles' local variation (the mean variation of their 8 x 8 windows)
    stays nearer the exemplar's, and the held ring is the same."""
    from btforge.plugins.synth.refine import exemplar_window_energy
    from btforge.plugins.wang import build_tile_set
    from btforge.plugins.wang.optimise import CONTRAST
    assert CONTRAST > 0
    stack, feats = exemplar96
    target = exemplar_window_energy(feats, 8).mean()
    shortfall, rings = {}, {}
    for contrast in (0.0, CONTRAST):
        tiles, _, _ = build_tile_set(stack, tile=48, edge=12, seed=1, optimise={"contrast": contrast})
        energy = [exemplar_window_energy(feats[c[..., 0], c[..., 1]], 8).mean() for c in tiles.tile_coords]
        shortfall[contrast] = abs(float(np.mean(energy)) - target) / target
        rings[contrast] = tiles.tile_coords[:, border_ring(48, 1)]
    np.testing.assert_array_equal(rings[0.0], rings[CONTRAST])
    assert shortfall[CONTRAST] < shortfall[0.0]


def test_the_strips_and_the_interiors_are_re_cut_in_the_tiles_wider_band(monkeypatch, exemplar96):
    """The runs left in the tiles cut through areas whose far side lies beyond the shared band: every refinement of
    a tile set (each edge strip's and the interiors') re-cuts in RECUT_BAND texels on either side, wider than the
    shared default."""
    import btforge.plugins.synth.refine as refine
    from btforge.plugins.synth.recut import BAND
    from btforge.plugins.wang import build_tile_set, optimise, synthesis
    assert optimise.RECUT_BAND > BAND
    asked = []
    original = refine.refine_map

    def recorded(*args, **kwargs):
        asked.append(("interiors" if "recut_passes" in kwargs else "strip", kwargs.get("recut_band")))
        return original(*args, **kwargs)

    monkeypatch.setattr(refine, "refine_map", recorded)
    monkeypatch.setattr(synthesis, "refine_map", recorded)
    build_tile_set(exemplar96[0], tile=48, edge=12, seed=1)
    assert {kind for kind, _ in asked} == {"strip", "interiors"}
    assert all(band == optimise.RECUT_BAND for _, band in asked)
