"""The shared refinement: texture optimisation with an occurrence term, then corrections, on any map."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btforge.buffers import CoordMap, SampleStack
from btforge.plugins.demo.patterns import make_pattern
from btforge.plugins.demo.procedural import hemisphere_lights, render_lights
from btforge.plugins.synth.features import texel_features, window_sums
from btforge.plugins.synth.refine import (appearance_classes, appearance_excess, jittered_windows, refine_map,
                                          window_index, window_starts)
from btforge.plugins.synth.visibility import evenness, seam_edges, shuffled_blocks

SIZE, OUT = 40, 72


@pytest.fixture(scope="module")
def stones():
    lights = hemisphere_lights(8)
    stack = SampleStack(render_lights(make_pattern("stones", SIZE, SIZE, seed=2), lights)[None], lights,
                        np.array([[0.0, 0.0, 1.0]]))
    return texel_features(stack)


def seam_cost(features: np.ndarray, coords: CoordMap) -> float:
    """Mean appearance jump across the map's seams (the feature-space twin of seam visibility)."""
    out = features[coords.coords[..., 0], coords.coords[..., 1]]
    edges = seam_edges(coords)
    jc = np.linalg.norm(np.roll(out, -1, axis=1) - out, axis=2)[edges.across_columns]
    jr = np.linalg.norm(np.roll(out, -1, axis=0) - out, axis=2)[edges.across_rows]
    return float(np.concatenate([jc, jr]).mean())


def test_refinement_hides_the_seams_of_shuffled_blocks(stones):
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=1)
    refined = refine_map(stones, start, iterations=3, occurrence=0.3, seed=0)
    assert refined.coords.shape == start.coords.shape and refined.source_size == start.source_size
    assert refined.coords.min() >= 0 and refined.coords[..., 0].max() < SIZE and refined.coords[..., 1].max() < SIZE
    assert seam_cost(stones, refined) < 0.8 * seam_cost(stones, start)
    before, after = seam_edges(start), seam_edges(refined)
    assert after.straight_count < 0.5 * before.straight_count


def test_occurrence_term_spreads_a_collapsed_map(stones):
    rows, cols = np.mgrid[0:OUT, 0:OUT]
    collapsed = CoordMap(np.stack([rows % 12, cols % 12], -1).astype(np.int32), (SIZE, SIZE))  # one corner only
    plain = refine_map(stones, collapsed, iterations=3, occurrence=0.0, seed=0)
    spread = refine_map(stones, collapsed, iterations=3, occurrence=1.0, seed=0)
    assert evenness(spread) > evenness(plain)
    assert evenness(spread) > 2 * evenness(collapsed)


def test_refinement_is_deterministic_and_keeps_the_map_kind(stones):
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=4)
    wrapped = CoordMap(start.coords, start.source_size, wrap=True, tile=8)
    a = refine_map(stones, wrapped, iterations=2, occurrence=0.3, seed=5)
    b = refine_map(stones, wrapped, iterations=2, occurrence=0.3, seed=5)
    assert np.array_equal(a.coords, b.coords)
    assert a.wrap and a.tile == 8
    assert refine_map(stones, wrapped, iterations=0, occurrence=0.3) is wrapped


def test_blended_map_is_refined_from_its_heavier_sources_and_keeps_their_blends(stones):
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=4)
    partner = np.roll(start.coords, 1, axis=1)
    blended = CoordMap(start.coords, start.source_size, partner, np.full((OUT, OUT), 0.9, np.float32))
    refined = refine_map(stones, blended, iterations=1, occurrence=0.3, seed=0)
    kept = refined.blend_weight > 0      # the heavier source (the partner, weight 0.9) stayed
    assert kept.any() and (~kept).any()
    assert np.all(refined.blend_weight[kept] == np.float32(0.9))
    assert np.array_equal(refined.blend_coords[kept], partner[kept])
    assert np.array_equal(refined.coords[kept], start.coords[kept])
    assert np.array_equal(refined.coords[~kept], refined.blend_coords[~kept])


