"""The measures of what the eye sees (seam and straight-seam visibility, evenness, a tiling's lattice share, the
shuffled-block baseline),
each checked on constructed maps whose answer is known."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btforge.buffers import CoordMap
from btforge.errors import BtforgeInputError
from btforge.plugins.synth import materialize
from btforge.plugins.synth.scoring import score
from btforge.plugins.synth.visibility import (evenness, lattice_share, missed_targets, recurring_share, seam_edges,
                                              shuffled_blocks)

SIZE, OUT = 48, 144


@pytest.fixture(scope="module")
def tileable(tileable_stack):
    return tileable_stack(SIZE, 10)


def measured(exemplar, coords) -> dict:
    output = materialize(coords=coords, source=exemplar)["output"]
    return score(output=output, exemplar=exemplar, coords=coords)["scores"].values


def periodic_copy(size: int, out: int, **kwargs) -> CoordMap:
    rows, cols = np.mgrid[0:out, 0:out]
    return CoordMap(np.stack([rows % size, cols % size], axis=-1).astype(np.int32), (size, size), **kwargs)


def test_periodic_copy_of_a_tileable_exemplar_has_invisible_seams(tileable):
    found = measured(tileable, periodic_copy(SIZE, OUT))
    assert 0.8 <= found["seam_visibility"] <= 1.25
    # every seam of a periodic copy is a whole straight row or column, and is as invisible
    assert found["straight_seam_share"] == pytest.approx(1.0)
    assert 0.8 <= found["straight_seam_visibility"] <= 1.25
    assert found["evenness"] == pytest.approx(1.0)


def test_shuffled_blocks_score_high_on_straight_seams(tileable):
    found = measured(tileable, shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=16, seed=3))
    assert found["straight_seam_share"] > 0.9
    assert found["straight_seam_visibility"] > 1.6
    assert found["seam_visibility"] > 1.6
    assert found["swd_vs_shuffled_blocks"] is not None and found["swd_vs_shuffled_blocks"] > 0


def test_constant_source_map_has_evenness_near_zero(tileable):
    coords = CoordMap(np.full((OUT, OUT, 2), 7, np.int32), (SIZE, SIZE))
    n_cells = (SIZE // 8) ** 2
    assert evenness(coords) == pytest.approx(1 / n_cells)
    assert measured(tileable, coords)["evenness"] < 0.05


def test_evenness_counts_blends_by_weight():
    coords = np.zeros((16, 16, 2), np.int32)
    partner = np.full((16, 16, 2), 15, np.int32)
    half = CoordMap(coords, (16, 16), partner, np.full((16, 16), 0.5, np.float32))
    assert evenness(half) == pytest.approx(2 / 4)  # two of four cells, equally


def test_tile_borders_are_not_straight_seams():
    tile = 16
    rng = np.random.default_rng(0)
    coords = np.zeros((64, 64, 2), np.int32)
    rows, cols = np.mgrid[0:tile, 0:tile]
    for r in range(0, 64, tile):
        for c in range(0, 64, tile):
            r0, c0 = rng.integers(0, 48 - tile + 1, 2)
            coords[r:r + tile, c:c + tile] = np.stack([rows + r0, cols + c0], -1)
    plain = seam_edges(CoordMap(coords, (48, 48)))
    tiled = seam_edges(CoordMap(coords, (48, 48), tile=tile))
    assert plain.count == tiled.count > 0
    assert plain.straight_count == plain.count
    assert tiled.straight_count == 0


def test_straight_runs_need_twelve_texels():
    coords = np.stack(np.mgrid[0:32, 0:32], -1).astype(np.int32)
    coords[:11, 16:, 1] += 8   # a vertical seam of 11 texels at column 15 | 16: not straight enough
    coords[20:, 16:, 0] = (coords[20:, 16:, 0] + 4) % 40  # a shifted piece below: seams of 12 (vertical) and 16
    edges = seam_edges(CoordMap(coords, (40, 40)))
    assert not edges.columns_straight[:11, 15].any()
    assert edges.columns_straight[20:, 15].all()
    assert edges.rows_straight[19, 16:].all()


def test_wrapping_map_counts_its_wrap_around_pairs(tileable):
    wrapped = measured(tileable, periodic_copy(SIZE, 2 * SIZE, wrap=True))
    assert wrapped["seam_edge_share"] > 0
    assert 0.8 <= wrapped["seam_visibility"] <= 1.25


def test_bad_tile_is_a_clear_error():
    with pytest.raises(BtforgeInputError, match="tile"):
        CoordMap(np.zeros((4, 4, 2), np.int32), (4, 4), tile=-2)


def test_missed_targets_names_each_target_missed_and_leaves_straight_seams_under_two_per_cent_alone():
    """Each target on its own side of its bound, the straight target only from 2 % straight seam edges, and a
    measure without a value (no seam at all) missing nothing."""
    good = {"seam_visibility": 1.3, "straight_seam_visibility": 1.2, "straight_seam_share": 0.5, "evenness": 0.5,
            "swd_vs_shuffled_blocks": 1.5}
    assert missed_targets(good) == []
    worse = {"seam_visibility": 1.31, "straight_seam_visibility": 1.21, "evenness": 0.49,
             "swd_vs_shuffled_blocks": 1.51}
    assert missed_targets({**good, **worse}) == ["seams", "straight", "evenness", "swd"]
    for key, name in (("seam_visibility", "seams"), ("evenness", "evenness"), ("swd_vs_shuffled_blocks", "swd")):
        assert missed_targets({**good, key: worse[key]}) == [name]
    few = {**good, "straight_seam_visibility": 3.0, "straight_seam_share": 0.019}
    assert missed_targets(few) == []
    assert missed_targets({**few, "straight_seam_share": 0.02}) == ["straight"]
    assert missed_targets({**good, "seam_visibility": None, "straight_seam_visibility": None}) == []


def tiles_with_shared_band(tile: int, grid: int, band: int, seed: int = 0) -> np.ndarray:
    """``[2, grid * tile, grid * tile, 3]`` images of independent noise tiles whose border band of ``band`` texels
    is the same in every tile (what 2 + 2-colour Wang tiles approach along their edge strips)."""
    rng = np.random.default_rng(seed)
    images = rng.normal(size=(2, grid, tile, grid, tile, 3))
    shared = rng.normal(size=(2, 1, tile, 1, tile, 3))
    ring = np.ones((tile, tile), bool)
    ring[band:tile - band, band:tile - band] = False
    images = np.where(ring[None, None, :, None, :, None], shared, images)
    return images.reshape(2, grid * tile, grid * tile, 3)


def test_a_tiling_of_one_tile_has_lattice_share_one(tileable):
    found = measured(tileable, periodic_copy(SIZE, OUT, tile=SIZE))
    assert found["lattice_share"] == pytest.approx(1.0, abs=1e-6)


def test_maps_that_lay_no_tiles_have_no_lattice_share(tileable):
    assert measured(tileable, periodic_copy(SIZE, OUT))["lattice_share"] is None
    assert lattice_share(np.ones((1, 20, 20, 3)), 16) is None  # a single whole tile


def test_tiles_placed_independently_of_the_lattice_score_near_zero():
    noise = tiles_with_shared_band(16, 8, band=0)
    assert lattice_share(noise, 16) < 0.03
    # blocks of the exemplar shuffled at random, read as tiles of their own side
    rng = np.random.default_rng(4)
    exemplar = rng.uniform(size=(2, 64, 64, 3))
    coords = shuffled_blocks((64, 64), (128, 128), block=16, seed=5).coords
    laid = exemplar[:, coords[..., 0], coords[..., 1]]
    assert lattice_share(laid, 16) < 0.05


def test_pieces_laid_at_the_same_place_in_every_tile_show_whatever_their_colours():
    """Every tile holds a square at its centre, each tile's square and ground in colours of their own: the values at
    a place do not recur (light squares in some tiles, dark in others), but the squares' outlines do, and the eye
    sees a grid of squares."""
    rng = np.random.default_rng(9)
    tile, grid = 16, 6
    inside = np.zeros((tile, tile), bool)
    inside[4:12, 4:12] = True
    colours = rng.uniform(size=(2, grid, grid, 2, 3))                  # per light and tile: ground, square
    tiles = np.where(inside[None, None, None, :, :, None], colours[:, :, :, None, None, 1],
                     colours[:, :, :, None, None, 0])                   # [L, rows, cols, tile, tile, 3]
    images = tiles.transpose(0, 1, 3, 2, 4, 5).reshape(2, grid * tile, grid * tile, 3)
    assert recurring_share(images, tile) < 0.1
    assert lattice_share(images, tile) > 0.5


@pytest.mark.parametrize("band", [1, 2, 4])
def test_a_band_repeated_along_every_tile_border_shows_as_its_share_of_the_tile(band):
    tile = 16
    expected = 1 - ((tile - 2 * band) / tile) ** 2   # the band's share of a tile's texels, all of equal variance
    assert lattice_share(tiles_with_shared_band(tile, 8, band, seed=band), tile) == pytest.approx(expected, abs=0.03)


@settings(max_examples=25, deadline=None)
@given(tile=st.integers(1, 24), size=st.integers(1, 64), value=st.sampled_from([0.0, 1e-6, 0.5, 1e4]),
       seed=st.integers(0, 2 ** 16))
def test_lattice_share_is_none_or_a_share_on_hard_inputs(tile, size, value, seed):
    """Constant, tiny and huge images, tiles larger than the image, single texels: None or a finite share in
    [0, 1]."""
    rng = np.random.default_rng(seed)
    images = np.full((2, size, size, 3), value)
    if seed % 2:
        images += rng.uniform(0, 2 * value + 1e-3, images.shape)
    found = lattice_share(images, tile)
    assert found is None or (np.isfinite(found) and 0.0 <= found <= 1.0)
    if size // tile < 2 or (seed % 2 == 0):
        assert found is None
