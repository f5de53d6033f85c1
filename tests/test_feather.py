"""Feathering a map's seams through its blend layer, and the seam measure that follows a blended band."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btforge import stage
from btforge.buffers import CoordMap, SampleStack
from btforge.plugins.synth import materialize
from btforge.plugins.synth.feather import FEATHER, feather_weight, feathered, grain, local_steps, smooth_bands
from btforge.plugins.synth.scoring import score
from btforge.plugins.synth.visibility import exemplar_band_jumps, exemplar_jump, seam_edges, seam_visibility

SYNTHESIZERS = ("synth.quilt", "synth.kcoherence", "synth.jumpmap")


def ramp_stack(side: int, lights: int = 4) -> SampleStack:
    """A linear stack whose radiance rises by one step per row and per column (the same under every light)."""
    rng = np.random.default_rng(0)
    dirs = np.c_[rng.normal(0, 0.3, (lights, 2)), np.ones(lights)]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    rows, cols = np.mgrid[0:side, 0:side].astype(np.float32)
    values = np.broadcast_to(((rows + cols) / (2 * side))[..., None], (side, side, 3))
    samples = np.broadcast_to(values, (1, lights, side, side, 3)).astype(np.float32)
    return SampleStack(np.ascontiguousarray(samples), dirs, np.array([[0.0, 0.0, 1.0]]))


def two_halves(side: int, out: int, jump: int) -> CoordMap:
    """Left half copies columns 0.., right half the columns ``jump`` further on: one straight seam down the middle."""
    rows, cols = np.mgrid[0:out, 0:out]
    cols = np.where(cols < out // 2, cols, cols + jump)
    return CoordMap(np.stack([rows, cols], axis=-1).astype(np.int32), (side, side))


def agreeing_halves() -> CoordMap:
    """The right half copies texels 10 rows down and 10 columns back, which on :func:`ramp_stack` hold the same
    values: a seam down the middle whose sides continue each other."""
    rows, cols = np.mgrid[0:32, 0:32]
    right = cols >= 16
    return CoordMap(np.stack([rows + 10 * right, cols - 10 * right], axis=-1).astype(np.int32), (64, 64))


def measured(exemplar, coords) -> dict:
    output = materialize(coords=coords, source=exemplar)["output"]
    return score(output=output, exemplar=exemplar, coords=coords)["scores"].values


@pytest.mark.parametrize("band", [1, 2, 3])
def test_texels_beside_a_seam_blend_with_the_other_side_continued(band):
    coords = feathered(two_halves(64, 32, 20), band)
    middle = 16                                       # the seam lies between columns 15 and 16
    for distance in range(1, band + 1):
        low, high = middle - distance, middle + distance - 1
        # the low texel's partner continues the right half's source back to it (its own column + 20), the high
        # texel's the left half's (its own column)
        assert (coords.blend_coords[:, low, 1] == low + 20).all()
        assert (coords.blend_coords[:, high, 1] == high).all()
        assert np.allclose(coords.blend_weight[:, [low, high]], feather_weight(distance, band))
    assert (coords.blend_weight[:, :middle - band] == 0).all() and (coords.blend_weight[:, middle + band:] == 0).all()
    # the heavier source of every texel is its own: the map's seams stay where they were
    assert coords.blend_weight.max() < 0.5
    assert seam_edges(coords).count == seam_edges(two_halves(64, 32, 20)).count


def test_the_cross_fade_is_a_linear_ramp_in_equal_steps():
    band = 2
    exemplar = ramp_stack(64)
    output = materialize(coords=feathered(two_halves(64, 32, 20), band), source=exemplar)["output"]
    row = output.samples[0, 0, 0, :, 0].astype(np.float64) * 64
    # from column 13 (the last unblended of the left) to 18 (the first unblended of the right): 5 equal steps
    steps = np.diff(row[13:19])
    assert np.allclose(steps, steps.mean(), atol=1e-4)
    assert steps.mean() == pytest.approx((row[18] - row[13]) / 5)


def relit(exemplar, coords) -> tuple[np.ndarray, np.ndarray]:
    """The output's and the exemplar's linear samples ``[L, H, W, C]``: the seam measure's inputs."""
    output = materialize(coords=coords, source=exemplar)["output"]
    return output.samples[0].astype(np.float64), exemplar.samples[0].astype(np.float64)