@pytest.mark.parametrize("wrap", [False, True])
def test_window_starts_cover_every_texel(wrap):
    for length, offset in ((72, 0), (72, 3), (37, 2), (8, 1)):
        starts = window_starts(length, 8, 4, offset, wrap)
        covered = np.zeros(length, bool)
        for s in starts:
            covered[(s + np.arange(8)) % length if wrap else slice(s, s + 8)] = True
        assert covered.all(), (length, offset)


@pytest.mark.parametrize("wrap", [False, True])
def test_jittered_windows_cover_every_texel_and_break_the_grid(wrap):
    for (h, w), seed in (((72, 72), 0), ((37, 45), 1), ((8, 19), 2), ((64, 64), 3)):
        rows, cols = jittered_windows(h, w, 8, wrap, np.random.default_rng(seed))
        covered = np.zeros((h, w), bool)
        for r, c in zip(rows.reshape(-1, 8), cols.reshape(-1, 8)):
            covered[np.ix_(r, c)] = True
            if not wrap:  # windows stay inside an output that does not wrap
                assert np.all(np.diff(r) == 1) and np.all(np.diff(c) == 1)
        assert covered.all(), (h, w, seed)
        if min(h, w) >= 64:  # the windows' left sides do not all line up down a column of windows
            assert len(np.unique(cols[:, 1, 0])) > 1


def test_pinned_texels_keep_their_sources_and_blends_and_shape_the_rest(stones):
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=4)
    partner = np.roll(start.coords, 1, axis=1)
    blended = CoordMap(start.coords, start.source_size, partner, np.full((OUT, OUT), 0.3, np.float32))
    pinned = np.zeros((OUT, OUT), bool)
    pinned[:24] = True
    pinned[50:60, 10:30] = True
    refined = refine_map(stones, blended, iterations=2, occurrence=0.3, seed=0, pinned=pinned)
    assert np.array_equal(refined.coords[pinned], blended.coords[pinned])
    assert np.array_equal(refined.blend_coords[pinned], partner[pinned])
    assert np.all(refined.blend_weight[pinned] == np.float32(0.3))
    assert not np.array_equal(refined.coords[~pinned], blended.coords[~pinned])   # the rest is refined
    assert refine_map(stones, blended, iterations=2, occurrence=0.3, pinned=np.ones((OUT, OUT), bool)) is blended


def test_pinned_mask_of_another_shape_is_refused(stones):
    from btforge.errors import BtforgeInputError
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=4)
    with pytest.raises(BtforgeInputError, match="pinned"):
        refine_map(stones, start, iterations=1, occurrence=0.3, pinned=np.zeros((OUT, OUT + 1), bool))


def test_a_verbatim_copy_stays_as_it_is(stones):
    """Every window of a verbatim copy is a whole exemplar window: without the occurrence term nothing beats it."""
    rows, cols = np.mgrid[0:32, 0:32]
    verbatim = CoordMap(np.stack([rows + 3, cols + 5], -1).astype(np.int32), (SIZE, SIZE))
    refined = refine_map(stones, verbatim, iterations=2, occurrence=0.0, seed=0)
    assert np.array_equal(refined.coords, verbatim.coords)


