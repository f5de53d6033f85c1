"""Jump-map synthesis: shared analysis on OpenCL against NumPy, the walk, seams, tiles and relighting."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from btforge.plugins.synth import bench as synth_bench
from btforge import BtforgeInputError
from btforge.buffers import CoordMap, SampleStack
from btforge.context import StageContext
from btforge.plugins.ptm.model import PTMModel
from btforge.plugins.synth import jumpmap as jm_module
from btforge.plugins.synth import search, textons
from btforge.plugins.synth import materialize
from btforge.plugins.synth.features import texel_features
from btforge.plugins.synth.jumpmap import ORDERS, automatic_overuse, build_jump_map, jumpmap, walk
from btforge.plugins.synth.scan_order import hilbert_order

LIGHTS = [[0, 0, 1], [1, 0, 1], [0, 1, 1], [-1, 0, 1]]


@pytest.fixture(scope="module")
def material():
    return synth_bench.benchmark_exemplar(32, lights=8)


def tiled_exemplar(period=16, copies=3, seed=0) -> SampleStack:
    tile = np.random.default_rng(seed).random((4, period, period, 3), dtype=np.float32)
    return SampleStack(np.tile(tile, (1, copies, copies, 1))[None], LIGHTS, [[0, 0, 1]])


def pair_coherence(coords, period=None):
    """Coherent fractions of (horizontal interior, vertical interior, horizontal seam, vertical seam) pairs."""
    c = coords.astype(np.int64)
    dh, dv = np.roll(c, -1, axis=1) - c, np.roll(c, -1, axis=0) - c
    if period:
        dh, dv = dh % period, dv % period
    h_ok = (dh[..., 0] == 0) & (dh[..., 1] == 1)
    v_ok = (dv[..., 0] == 1) & (dv[..., 1] == 0)
    return np.array([h_ok[:, :-1].mean(), v_ok[:-1].mean(), h_ok[:, -1].mean(), v_ok[-1].mean()])


def test_the_analysis_is_the_shared_search():
    # one implementation of the neighbourhood search, imported - not a copy
    assert jm_module.similar_texels is search.similar_texels
    assert jm_module.texton_analysis is textons.texton_analysis


@pytest.mark.parametrize("case", ["material", "constant", "one-dim"])
def test_jump_map_analysis_on_opencl_matches_numpy(material, case):
    if case == "material":
        features = texel_features(material)
    elif case == "constant":
        features = np.ones((12, 14, 3), np.float32)
    else:
        features = np.random.default_rng(1).random((15, 13, 1)).astype(np.float32)
    a = build_jump_map(features, jumps=3)
    b = build_jump_map(features, jumps=3, engine="numpy")
    np.testing.assert_array_equal(a.targets, b.targets)
    np.testing.assert_array_equal(a.distance, b.distance)
    np.testing.assert_array_equal(a.probability, b.probability)


@pytest.mark.parametrize("wrap,probability,size,case", [
    (False, 0.1, (37, 41), "material"), (True, 0.1, (40, 33), "material"), (True, 1.0, (16, 64), "material"),
    (False, 0.0, (25, 25), "material"), (True, 0.3, (21, 18), "constant"), (False, 0.5, (1, 30), "material"),
])
@pytest.mark.parametrize("balance,overuse", [(False, 4), (True, 4), (True, 1)])
@pytest.mark.parametrize("order", ORDERS)
def test_walk_kernel_matches_numpy(material, wrap, probability, size, case, balance, overuse, order):
    features = texel_features(material) if case == "material" else np.ones((9, 10, 2), np.float32)
    jm = build_jump_map(features, jumps=3, jump_probability=probability, neighborhood=5 if case == "material" else 3)
    a, counts_a = walk(jm, size, wrap=wrap, seed=11, balance=balance, overuse=overuse, order=order)
    b, counts_b = walk(jm, size, wrap=wrap, seed=11, balance=balance, overuse=overuse, order=order, engine="numpy")
    np.testing.assert_array_equal(a, b)
    assert counts_a == counts_b


def test_balance_evens_out_the_use_of_the_exemplar():
    """The plain walk gets caught in pockets whose jumps land in the pocket again; the balanced one spreads its
    copies (in either order)."""
    from btforge.plugins.synth.bench import benchmark_exemplar
    jm = build_jump_map(texel_features(benchmark_exemplar(64, lights=8)), jumps=3, jump_probability=0.02)
    spread = {}
    for balance in (False, True):
        use = []
        for seed in range(3):
            coords, _ = walk(jm, (128, 128), seed=seed, balance=balance)
            cells = (coords[..., 0] // 8) * 8 + coords[..., 1] // 8
            share = np.bincount(cells.ravel(), minlength=64) / (128 * 128 / 64)   # 1 = the fair share
            use.append(np.abs(share - 1).mean())
        spread[balance] = float(np.median(use))
    assert spread[True] < 0.85 * spread[False], spread


@pytest.mark.parametrize("engine", ["numpy", "opencl"])
def test_overuse_brings_in_an_exemplar_region_no_neighbourhood_leads_to(engine):
    """Two unlike halves (a smooth ramp, fine noise): jumps land only on similar neighbourhoods, so a walk that
    started in one half crosses into the other only when it leaves an over-used cell.  At ``overuse`` 1 (a cell left
    at its fair share plus one cell's worth: at most 3 / 4 of this output in one half) the other half comes in; at
    4 (the share for larger outputs) it stays out.  In scanline order: a walk that only continues down and right
    does not step back across the halves' border, as one along the Hilbert curve does."""
    rng = np.random.default_rng(3)
    ramp = np.linspace(0.2, 0.4, 48, dtype=np.float32)[None, :, None] + np.zeros((48, 1, 3), np.float32)
    noise = 0.6 + 0.3 * rng.random((48, 48, 3), dtype=np.float32)
    jm = build_jump_map(np.concatenate([ramp, noise], axis=1), jumps=3, jump_probability=0.02)
    right = {overuse: float(np.median([(walk(jm, (96, 96), seed=s, overuse=overuse, order="scanline",
                                                 engine=engine)[0][..., 1] >= 48)
                                       .mean() for s in range(3)])) for overuse in (1, 4)}
    assert 0.2 <= right[1] <= 0.8, right
    assert min(right[4], 1 - right[4]) < 0.05, right


@given(st.integers(1, 70), st.integers(1, 70))
@settings(max_examples=60, deadline=None)
def test_the_hilbert_order_visits_every_pixel_once_mostly_in_unit_steps(ho, wo):
    order = hilbert_order(ho, wo)
    np.testing.assert_array_equal(np.sort(order), np.arange(ho * wo))
    ys, xs = np.divmod(order.astype(np.int64), wo)
    steps = np.abs(np.diff(ys)) + np.abs(np.diff(xs))
    side = 1 << max(0, (min(ho, wo) - 1).bit_length())
    if min(ho, wo) == side and max(ho, wo) % side == 0:   # whole squares: every step to a 4-neighbour
        assert (steps == 1).all()


def copied_pieces(coords):
    """Connected pieces of pixels copied with the same offset, their areas and how elongated the 20 largest are
    (the square root of their coordinates' covariance eigenvalue ratio: 1 for a disc, large for a streak)."""
    h, w = coords.shape[:2]
    offset = (coords[..., 0].astype(np.int64) - np.arange(h)[:, None]) * 4 * w + coords[..., 1] - np.arange(w)
    labels, count = np.zeros((h, w), np.int64), 0
    for value in np.unique(offset):
        piece, n = ndimage.label(offset == value)
        labels[piece > 0] = piece[piece > 0] + count
        count += n
    areas = np.bincount(labels.ravel())[1:]
    elongation = []
    for index in np.argsort(areas)[::-1][:20]:
        ys, xs = np.nonzero(labels == index + 1)
        low, high = np.linalg.eigvalsh(np.cov(np.stack([ys, xs]).astype(np.float64)))
        elongation.append(np.sqrt(high / max(low, 1e-9)))
    return areas, float(np.median(elongation))


def test_the_hilbert_walk_copies_patches_where_the_scanline_walk_copies_streaks():
    """In scanline order a copy continues down and right only, and the pieces are diagonal streaks (measured: 3.9
    x as long as wide at the median); along the Hilbert curve they grow on every side (1.6) and are larger."""
    jm = build_jump_map(texel_features(synth_bench.benchmark_exemplar(64, lights=8)), jumps=3)
    found = {order: [copied_pieces(walk(jm, (128, 128), seed=seed, order=order)[0]) for seed in range(3)]
             for order in ORDERS}
    elongation = {order: np.median([e for _, e in runs]) for order, runs in found.items()}
    area = {order: np.median([(a ** 2).sum() / a.sum() for a, _ in runs]) for order, runs in found.items()}
    assert elongation["hilbert"] < 0.6 * elongation["scanline"], elongation
    assert area["hilbert"] > 1.2 * area["scanline"], area


def test_the_automatic_overuse_grows_with_the_copies_of_each_exemplar_texel():
    """Half the output's copies of each exemplar texel, at least 1: a walk from 192 x 192 to 256 x 256 leaves
    cells at their fair share; from 128 x 128 (four copies) it leaves them at twice it."""
    assert automatic_overuse((192, 192), (256, 256)) == 1
    assert automatic_overuse((128, 128), (256, 256)) == 2
    assert automatic_overuse((256, 256), (256, 256)) == 1
    assert automatic_overuse((64, 64), (256, 256)) == 8
    assert automatic_overuse((1, 1), (4096, 4096)) >= 1


def test_the_stage_uses_the_automatic_overuse_unless_given(material):
    """The 32 x 32 material grown to 64 x 64 (four copies per texel) walks at 2, the share given where one is."""
    auto, given = StageContext(node="jm", quiet=True), StageContext(node="jm", quiet=True)
    jumpmap(ctx=auto, exemplar=material, size=[64, 64], seed=0, refine=0)
    jumpmap(ctx=given, exemplar=material, size=[64, 64], seed=0, refine=0, overuse=5)
    assert (auto.notes["overuse"], given.notes["overuse"]) == (2, 5)


def test_jump_targets_are_away_from_the_texel_and_inside_the_border(material):
    features = texel_features(material)
    jm = build_jump_map(features, jumps=4, neighborhood=5, jump_probability=0.1, coverage=0.0)
    h, w = jm.height, jm.width
    ys, xs = np.divmod(np.arange(h * w), w)
    real = jm.targets >= 0
    assert real[:, 0].all()
    ty, tx = np.divmod(np.where(real, jm.targets, 0), w)
    assert (np.maximum(np.abs(ty - ys[:, None]), np.abs(tx - xs[:, None]))[real] > 2).all()
    assert ((ty >= 1) & (ty <= h - 2) & (tx >= 1) & (tx <= w - 2))[real].all()
    # choice probabilities: cumulative, ending at 1; jump chance averages the requested probability
    assert np.allclose(jm.cumulative[:, -1], 1.0)
    assert (np.diff(jm.cumulative, axis=1) >= 0).all()
    assert abs(jm.probability.mean() - 0.1) < 0.02
    # a closer neighbourhood is at least as likely a choice as a farther one
    choice = np.diff(np.concatenate([np.zeros((h * w, 1)), jm.cumulative], axis=1), axis=1)
    assert (choice[:, :-1] >= choice[:, 1:] - 1e-6).all()


def test_output_shape_range_determinism_and_notes(material):
    ctx = StageContext(node="jm", quiet=True)
    out = jumpmap(ctx=ctx, exemplar=material, size=[37, 45], seed=4)["coords"]
    assert isinstance(out, CoordMap)
    assert out.coords.shape == (37, 45, 2) and out.source_size == (32, 32)
    assert out.coords.min() >= 0 and out.coords.max() < 32
    again = jumpmap(exemplar=material, size=[37, 45], seed=4)["coords"]
    np.testing.assert_array_equal(out.coords, again.coords)
    other = jumpmap(exemplar=material, size=[37, 45], seed=5)["coords"]
    assert (other.coords != out.coords).any()
    assert ctx.notes["jumps_taken"] > 0 and ctx.notes["jump_targets"] == 32 * 32
    assert 0 < ctx.notes["coherent_fraction"] <= 1


def test_jump_probability_controls_the_jumps(material):
    jm = build_jump_map(texel_features(material), jumps=3, jump_probability=0.0)
    _, never = walk(jm, (48, 48), seed=1, balance=False)   # balance also jumps away from over-used cells
    jm = build_jump_map(texel_features(material), jumps=3, jump_probability=0.5)
    _, often = walk(jm, (48, 48), seed=1, balance=False)
    assert never["jumps_taken"] == never["forced_jumps"]      # only where a copy would leave the exemplar
    assert often["jumps_taken"] > never["jumps_taken"] + 200


def choice_probabilities(jm):
    """Each target's choice probability, from the cumulative lists (0 where the target is missing)."""
    cumulative = np.where(jm.targets >= 0, np.minimum(jm.cumulative, 1.0), 1.0)
    return np.diff(np.concatenate([np.zeros((len(cumulative), 1)), cumulative], axis=1), axis=1) * (jm.targets >= 0)


def test_coverage_evens_out_the_landings_and_keeps_the_rate(material):
    features = texel_features(material)
    plain = build_jump_map(features, jumps=6, coverage=0.0)
    balanced = build_jump_map(features, jumps=6, coverage=1.0)
    np.testing.assert_allclose(choice_probabilities(balanced).sum(axis=1), 1.0, atol=1e-6)  # per source texel
    np.testing.assert_array_equal(plain.probability, balanced.probability)   # the rate is the similarity's
    landings = [np.bincount(jm.targets.ravel()[jm.targets.ravel() >= 0],
                            weights=choice_probabilities(jm)[jm.targets >= 0], minlength=32 * 32)
                for jm in (plain, balanced)]
    assert landings[1].std() < 0.8 * landings[0].std(), [x.std() for x in landings]


@pytest.mark.parametrize("params,name", [({"jumps": 0}, "'jumps'"), ({"jump_probability": 1.5}, "'jump_probability'")])
def test_build_jump_map_checks_what_the_stage_params_bound(material, params, name):
    # Direct callers skip the stage's Param bounds; with no targets the walk would index past the lists.
    with pytest.raises(BtforgeInputError) as info:
        build_jump_map(texel_features(material), **params)
    assert name in str(info.value) and info.value.hint


def seam_mismatch(coords, features):
    """Mean squared feature difference of neighbours (interior, seam), both directions pooled."""
    f = features[coords[..., 0], coords[..., 1]].astype(np.float64)
    dh = ((np.roll(f, -1, axis=1) - f) ** 2).sum(-1)
    dv = ((np.roll(f, -1, axis=0) - f) ** 2).sum(-1)
    return np.array([np.concatenate([dh[:, :-1].ravel(), dv[:-1].ravel()]).mean(),
                     np.concatenate([dh[:, -1], dv[-1]]).mean()])


def test_wrap_makes_the_seam_as_coherent_as_the_interior(material):
    features = textons.normalise_features(texel_features(material))
    coherence, mismatch = {}, {}
    for wrap in (False, True):
        runs = [jumpmap(exemplar=material, size=[64, 64], wrap=wrap, seed=s)["coords"].coords for s in range(3)]
        coherence[wrap] = np.mean([pair_coherence(c) for c in runs], axis=0)
        mismatch[wrap] = np.mean([seam_mismatch(c, features) for c in runs], axis=0)
    stats = coherence, mismatch
    # The walk has no correction pass: the pixels that close the torus must agree with both sides, so the seam
    # is somewhat worse than the interior, but far better than the random cut without wrap.
    assert mismatch[False][1] > 3 * mismatch[False][0], stats
    assert mismatch[True][1] < 2.5 * mismatch[True][0], stats
    assert mismatch[True][1] < 0.6 * mismatch[False][1], stats
    interior, seam = coherence[True][:2].mean(), coherence[True][2:].mean()
    assert seam > 0.55 * interior, stats
    assert coherence[False][2:].mean() < 0.1, stats


def test_periodic_tile_is_reproduced_in_large_coherent_patches():
    coords = jumpmap(exemplar=tiled_exemplar(), size=[80, 80], seed=2, jump_probability=0.05)["coords"].coords
    fractions = pair_coherence(coords, period=16)
    assert fractions[:2].mean() > 0.8, fractions


def test_relights_consistently_through_materialize():
    rng = np.random.default_rng(7)
    coeffs = rng.normal(0, 0.1, (20, 22, 3, 6)).astype(np.float32)
    coeffs[..., 5] += 0.6
    model = PTMModel(coeffs, np.zeros((20, 22, 0), np.float32))
    coords = jumpmap(exemplar=model, size=[33, 29], seed=3)["coords"]
    lights = np.array([[0.2, -0.3, 0.93]])
    relit = materialize(coords=coords, source=model)["output"].evaluate(lights)
    exemplar_relit = model.evaluate(lights)
    r, c = coords.coords[..., 0], coords.coords[..., 1]
    assert coords.blend_weight.size      # a linear RGB PTM blends, so the seams that stand out are feathered
    w = coords.blend_weight[..., None]
    partner = exemplar_relit[:, :, coords.blend_coords[..., 0], coords.blend_coords[..., 1]]
    np.testing.assert_allclose(relit, (1 - w) * exemplar_relit[:, :, r, c] + w * partner, rtol=1e-5, atol=1e-6)
    stack = materialize(coords=coords, source=SampleStack(exemplar_relit, lights, [[0, 0, 1]]))["output"]
    np.testing.assert_allclose(stack.samples, relit, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("params,name", [
    ({"neighborhood": 6}, "neighborhood"),
    ({"size": [8, 0]}, "size"),
    ({"jumps": 0}, "jumps"),
    ({"jump_probability": 1.5}, "jump_probability"),
])
def test_invalid_params_name_the_param(material, params, name):
    with pytest.raises(BtforgeInputError) as info:
        jumpmap(exemplar=material, **{"size": [16, 16], **params})
    assert name in str(info.value)


def test_tiny_exemplar_is_rejected():
    tiny = SampleStack(np.ones((1, 4, 2, 5, 3), np.float32), LIGHTS, [[0, 0, 1]])
    with pytest.raises(BtforgeInputError, match="exemplar"):
        jumpmap(exemplar=tiny, size=[8, 8], neighborhood=3)


def test_refinement_window_is_the_stage_param(material):
    """The jump map refines with its own window size; 0 refinement rounds leave the walk as it is."""
    default = jumpmap(exemplar=material, size=[48, 48], seed=2)["coords"]
    eight = jumpmap(exemplar=material, size=[48, 48], seed=2, window=8)["coords"]
    assert (default.coords != eight.coords).any()
    walked = jumpmap(exemplar=material, size=[48, 48], seed=2, refine=0)["coords"]
    coords, _ = walk(jm_module.cached_jump_map(texel_features(material), jumps=3,
                                               jump_probability=jm_module.JUMP_PROBABILITY, neighborhood=5,
                                               textons=textons.DEFAULT_TEXTONS, search="fast",
                                               coverage=jm_module.COVERAGE), (48, 48), seed=2)
    np.testing.assert_array_equal(walked.coords, coords)
    for bad in (3, 33):
        with pytest.raises(BtforgeInputError, match="window"):
            jumpmap(exemplar=material, size=[16, 16], window=bad)


def test_the_jump_maps_refinement_recuts_one_pass_more(material, monkeypatch):
    """The stage asks the shared refinement for :data:`RECUT_PASSES` re-cut passes with :data:`BRIDGE_TRIES`
    bridging pieces per run (the passes themselves: ``tests/test_recut.py``)."""
    from btforge.plugins.synth import recut, refine
    asked = []
    real = recut.recut_straight_seams
    monkeypatch.setattr(refine, "recut_straight_seams", lambda *a, **k: asked.append(a[4:]) or real(*a, **k))
    jumpmap(exemplar=material, size=[64, 64], seed=3, refine=1)
    assert asked == [(jm_module.RECUT_PASSES, jm_module.BRIDGE_TRIES)] and jm_module.RECUT_PASSES > recut.PASSES


def test_the_refinement_ends_with_the_jump_maps_polish_rounds(material, monkeypatch):
    """The jump map asks the shared refinement for its rounds, then for :data:`POLISH_ROUNDS` polish rounds (two, one
    more than the shared default: its 12 x 12 windows leave more cuts to move); ``polish: 0`` leaves them out."""
    from btforge.plugins.synth import refine
    from btforge.plugins.synth.synthesizer import POLISH
    asked = []
    real = refine._refine_sources
    monkeypatch.setattr(refine, "_refine_sources", lambda *a: asked.append(a[3]) or real(*a))
    jumpmap(exemplar=material, size=[48, 48], seed=1)
    rounds = jm_module.POLISH_ROUNDS
    assert asked[-1] == (rounds, rounds) and rounds == POLISH + 1
    asked.clear()
    jumpmap(exemplar=material, size=[48, 48], seed=1, polish=0)
    assert (rounds, rounds) not in asked and asked
