"""Wang tiles: seam relaxation, the usage term, and graph cuts on small cases."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from btforge.plugins.wang.cuts import grid_edges, min_cut
from btforge.plugins.wang.relax import pair_cost, relax_seams
from btforge.plugins.wang.synthesis import pixel_errors, window_means


def _seam_energy(coords, feats):
    """Summed pair cost over every neighbour pair of a canvas (each pair once)."""
    right = pair_cost(feats, coords[:, :-1], coords[:, 1:], (0, 1)).sum()
    down = pair_cost(feats, coords[:-1], coords[1:], (1, 0)).sum()
    return right + down


def _patchwork(rng, h=14, w=15, src=(20, 22), patches=6):
    """A canvas of a few random exemplar patches laid over each other (a filling's typical result)."""
    coords = np.zeros((h, w, 2), np.int32)
    for _ in range(patches):
        y0, x0 = rng.integers(0, h), rng.integers(0, w)
        ph, pw = rng.integers(3, h + 1), rng.integers(3, w + 1)
        sy, sx = rng.integers(0, src[0] - ph + 1), rng.integers(0, src[1] - pw + 1)
        dy, dx = np.mgrid[0:ph, 0:pw]
        ys, xs = slice(y0, min(h, y0 + ph)), slice(x0, min(w, x0 + pw))
        block = np.stack([sy + dy, sx + dx], -1)[:ys.stop - y0, :xs.stop - x0]
        coords[ys, xs] = block
    return coords


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([1.0, 1e-20, 1e20]))
def test_relaxation_never_raises_the_seam_energy_and_keeps_fixed_texels(seed, scale):
    rng = np.random.default_rng(seed)
    feats = (rng.random((20, 22, 3)) * scale).astype(np.float32)
    coords = _patchwork(rng)
    movable = np.zeros(coords.shape[:2], bool)
    movable[2:-2, 2:-2] = True
    relaxed = relax_seams(coords, feats, movable)
    assert np.isfinite(_seam_energy(relaxed, feats))
    assert _seam_energy(relaxed, feats) <= _seam_energy(coords, feats) * (1 + 1e-6) + 1e-30
    np.testing.assert_array_equal(relaxed[~movable], coords[~movable])
    assert (relaxed >= 0).all() and (relaxed[..., 0] < 20).all() and (relaxed[..., 1] < 22).all()


def test_relaxation_removes_an_island_and_leaves_continuous_content_alone():
    rng = np.random.default_rng(1)
    feats = rng.random((16, 30, 2)).astype(np.float32)
    rows, cols = np.mgrid[0:12, 0:12]
    coords = np.stack([rows, cols + 3], -1).astype(np.int32)
    movable = np.ones((12, 12), bool)
    np.testing.assert_array_equal(relax_seams(coords, feats, movable), coords)   # nothing to relax
    spotted = coords.copy()
    spotted[5, 6] = (2, 25)                          # a texel from elsewhere: four seams around it
    spotted[8, 3] = (14, 1)
    np.testing.assert_array_equal(relax_seams(spotted, feats, movable), coords)


def test_window_means_match_a_brute_force_window_mean():
    rng = np.random.default_rng(2)
    usage = rng.random((13, 17))
    for window, stride in (((4, 5), 1), ((3, 3), 2), ((13, 17), 1)):
        got = window_means(usage, window, stride)
        want = np.array([[usage[y:y + window[0], x:x + window[1]].mean()
                          for x in range(0, 17 - window[1] + 1, stride)]
                         for y in range(0, 13 - window[0] + 1, stride)])
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    channels = rng.random((13, 17, 3))
    want = np.stack([window_means(channels[..., d], (4, 5)) for d in range(3)], -1)
    np.testing.assert_allclose(window_means(channels, (4, 5)), want, rtol=1e-6)