@pytest.mark.parametrize("band", [0, 1, 2, 3])
def test_a_feathered_step_still_counts_with_its_sharpest_part(band):
    """A 20-step jump on a ramp of unit steps: across ``2 band + 1`` equal pairs each pair rises 1 + 20 / (2 band
    + 1), and the exemplar's largest of as many consecutive steps is 1."""
    coords = feathered(two_halves(64, 32, 20), band)
    found = seam_visibility(*relit(ramp_stack(64), coords), coords).seam_visibility
    assert found == pytest.approx(1 + 20 / (2 * band + 1), rel=1e-3)


@pytest.mark.parametrize("band", [1, 2, 3])
def test_a_feathered_seam_between_sides_that_agree_stays_invisible(band):
    """Every edge down the middle of :func:`agreeing_halves` is a seam edge, and no more visible than the exemplar's
    own steps at any band."""
    blended = feathered(agreeing_halves(), band)
    assert blended.blend_weight.max() > 0
    assert seam_visibility(*relit(ramp_stack(64), blended), blended).seam_visibility == pytest.approx(1.0, rel=1e-3)


def test_only_seams_whose_step_stands_out_are_feathered():
    """With the exemplar's appearance vectors, a 20-step jump is feathered and a seam between sides that continue
    the ramp (a step like the exemplar's own) is not."""
    features = ramp_stack(64).samples[0].transpose(1, 2, 0, 3).reshape(64, 64, -1)
    agreeing = agreeing_halves()
    # the agreeing seam's step is the exemplar's own, so any threshold over 1 leaves it alone
    assert feathered(two_halves(64, 32, 20), 1, features=features, step=1.5).blend_weight.max() > 0
    assert feathered(agreeing, 1, features=features, step=1.5).blend_weight.max() == 0
    assert feathered(agreeing, 1).blend_weight.max() > 0          # without the vectors every seam is feathered


def test_local_steps_are_each_texels_mean_step_to_its_neighbours():
    features = ramp_stack(16).samples[0].transpose(1, 2, 0, 3).reshape(16, 16, -1).astype(np.float64)
    one_step = np.sqrt(features.shape[2]) / 32                # each neighbour differs by 1/32 in every channel
    assert np.allclose(local_steps(features), one_step)
    assert (local_steps(np.zeros((5, 7, 3))) == 0).all()
    spike = np.zeros((5, 5, 1))
    spike[2, 2] = 1.0
    steps = local_steps(spike)
    assert steps[2, 2] == 1.0 and steps[1, 2] == pytest.approx(1 / 4) and steps[0, 2] == 0
    assert steps[2, 1] == pytest.approx(1 / 4) and steps[0, 0] == 0


def test_maps_that_cannot_or_need_not_blend_are_left_alone():
    coords = two_halves(64, 32, 20)
    assert feathered(coords, 0) is coords
    assert feathered(coords, 2, mixes=False) is coords
    blended = CoordMap(coords.coords, coords.source_size, coords.coords.copy(), np.full((32, 32), 0.3, np.float32))
    assert feathered(blended, 2) is blended


def test_the_band_reference_starts_at_the_plain_mean_jump_and_grows_with_the_band():
    exemplar = ramp_stack(32)
    enc = exemplar.samples[0][..., :3].astype(np.float64)
    assert exemplar_band_jumps(enc, 3)[1] == pytest.approx(exemplar_jump(enc))
    # the exemplar's largest of k consecutive jumps grows with k on any texture with varied steps
    rng = np.random.default_rng(1)
    noisy = rng.random((2, 16, 16, 3))
    band_means = exemplar_band_jumps(noisy, 4)
    assert band_means[0] == 0 and np.all(np.diff(band_means[1:]) > 0)


def ex_mean_over_max(ex: np.ndarray) -> float:
    """The exemplar's mean neighbour jump over its largest: the most a band's reference can exceed the plain one."""
    gx, gy = np.linalg.norm(np.diff(ex, axis=2), axis=3), np.linalg.norm(np.diff(ex, axis=1), axis=3)
    return exemplar_jump(ex) / max(gx.max(), gy.max())


@settings(max_examples=40, deadline=None)
@given(side=st.integers(4, 12), out=st.integers(2, 24), band=st.integers(1, 4), wrap=st.booleans(),
       seed=st.integers(0, 2**16), spread=st.sampled_from([0, 1, 3]))