def test_coarse_scales_run_their_own_rounds(stones, monkeypatch):
    from btforge.plugins.synth import refine
    rounds_at = []
    real_step = refine.optimise_step

    def counted(index, *args, **kwargs):
        rounds_at.append(index.texels.shape[0])
        return real_step(index, *args, **kwargs)

    monkeypatch.setattr(refine, "optimise_step", counted)
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=1)
    refine_map(stones, start, iterations=1, occurrence=0.3, seed=0, patch=4, scales=1, coarse_iterations=3)
    assert rounds_at == [SIZE // 2] * 3 + [SIZE]
    rounds_at.clear()
    refine_map(stones, start, iterations=2, occurrence=0.3, seed=0, patch=4, scales=1)
    assert rounds_at == [SIZE // 2] * 2 + [SIZE] * 2


def test_halved_features_are_block_means_and_their_variance_is_the_blocks_share():
    from btforge.plugins.synth.quilting import COARSE_KEEP
    from btforge.plugins.synth.features import appearance_variance
    from btforge.plugins.synth.refine import halved, keeps_structure
    rng = np.random.default_rng(3)
    blocks = np.repeat(np.repeat(rng.standard_normal((10, 12, 3)), 2, 0), 2, 1)   # constant on 2 x 2 blocks
    checker = np.indices((20, 24)).sum(0) % 2 * 2.0 - 1.0                        # zero mean in every block
    assert np.allclose(halved(blocks), blocks[::2, ::2])
    assert appearance_variance(np.full((6, 6, 2), 0.7)) == pytest.approx(0.0, abs=1e-20)
    assert halved(np.zeros((7, 9, 1))).shape == (3, 4, 1)
    for share in (COARSE_KEEP - 0.02, COARSE_KEEP + 0.02):
        # the blocks carry `share` of the variance and the checker the rest, which halving removes exactly
        detail = checker[..., None] * np.ones(3) * np.sqrt(appearance_variance(blocks) / 3 * (1 - share) / share)
        features = blocks + detail
        kept = appearance_variance(halved(features)) / appearance_variance(features)
        assert kept == pytest.approx(share, abs=1e-9)
        assert keeps_structure(halved(features), appearance_variance(features), COARSE_KEEP) == (share >= COARSE_KEEP)


@settings(max_examples=40, deadline=None)
@given(rows=st.integers(2, 12), cols=st.integers(2, 12), dims=st.integers(1, 6), seed=st.integers(0, 2 ** 16),
       exponent=st.integers(-12, 12), offset=st.floats(-1.0, 1.0), smooth=st.booleans())
def test_the_kept_share_is_bounded_and_does_not_depend_on_scale_or_offset(rows, cols, dims, seed, exponent, offset,
                                                                          smooth):
    """Hard cases: values from 1e-12 to 1e12 wide, shifted by up to a million times their spread, noise or
    block-constant fields.  Block means never hold more variance than the texels (even sizes), and scaling or
    shifting the features leaves the kept share, hence the decision, as it was: it is a property of the texture, not
    of its units.  (Each deviation from the mean loses about 2e-16 x shift / spread of its precision in float64, at
    most 2e-10 here, so 1e-6 is a safe relative tolerance; a shift beyond that ratio would leave no digits.)"""
    from btforge.plugins.synth.features import appearance_variance
    from btforge.plugins.synth.refine import halved, keeps_structure
    rng = np.random.default_rng(seed)
    base = rng.standard_normal((rows, cols, dims))
    if smooth:
        base = np.repeat(np.repeat(base, 2, 0), 2, 1)[:2 * rows, :2 * cols]
    else:
        base = base[:2 * (rows // 2), :2 * (cols // 2)]
    shares = []
    for features in (base, (base + offset * 1e6) * 10.0 ** exponent):
        total, kept = appearance_variance(features), appearance_variance(halved(features))
        assert np.isfinite(total) and np.isfinite(kept) and 0.0 <= kept <= total * (1 + 1e-9) + 1e-300
        shares.append(kept / total)
    assert shares[1] == pytest.approx(shares[0], rel=1e-6, abs=1e-9)
    if smooth:   # block-constant: halving keeps it all
        assert keeps_structure(halved(base), appearance_variance(base), 0.999)


def test_a_coarse_scale_is_refined_only_where_it_keeps_the_exemplars_structure(monkeypatch):
    """White noise keeps a quarter of its variance at half resolution: its coarse windows all look alike, and the
    coarse rounds are skipped where a share of 0.53 must be kept; a smooth field keeps nearly all of it, and they
    run."""
    from scipy.ndimage import gaussian_filter

    from btforge.plugins.synth import refine
    rounds_at = []
    real_step = refine.optimise_step
    monkeypatch.setattr(refine, "optimise_step",
                        lambda index, *a, **k: rounds_at.append(index.texels.shape[0]) or real_step(index, *a, **k))
    rng = np.random.default_rng(0)
    noise = rng.standard_normal((SIZE, SIZE, 4)).astype(np.float32)
    smooth = gaussian_filter(noise, (4, 4, 0), mode="wrap").astype(np.float32)
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=1)
    for features, coarse_rounds in ((noise, []), (smooth, [SIZE // 2])):
        rounds_at.clear()
        refine_map(features, start, iterations=1, occurrence=0.3, seed=0, patch=4, scales=1, coarse_keep=0.53)
        assert rounds_at == coarse_rounds + [SIZE]
    rounds_at.clear()   # without a share to keep, every scale that fits runs (the default)
    refine_map(noise, start, iterations=1, occurrence=0.3, seed=0, patch=4, scales=1)
    assert rounds_at == [SIZE // 2, SIZE]


def test_the_default_contrast_weight_depends_on_how_much_larger_the_output_is():
    """A negative (default) ``contrast`` becomes the synthesizer's weight (AUTO_CONTRAST, quilting's own) up to
    AUTO_AREA x the exemplar's texels and its large-output weight beyond (0 unless it declares one: k-coherence's and
    the jump map's LARGE_CONTRAST); a given weight is kept; the stage notes the weight it used."""
    from btforge.context import StageContext
    from btforge.plugins.synth.quilting import AUTO_CONTRAST as QUILT_CONTRAST
    from btforge.plugins.synth.quilting import quilt
    from btforge.plugins.synth.synthesizer import AUTO, AUTO_AREA, AUTO_CONTRAST, automatic_weight
    assert automatic_weight(AUTO, (256, 256), (256, 256), AUTO_CONTRAST) == AUTO_CONTRAST
    assert automatic_weight(AUTO, (256, 256), (320, 320), AUTO_CONTRAST) == AUTO_CONTRAST
    assert automatic_weight(AUTO, (int(100 * AUTO_AREA), 100), (100, 100), AUTO_CONTRAST) == AUTO_CONTRAST
    assert automatic_weight(AUTO, (int(100 * AUTO_AREA) + 1, 100), (100, 100), AUTO_CONTRAST) == 0.0
    assert automatic_weight(AUTO, (256, 256), (192, 192), AUTO_CONTRAST) == 0.0
    assert automatic_weight(0.0, (256, 256), (256, 256), AUTO_CONTRAST) == 0.0
    assert automatic_weight(4.0, (256, 256), (64, 64), AUTO_CONTRAST) == 4.0
    assert automatic_weight(AUTO, (64, 64), (64, 64), 3.0) == 3.0
    assert automatic_weight(AUTO, (256, 256), (192, 192), AUTO_CONTRAST, 5.0) == 5.0
    assert automatic_weight(AUTO, (256, 256), (256, 256), AUTO_CONTRAST, 5.0) == AUTO_CONTRAST
    assert automatic_weight(2.0, (256, 256), (64, 64), AUTO_CONTRAST, 5.0) == 2.0
    lights = hemisphere_lights(8)
    stack = SampleStack(render_lights(make_pattern("stones", SIZE, SIZE, seed=2), lights)[None], lights,
                        np.array([[0.0, 0.0, 1.0]]))
    for size, expected in ((SIZE, QUILT_CONTRAST), (OUT, 0.0)):
        ctx = StageContext(node="quilt")
        quilt(ctx=ctx, exemplar=stack, size=[size, size], seed=0, block=12, overlap=4, refine=1, scales=0)
        assert ctx.notes["contrast"] == expected
    from btforge.plugins.synth.jumpmap import LARGE_CONTRAST, jumpmap
    for size, expected in ((SIZE, AUTO_CONTRAST), (OUT, LARGE_CONTRAST)):
        ctx = StageContext(node="jumpmap")
        jumpmap(ctx=ctx, exemplar=stack, size=[size, size], seed=0, refine=1, scales=0, coarse_refine=0, polish=0)
        assert ctx.notes["contrast"] == expected
    from btforge.plugins.synth.kcoherence import LARGE_CONTRAST as KC_LARGE
    from btforge.plugins.synth.kcoherence import kcoherence
    assert 0 < KC_LARGE != LARGE_CONTRAST
    for size, expected in ((SIZE, AUTO_CONTRAST), (OUT, KC_LARGE)):
        ctx = StageContext(node="kcoherence")
        kcoherence(ctx=ctx, exemplar=stack, size=[size, size], seed=0, refine=1, scales=0, coarse_refine=0, polish=0)
        assert ctx.notes["contrast"] == expected


def test_the_automatic_balance_is_on_where_the_exemplar_is_about_as_large_as_the_output():
    """A negative (default) ``appearance_balance`` becomes AUTO_BALANCE up to AUTO_AREA x the exemplar's texels and 0
    beyond (:func:`automatic_weight`, as the contrast weight): each synthesizer notes the weight it refined with."""
    from btforge.context import StageContext
    from btforge.plugins.synth.jumpmap import jumpmap
    from btforge.plugins.synth.kcoherence import kcoherence
    from btforge.plugins.synth.quilting import quilt
    from btforge.plugins.synth.synthesizer import AUTO_BALANCE
    assert AUTO_BALANCE > 0
    lights = hemisphere_lights(8)
    stack = SampleStack(render_lights(make_pattern("stones", SIZE, SIZE, seed=2), lights)[None], lights,
                        np.array([[0.0, 0.0, 1.0]]))
    few_rounds = {"refine": 1, "scales": 0, "polish": 0}
    runs = [(quilt, {"block": 12, "overlap": 4}), (jumpmap, {"coarse_refine": 0}), (kcoherence, {"coarse_refine": 0})]
    for stage, own in runs:
        for size, expected in ((SIZE, AUTO_BALANCE), (OUT, 0.0)):
            ctx = StageContext(node=stage.name)
            stage(ctx=ctx, exemplar=stack, size=[size, size], seed=0, **few_rounds, **own)
            assert ctx.notes["appearance_balance"] == expected


def test_a_polish_round_runs_last_with_small_windows_and_no_terms(stones, monkeypatch):
    """``polish`` adds rounds at the finest scale after the others, with 8 x 8 windows whatever ``patch`` is, and
    without the occurrence, contrast and balance terms; on a map refined with 12 x 12 windows it lowers the seam cost."""
    from btforge.plugins.synth import refine
    calls = []
    real_step = refine.optimise_step

    def recorded(index, src, wrap, weights, *args, **kwargs):
        calls.append((index.patch, tuple(weights)))
        return real_step(index, src, wrap, weights, *args, **kwargs)

    monkeypatch.setattr(refine, "optimise_step", recorded)
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=1)
    plain = refine_map(stones, start, iterations=2, occurrence=0.5, seed=0, patch=12, contrast=4.0)
    seam = refine.SEAM_WEIGHT
    assert calls == [(12, (0.5, 4.0, seam, 0.0))] * 2
    calls.clear()
    polished = refine_map(stones, start, iterations=2, occurrence=0.5, seed=0, patch=12, contrast=4.0, polish=1)
    assert calls == [(12, (0.5, 4.0, seam, 0.0))] * 2 + [(refine.POLISH_WINDOW, (0.0, 0.0, seam, 0.0))]
    assert seam_cost(stones, polished) < seam_cost(stones, plain)
    calls.clear()
    small = shuffled_blocks((SIZE, SIZE), (6, 6), block=3, seed=1)   # windows of 4 fit, the polish's 8 do not
    kept = refine_map(stones, small, iterations=1, occurrence=0.5, seed=0, patch=4, polish=1, recut=False)
    assert [patch for patch, _ in calls] == [4] and kept.coords.shape == (6, 6, 2)


def test_a_heavier_seam_weight_leaves_less_costly_seams(stones):
    """The vote weighs its seam cost by ``seam_weight``: heavier, its cuts run where the two sides continue each
    other more closely, so the mean appearance jump across the seams falls (there need not be fewer of them)."""
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=1)
    costs = [seam_cost(stones, refine_map(stones, start, iterations=2, occurrence=0.5, seed=0, seam_weight=w,
                                          recut=False)) for w in (0.0, 1.0, 4.0)]
    assert costs[0] > costs[1] > costs[2] and np.isfinite(costs).all()


@pytest.mark.parametrize("name", ["synth.quilt", "synth.kcoherence", "synth.jumpmap", "wang.tiles"])
def test_each_synthesizer_hands_its_seam_weight_to_every_round(name, monkeypatch):
    """Every round of the refinement, the polish's too, weighs seams by the stage's ``seam_weight`` (its declared
    default unless given)."""
    from btforge import stage
    from btforge.plugins.synth import refine
    lights = hemisphere_lights(8)
    stack = SampleStack(render_lights(make_pattern("stones", 48, 48, seed=2), lights)[None], lights,
                        np.array([[0.0, 0.0, 1.0]]))
    seen = []
    real_step = refine.optimise_step
    monkeypatch.setattr(refine, "optimise_step",
                        lambda index, src, wrap, weights, *a, **k: seen.append(weights[2]) or
                        real_step(index, src, wrap, weights, *a, **k))
    declared = {p.name: p.default for p in stage(name).params}["seam_weight"]
    size = {"tile": 16} if name == "wang.tiles" else {"size": [64, 64]}
    for chosen in ({}, {"seam_weight": 2.5}):
        seen.clear()
        stage(name)(exemplar=stack, seed=0, **size, **chosen)
        assert seen and set(seen) == {chosen.get("seam_weight", declared)}


def test_appearance_excess_is_zero_for_the_exemplar_itself_and_marks_an_overused_class(stones):
    index = window_index(stones, 8)
    labels, shares = appearance_classes(index.texels)
    assert labels.shape == (SIZE * SIZE,) and np.isclose(shares.sum(), 1.0) and (shares > 0).all()
    identity = np.arange(SIZE * SIZE).reshape(SIZE, SIZE)
    assert np.allclose(appearance_excess(identity, index), 0.0)
    commonest = int(np.argmax(shares))
    one_class = np.resize(np.flatnonzero(labels == commonest), (OUT, OUT))   # a map of that class alone
    excess = appearance_excess(one_class, index).reshape(index.grid)
    share_in_window = window_sums((labels == commonest).reshape(SIZE, SIZE).astype(float), (8, 8)) / 64
    assert np.allclose(excess, share_in_window * (1.0 / shares[commonest] - 1.0))
    assert (excess[share_in_window > 0] > 0).all()


def test_balance_term_brings_the_class_shares_towards_the_exemplar(stones):
    labels, shares = appearance_classes(window_index(stones, 8).texels)
    start = shuffled_blocks((SIZE, SIZE), (OUT, OUT), block=12, seed=2)
    def gap(coords):
        src = coords.coords[..., 0] * SIZE + coords.coords[..., 1]
        return np.abs(np.bincount(labels[src.ravel()], minlength=len(shares)) / src.size - shares).sum()
    plain = refine_map(stones, start, iterations=3, occurrence=0.0, seed=0)
    balanced = refine_map(stones, start, iterations=3, occurrence=0.0, seed=0, balance=16.0)
    assert gap(balanced) < gap(plain)