def test_min_cut_is_the_cheapest_split_on_small_grids():
    # every split of a 3 x 3 window that respects the ties, enumerated
    rng = np.random.default_rng(5)
    for _ in range(20):
        difference = rng.random((3, 3))
        keep = np.zeros((3, 3), bool)
        keep[:, 0] = True
        take = np.zeros((3, 3), bool)
        take[:, 2] = True
        new, cost = min_cut(difference, keep, take)
        s, t = grid_edges((3, 3))
        flat = difference.ravel()
        edge_cost = flat[s] + flat[t]
        best = np.inf
        for bits in itertools.product([False, True], repeat=3):
            split = np.zeros(9, bool)
            split[[2, 5, 8]] = True
            split[[1, 4, 7]] = bits
            best = min(best, edge_cost[split[s] != split[t]].sum())
        assert not new[keep].any() and new[take].all()
        assert cost <= best * (1 + 1e-3) + 1e-9        # integer capacities: a relative tolerance of the scale


def test_pixel_errors_agree_with_the_pair_cost():
    rng = np.random.default_rng(6)
    feats = rng.random((20, 22, 3)).astype(np.float32)
    coords = _patchwork(rng)
    err = pixel_errors(coords, feats)
    right = pair_cost(feats, coords[:, :-1], coords[:, 1:], (0, 1))
    down = pair_cost(feats, coords[:-1], coords[1:], (1, 0))
    worst = np.zeros(coords.shape[:2])
    worst[:, :-1] = np.maximum(worst[:, :-1], right)
    worst[:, 1:] = np.maximum(worst[:, 1:], right)
    worst[:-1] = np.maximum(worst[:-1], down)
    worst[1:] = np.maximum(worst[1:], down)
    np.testing.assert_allclose(err, worst, rtol=1e-5, atol=1e-7)


def _set_spread(**options) -> tuple[float, float]:
    """Mean evenness and referenced share of 32-texel tile sets of a 64 x 64 procedural exemplar, tile-set seeds
    1 and 2 (one seed decides much: at seed 0 and usage 0 the evenness is 0.82, at seeds 1-3 0.67-0.75)."""
    from btforge.buffers import CoordMap
    from btforge.plugins.synth.visibility import evenness
    from btforge.plugins.wang import build_tile_set
    from btforge.plugins.wang.bench import procedural_exemplar
    stack = procedural_exemplar(64, lights=16)
    figures = []
    for seed in (1, 2):
        tiles, _, _ = build_tile_set(stack, tile=32, edge=8, seed=seed, **options)
        flat = CoordMap(np.ascontiguousarray(tiles.tile_coords.reshape(-1, 32, 2)), (64, 64))
        figures.append((evenness(flat), tiles.statistics()["referenced_share"]))
    return tuple(np.mean(figures, axis=0))


def test_the_usage_term_spreads_a_tile_set_over_the_exemplar():
    plain, spread = _set_spread(usage_weight=0.0, centre=0.0), _set_spread(usage_weight=2.0, centre=0.0)
    # measured: evenness 0.71 -> 0.88 and referenced share 0.78 -> 0.90
    assert spread[0] > plain[0] + 0.05 and spread[1] > plain[1], (plain, spread)


def test_the_filling_stops_once_the_region_is_covered():
    """A covered canvas takes no more patches, however bad its seams: with every pixel filled nothing ties a minimum
    cut to a new patch, so the cheapest cut keeps the old canvas and such a patch only costs its search."""
    rng = np.random.default_rng(5)
    feats = rng.random((40, 40, 3)).astype(np.float32)
    filler = _filler_with_usage(feats, 0.0)
    canvas = np.stack(np.mgrid[5:21, 5:21], -1).astype(np.int32)
    canvas[7:10, 7:10] = np.stack(np.mgrid[28:31, 28:31], -1)      # an island with seams all round
    region = np.ones((16, 16), bool)
    covered = canvas.copy()
    filler.fill(canvas, region, (8, 8))
    assert filler.placed == 0
    np.testing.assert_array_equal(canvas, covered)
    canvas[:4, :4] = -1
    filler.fill(canvas, region, (8, 8))
    assert filler.placed >= 1 and (canvas[..., 0] >= 0).all()