def test_feathering_any_map_keeps_its_sources_and_is_measured_finitely(side, out, band, wrap, seed, spread):
    """Random maps (mostly coherent runs, or scattered texels): the partners lie inside the exemplar, no weight
    reaches one half, the heavier sources are the map's own, and the banded measure is finite and non-negative."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:out, 0:out]
    start = rng.integers(0, side, (out, 1, 2)) if spread else rng.integers(0, side, (out, out, 2))
    src = np.stack([(rows * 0 + start[..., 0]) % side, (cols + start[..., 1]) % side], axis=-1).astype(np.int32)
    coords = CoordMap(src, (side, side), wrap=wrap)
    done = feathered(coords, band)
    if done.blend_weight.size:
        assert done.blend_coords.min() >= 0 and done.blend_coords.max() < side
        assert 0 <= done.blend_weight.min() and done.blend_weight.max() < 0.5
    assert (done.coords == coords.coords).all()
    # with appearance vectors only some seams stand out; a band never reaches across one that does not, so every
    # texel that blends takes another source than its own
    features = rng.random((side, side, 3)).astype(np.float32) * rng.random((side, side, 1)).astype(np.float32)
    some = feathered(coords, band, features=features, step=1.5)
    if some.blend_weight.size:
        blends = some.blend_weight > 0
        assert (some.blend_coords[blends] != coords.coords[blends]).any(axis=-1).all()
    images = rng.random((2, out, out, 3))
    ex = rng.random((2, side, side, 3))
    plain, banded = seam_visibility(images, ex, coords), seam_visibility(images, ex, done)
    assert plain.seam_edge_share == banded.seam_edge_share
    for value in (plain.seam_visibility, banded.seam_visibility):
        assert value is None or (np.isfinite(value) and value >= 0)
    if plain.seam_visibility is not None:
        # a band's largest jump is at least the jump across the edge; its reference at most the largest jump
        assert banded.seam_visibility >= plain.seam_visibility * ex_mean_over_max(ex) - 1e-9


@pytest.mark.parametrize("name", SYNTHESIZERS)
def test_each_synthesizer_feathers_blendable_exemplars_by_default(name, tileable_stack):
    exemplar = tileable_stack(32, 6)                       # a linear stack: blendable
    params = {p.name: p.default for p in stage(name).params}
    assert params["feather"] == FEATHER
    coords = stage(name)(exemplar=exemplar, size=[48, 48], seed=0)["coords"]
    plain = stage(name)(exemplar=exemplar, size=[48, 48], seed=0, feather=0)["coords"]
    assert not plain.blend_weight.size
    assert (coords.coords == plain.coords).all()           # the same synthesis, only cross-faded
    assert coords.blend_weight.size and 0 < coords.blend_weight.max() < 0.5
    assert measured(exemplar, coords)["seam_visibility"] < measured(exemplar, plain)["seam_visibility"]


@pytest.mark.parametrize("name", SYNTHESIZERS)
def test_each_synthesizer_feathers_an_srgb_ptm(name, tileable_stack):
    """An sRGB lrgb PTM (what ptm.fit makes of most photographs) mixes the display values of its rgb form, so its
    maps are feathered too, and the cross-fade lowers the seams measured in radiance."""
    import dataclasses
    from btforge.plugins.ptm.model import fit_ptm
    exemplar = dataclasses.replace(fit_ptm(tileable_stack(32, 6), "lrgb")[0], space="srgb")
    assert not exemplar.blendable and exemplar.mixing_form() is not None
    coords = stage(name)(exemplar=exemplar, size=[48, 48], seed=0)["coords"]
    plain = stage(name)(exemplar=exemplar, size=[48, 48], seed=0, feather=0)["coords"]
    assert (coords.coords == plain.coords).all() and coords.blend_weight.size
    assert measured(exemplar, coords)["seam_visibility"] < measured(exemplar, plain)["seam_visibility"]


def test_bands_are_widest_where_the_exemplar_is_flat_and_narrow_where_it_is_grainy():
    """Half flat, half noise: a seam edge between flat sources gets the widest band, one between noisy sources one
    texel, so grain is not averaged over a wide strip."""
    rng = np.random.default_rng(3)
    features = np.zeros((32, 32, 4), np.float32)
    features[:, 16:] = rng.random((32, 16, 4))
    steps = local_steps(features)
    src = np.stack(np.mgrid[0:8, 0:8], axis=-1)
    src[..., 1] += np.where(np.arange(8) < 4, 2, 22)[None, :]         # left half flat, right half noise
    edges = np.ones((8, 8), bool)
    bands = smooth_bands(steps, src, edges, 1, 3)
    assert (bands[:, :3] == 3).all()                                  # both sources flat
    assert (bands[:, 4:7] == 1).all()                                 # both sources in the noise
    assert (smooth_bands(steps, src, ~edges, 1, 3) == 0).all()        # no seam edge, no band


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**16), widest=st.integers(1, 5), scale=st.sampled_from([0.0, 1e-6, 1.0, 1e6]))
def test_bands_stay_within_one_and_the_widest_on_any_exemplar(seed, widest, scale):
    """Any exemplar, a constant one (every step 0) included: each seam edge's band is an integer in [1, widest]."""
    rng = np.random.default_rng(seed)
    features = (rng.random((12, 12, 3)) * scale).astype(np.float32)
    src = rng.integers(0, 12, (10, 10, 2))
    edges = rng.random((10, 10)) < 0.5
    bands = smooth_bands(local_steps(features), src, edges, seed % 2, widest)
    assert (bands[edges] >= 1).all() and (bands[edges] <= widest).all() and (bands[~edges] == 0).all()


def test_a_smooth_exemplar_is_feathered_wider_than_a_grainy_one():
    """The same map on two flat halves of different colour and on the same with grain added: the seam between
    them cross-fades over more texels where the exemplar is flat."""
    coords = two_halves(64, 32, 20)                  # its sides copy columns 15 and 36 of the exemplar
    flat = np.zeros((64, 64, 4), np.float32)
    flat[:, 32:] = 1.0
    grain = np.random.default_rng(0).random(flat.shape).astype(np.float32) * 0.2
    smooth = feathered(coords, 3, features=flat, step=1.5)
    grainy = feathered(coords, 3, features=flat + grain, step=1.5)
    assert (smooth.blend_weight > 0).sum() == 6 * 32                 # three texels either side on every row
    assert 0 < (grainy.blend_weight > 0).sum() < (smooth.blend_weight > 0).sum()


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(1e-6, 1e6), offset=st.floats(-100.0, 100.0))
def test_grain_tells_grain_from_shading_whatever_the_units(seed, scale, offset):
    """Independent noise scores near its expected mean step over spread (2 Gamma(2) / Gamma(1.5) / sqrt(3), about 1.30,
    in 3 dimensions), a smooth ramp
    with faint noise near 0, and a constant exactly 0; the ratio is finite and does not change when the vectors are
    scaled or shifted (by up to 100 x their scale)."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(32, 32, 3))
    yy, xx = np.mgrid[0:32, 0:32] / 32.0
    ramp = np.stack([yy, xx, yy * xx], axis=2) + 1e-3 * noise
    for features, low, high in ((noise, 1.2, 1.4), (ramp, 0.0, 0.1)):
        value = grain(features)
        assert np.isfinite(value) and low < value < high, value
        assert grain(features * scale + offset * scale) == pytest.approx(value, rel=1e-3)
    assert grain(np.full((16, 16, 3), offset * scale)) == 0.0


def test_the_tiles_feather_smooth_exemplars_at_a_lower_step():
    """The Wang tiles' factor is the smooth one up to GRAIN_SMOOTH, the grainy one from GRAIN_GRAINY, and never
    falls as the grain rises."""
    from btforge.plugins.synth.feather import GRAIN_GRAINY, GRAIN_SMOOTH
    from btforge.plugins.wang import SMOOTH_FEATHER_STEP, TILE_FEATHER_STEP, tile_feather_step
    assert SMOOTH_FEATHER_STEP < TILE_FEATHER_STEP
    assert tile_feather_step(0.0) == tile_feather_step(GRAIN_SMOOTH) == SMOOTH_FEATHER_STEP
    assert tile_feather_step(GRAIN_GRAINY) == tile_feather_step(5.0) == TILE_FEATHER_STEP
    factors = [tile_feather_step(g) for g in np.linspace(0, 1, 41)]
    assert all(b >= a for a, b in zip(factors, factors[1:]))