def test_each_tile_starts_from_a_least_used_piece_at_its_centre():
    from btforge.plugins.wang.synthesis import centre_piece_side
    rng = np.random.default_rng(3)
    feats = rng.random((40, 48, 3)).astype(np.float32)
    filler = _filler_with_usage(feats, 1.0)
    used = np.full((40, 48, 2), -1, np.int32)
    used[:, :30] = np.stack(np.mgrid[0:40, 0:30], -1)
    filler.record(used)   # the left 30 columns are used: a 16-texel piece fits only from column 30 on
    canvas = np.full((32, 32, 2), -1, np.int32)
    filler.seed_centre(canvas, 16)
    piece = canvas[8:24, 8:24]
    assert (canvas[..., 0] >= 0).sum() == 16 * 16
    y, x = piece[0, 0]
    assert x >= 30 and x + 16 <= 48
    np.testing.assert_array_equal(piece, np.stack(np.mgrid[y:y + 16, x:x + 16], -1))   # laid whole
    assert centre_piece_side(64, 16, 0.5) == 32 and centre_piece_side(64, 16, 1.0) == 48
    assert centre_piece_side(64, 16, 0.0) == 0


def test_each_edge_strip_starts_from_a_least_used_piece_at_its_middle():
    """A horizontal strip's piece is edge x length, laid whole between its corner halves, from where the set has
    used least; a vertical strip's is length x edge."""
    from btforge.plugins.wang.synthesis import centre_piece_side
    rng = np.random.default_rng(4)
    feats = rng.random((40, 48, 3)).astype(np.float32)
    filler = _filler_with_usage(feats, 1.0)
    used = np.full((40, 48, 2), -1, np.int32)
    used[:, :30] = np.stack(np.mgrid[0:40, 0:30], -1)
    filler.record(used)
    strip = np.full((8, 32, 2), -1, np.int32)
    strip[:, :4] = strip[:, 28:] = 0          # the two corner halves, laid already
    filler.seed_centre(strip, (8, 16))
    piece = strip[:, 8:24]
    y, x = piece[0, 0]
    assert x >= 30 and x + 16 <= 48
    np.testing.assert_array_equal(piece, np.stack(np.mgrid[y:y + 8, x:x + 16], -1))
    assert (strip[:, 4:8, 0] < 0).all() and (strip[:, 24:28, 0] < 0).all()   # left for the filling to join
    column = np.full((32, 8, 2), -1, np.int32)
    filler.seed_centre(column, (16, 8))
    assert (column[8:24, :, 0] >= 0).all() and (column[:8, :, 0] < 0).all()
    assert centre_piece_side(64, 16, 0.5) == 32   # a strip of 64 with edges of 16: 16 x 32


def test_the_tile_set_lays_the_edge_pieces_and_leaves_them_out_at_zero(monkeypatch):
    """``edge_centre`` reaches every strip: one piece per strip colour, edge x length across a horizontal strip and
    length x edge down a vertical one, besides the interiors' square centre pieces; none at 0."""
    from btforge.plugins.wang import synthesis
    laid = []
    plain = synthesis.Filler.seed_centre
    monkeypatch.setattr(synthesis.Filler, "seed_centre",
                        lambda self, coords, side: (laid.append(side), plain(self, coords, side))[1])
    rng = np.random.default_rng(2)
    feats = rng.random((48, 48, 3)).astype(np.float32)
    synthesis.synthesize_tiles(feats, 32, 8, (2, 2), engine="numpy", relax=0, edge_centre=0.5)
    strips = [side for side in laid if not np.isscalar(side)]
    assert sorted(strips) == [(8, 16), (8, 16), (16, 8), (16, 8)]
    assert sum(np.isscalar(side) for side in laid) == 16
    laid.clear()
    synthesis.synthesize_tiles(feats, 32, 8, (2, 2), engine="numpy", relax=0, edge_centre=0.0)
    assert all(np.isscalar(side) for side in laid)


def test_pieces_can_be_kept_to_the_typical_places():
    """A small bright patch on a noisy ground, the ground already used: every place of the patch is least used, so a
    centre piece comes from it; with a typical share of 0.75 it comes from the ground, as the typical places are."""
    rng = np.random.default_rng(5)
    feats = (0.4 + 0.1 * rng.random((48, 48, 3))).astype(np.float32)
    feats[36:, 36:] = 1.0                                  # the rare part: 12 x 12 texels in a corner
    filler = _filler_with_usage(feats, 1.0)
    filler.rare = 0.0                                      # the share alone (the patch is rare too)
    used = np.full((48, 48, 2), -1, np.int32)
    used[:36] = np.stack(np.mgrid[0:36, 0:48], -1)
    used[:, :36] = np.stack(np.mgrid[0:48, 0:36], -1)
    filler.record(used)                                    # everything but the patch has been laid once
    in_patch = {}
    for share in (1.0, 0.75):
        canvas = np.full((24, 24, 2), -1, np.int32)
        filler.typical_share = share
        filler.seed_centre(canvas, 8)
        piece = canvas[8:16, 8:16]
        in_patch[share] = int(((piece[..., 0] >= 36) & (piece[..., 1] >= 36)).sum())
    assert in_patch == {1.0: 64, 0.75: 0}                   # least used: the patch; among the typical: the ground
    typical = filler.allowed_places((8, 8)).reshape(41, 41)
    assert typical.mean() == pytest.approx(0.75, abs=0.01) and not typical[36:, 36:].any()
    filler.typical_share = 1.0
    assert filler.allowed_places((8, 8)).all()


def _patch_taken(typical_share: float, rare: float) -> tuple[int, int]:
    """Texels of a bright 12 x 12 corner patch on a used noisy ground (the patch itself unused) that a centre piece
    and a filled strip take, with the filler's typical share and rare fence set as given."""
    rng = np.random.default_rng(5)
    feats = (0.4 + 0.1 * rng.random((48, 48, 3))).astype(np.float32)
    feats[36:, 36:] = 1.0
    filler = _filler_with_usage(feats, 50.0)
    filler.usage[:36] = filler.usage[:, :36] = 1.0
    filler.typical_share, filler.rare = typical_share, rare
    centre = np.full((24, 24, 2), -1, np.int32)
    filler.seed_centre(centre, 8)
    strip = np.full((8, 40, 2), -1, np.int32)
    strip[:, :4] = np.stack(np.mgrid[0:8, 0:4], -1)
    filler.fill(strip, strip[..., 0] < 0, (8, 8))
    return tuple(int(((c[..., 0] >= 36) & (c[..., 1] >= 36)).sum()) for c in (centre, strip))


def test_the_filling_keeps_to_the_typical_places_too():
    """The filling's patches obey the typical share as the centre pieces do: at share 1 a strip lays patch texels
    (the usage term pulls it there); at 0.75 none."""
    assert _patch_taken(1.0, 0.0)[1] > 0 and _patch_taken(0.75, 0.0)[1] == 0


def test_pieces_holding_a_rare_texel_stay_out_of_the_tiles():
    """At the default fence the bright patch's texels are rare, so neither a centre piece nor the filling takes any
    of them though they are the least used; with the fence off both do.  Where rare texels are strewn over the
    whole exemplar (every window holds one) they are its texture and no place is left out."""
    from btforge.plugins.wang.synthesis import RARE_FENCE
    assert _patch_taken(1.0, RARE_FENCE) == (0, 0)
    assert min(_patch_taken(1.0, 0.0)) > 0
    rng = np.random.default_rng(6)
    speckled = (0.4 + 0.1 * rng.random((48, 48, 3))).astype(np.float32)
    speckled[::6, ::6] = 1.0                               # one bright texel in every 6 x 6
    assert _filler_with_usage(speckled, 1.0).allowed_places((8, 8)).all()


def test_the_centre_pieces_spread_a_tile_set_over_the_exemplar():
    """With a least-used piece at each tile's centre the set uses more of the exemplar, even without the usage
    term (measured: evenness 0.71 -> 0.83)."""
    plain, centred = _set_spread(usage_weight=0.0, centre=0.0), _set_spread(usage_weight=0.0, centre=0.5)
    assert centred[0] > plain[0] + 0.05, (plain, centred)


def _filler_with_usage(feats, weight):
    from btforge.plugins.wang.placement import PlacementSearch
    from btforge.plugins.wang.synthesis import Filler
    return Filler(feats, PlacementSearch(feats, "numpy"), np.random.default_rng(0), "graph", weight, "match")


def test_the_usage_term_in_match_units_is_weighed_in_the_fillings_own_match_level():
    """The usage cost of a placement: weight x the median 4th-best match error per known texel of the searches so
    far (the placements a draw chooses among) x known texels x the mean earlier use under it, zero over texels not used before."""
    rng = np.random.default_rng(3)
    feats = rng.random((24, 24, 3)).astype(np.float32)
    filler = _filler_with_usage(feats, 2.0)
    errors = rng.random((17, 17)) * 5.0
    assert filler._usage_cost(errors, 10, (8, 8), 1) == 0.0        # nothing used yet: no cost, but the level counts
    filler.usage[4:12, 4:12] = 3.0
    second = errors + 1.0
    cost = filler._usage_cost(second, 20, (8, 8), 1)
    level = np.median([np.sort(errors.ravel())[3] / 10, np.sort(second.ravel())[3] / 20])
    np.testing.assert_allclose(cost, 2.0 * level * 20 * window_means(filler.usage, (8, 8)), rtol=1e-6)
    assert cost[0, 0] > 0 and cost[-1, -1] == 0.0                  # over the used texels only


def test_a_grainy_and_a_smooth_exemplar_spread_alike_in_match_units():
    """The same usage weight (``usage_unit`` match) spreads a strip's fillings over a grainy (white noise) and a smooth (blurred noise)
    exemplar alike: the term is weighed in each exemplar's own match level.  Filled twice from the same start,
    the second strip must reuse at most half as many of the first one's exemplar texels as without the term, in
    both.  (With the best placement's error as the level, exact continuations of the known texels made it zero
    and the term vanished here.)"""
    from scipy.ndimage import gaussian_filter
    rng = np.random.default_rng(5)
    noise = rng.random((96, 96, 3)).astype(np.float32)
    smooth = gaussian_filter(noise, (3, 3, 0)).astype(np.float32)
    smooth = (smooth - smooth.mean()) / smooth.std() * noise.std()
    for feats in (noise, smooth):
        reuse = {}
        for weight in (0.0, 2.0):
            filler = _filler_with_usage(feats, weight)
            laid = []
            for _ in range(2):
                coords = -np.ones((8, 48, 2), np.int32)
                coords[:, :8] = np.stack(np.mgrid[40:48, 40:48], -1)   # the same known start each time
                region = coords[..., 0] < 0
                filler.fill(coords, region, (8, 8))
                filler.record(np.where(region[..., None], coords, -1))
                laid.append({(int(y), int(x)) for y, x in coords[region]})
            reuse[weight] = len(laid[0] & laid[1]) / len(laid[1])
        assert reuse[2.0] <= 0.5 * reuse[0.0], reuse


def test_interior_window_defaults_to_one_and_a_half_edges_within_the_interior():
    from btforge.plugins.wang.synthesis import interior_window
    assert interior_window(64, 16) == 24 and interior_window(64, 16, 40) == 40
    assert interior_window(64, 16, 200) == 48     # never wider than the interior's span, tile - edge


def test_larger_interior_windows_fill_the_tiles_with_fewer_larger_pieces():
    from btforge.plugins.synth.visibility import seam_masks
    from btforge.plugins.wang import build_tile_set
    from btforge.plugins.wang.bench import procedural_exemplar
    stack = procedural_exemplar(64, lights=16)
    seam_edges = {}
    for interior in (0, 22):
        tiles, _, _ = build_tile_set(stack, tile=32, edge=8, seed=0, interior=interior, optimise={"iterations": 0})
        coords = tiles.tile_coords[:, 4:-4, 4:-4]          # inside the frames the edge strips lay
        seam_edges[interior] = sum(int(sum(m.sum() for m in seam_masks(c[..., 0], c[..., 1], False)))
                                   for c in coords)
    # windows of 22 instead of 12 texels: fewer cuts inside the frames
    assert seam_edges[22] < 0.8 * seam_edges[0], seam_edges
