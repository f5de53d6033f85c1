"""k-coherence synthesis: OpenCL kernels against their NumPy twins, hard inputs, seams, tiles and relighting."""
import numpy as np
import pytest

from btforge.plugins.synth import bench as synth_bench
from btforge import BtforgeInputError
from btforge.buffers import CoordMap, SampleStack
from btforge.context import StageContext
from btforge.plugins.ptm.model import PTMModel
from btforge.plugins.synth import block_start
from btforge.plugins.synth import kcoherence as kc
from btforge.plugins.synth import synthesizer, textons
from btforge.plugins.synth import materialize
from btforge.plugins.synth.features import beside, edge_padded, texel_features
from btforge.plugins.synth.kcoherence import kcoherence

LIGHTS = [[0, 0, 1], [1, 0, 1], [0, 1, 1], [-1, 0, 1], [0, -1, 1], [1, 1, 2]]


def stack_of(values: np.ndarray) -> SampleStack:
    """A single-view stack from ``[L, H, W, C]`` radiance."""
    return SampleStack(np.ascontiguousarray(values[None], np.float32), LIGHTS[:values.shape[0]], [[0, 0, 1]])


@pytest.fixture(scope="module")
def material():
    return synth_bench.benchmark_exemplar(32, lights=8)


def tiled_exemplar(period=16, copies=3, seed=0) -> SampleStack:
    tile = np.random.default_rng(seed).random((4, period, period, 3), dtype=np.float32)
    return stack_of(np.tile(tile, (1, copies, copies, 1)))


def pair_coherence(coords: np.ndarray, period: int | None = None):
    """Coherent fractions of (horizontal interior, vertical interior, horizontal seam, vertical seam) pairs.

    A pair is coherent when the second source is the first plus one texel along the pair (modulo ``period``).
    """
    c = coords.astype(np.int64)
    right, down = np.roll(c, -1, axis=1), np.roll(c, -1, axis=0)
    dh, dv = right - c, down - c
    if period:
        dh, dv = dh % period, dv % period
    h_ok = (dh[..., 0] == 0) & (dh[..., 1] == 1)
    v_ok = (dv[..., 0] == 1) & (dv[..., 1] == 0)
    return h_ok[:, :-1].mean(), v_ok[:-1].mean(), h_ok[:, -1].mean(), v_ok[-1].mean()


def seam_mismatch(coords, features):
    """Mean squared feature difference of neighbours (interior, seam), both directions pooled."""
    f = features[coords[..., 0], coords[..., 1]].astype(np.float64)
    dh = ((np.roll(f, -1, axis=1) - f) ** 2).sum(-1)
    dv = ((np.roll(f, -1, axis=0) - f) ** 2).sum(-1)
    interior = np.concatenate([dh[:, :-1].ravel(), dv[:-1].ravel()]).mean()
    seam = np.concatenate([dh[:, -1], dv[-1]]).mean()
    return interior, seam


# --------------------------------------------------------------------------------------------- kernels vs twins


@pytest.mark.parametrize("case", ["random", "one-dim", "constant", "huge", "many-centres"])
def test_kmeans_assignment_kernel_matches_numpy(case):
    rng = np.random.default_rng(1)
    if case == "random":
        x, c = rng.normal(size=(1000, 7)), rng.normal(size=(37, 7))
    elif case == "one-dim":
        x, c = rng.normal(size=(500, 1)), rng.normal(size=(5, 1))
    elif case == "constant":  # every distance ties: the first centre wins
        x, c = np.full((300, 4), 0.5), np.full((9, 4), 0.25)
    elif case == "huge":  # distances overflow to inf in float32
        x, c = rng.normal(size=(300, 3)) * 1e25, rng.normal(size=(6, 3)) * 1e25
    else:
        x, c = rng.random((2000, 32)), rng.random((300, 32))
    x, c = x.astype(np.float32), c.astype(np.float32)
    labels_cl, dist_cl = textons.assign_opencl(x, c)
    labels_np, dist_np = textons.assign_numpy(x, c)
    np.testing.assert_array_equal(labels_cl, labels_np)
    np.testing.assert_array_equal(dist_cl, dist_np)
    if case == "constant":
        assert (labels_cl == 0).all()


@pytest.mark.parametrize("wrap,levels,k,neighborhood,corrections,coverage,blocks,keep", [
    (False, 2, 4, 5, 1, 0.0, 0, 1.0), (True, 2, 3, 5, 1, 0.0, 0, 0.5), (False, 1, 1, 3, 1, 0.0, 0, 1.0),
    (True, 1, 6, 3, 1, 0.0, 0, 0.0), (False, 2, 4, 5, 2, 0.3, 0, 0.8), (True, 2, 3, 5, 3, 1.0, 0, 1.0),
    (False, 1, 6, 3, 0, 0.5, 0, 0.8), (False, 2, 6, 5, 1, 0.5, -1, 0.8), (True, 2, 4, 5, 2, 0.5, 7, 0.5),
    (False, 1, 3, 3, 1, 1.0, 5, 0.0), (True, 1, 6, 5, 0, 0.0, 16, 1.0)])
def test_synthesis_kernels_match_numpy(material, wrap, levels, k, neighborhood, corrections, coverage, blocks, keep):
    features = texel_features(material)
    analysis = kc.analyse_exemplar(features, k=k, neighborhood=neighborhood, levels=levels)
    args = dict(k=k, neighborhood=neighborhood, levels=levels, wrap=wrap, seed=5, analysis=analysis,
                corrections=corrections, coverage=coverage, blocks=blocks, keep=keep)
    a = kc.synthesize(features, (30, 23), **args)
    b = kc.synthesize(features, (30, 23), engine="numpy", **args)
    np.testing.assert_array_equal(a.coords, b.coords)


def stratum_of(origins, exemplar_size, block):
    strata = block_start.Strata.of(exemplar_size, block)
    return ((np.searchsorted(strata.lo_y, origins[:, 0], side="right") - 1) * (len(strata.lo_x) - 1)
            + np.searchsorted(strata.lo_x, origins[:, 1], side="right") - 1), strata.count


@pytest.mark.parametrize("candidates", [1, 384])
def test_block_start_uses_the_exemplar_evenly(candidates):
    rng = np.random.default_rng(0)
    features = rng.random((48, 40, 3), dtype=np.float32)
    sources = block_start.matched_blocks(rng, features, (96, 96), 8, candidates)
    rows, cols = np.divmod(sources.reshape(96, 96), 40)
    # whole pieces: each 8 x 8 block of the output is one coherent copy
    assert (np.diff(cols.reshape(12, 8, 12, 8), axis=3) == 1).all()
    assert (np.diff(rows.reshape(12, 8, 12, 8), axis=1) == 1).all()
    # origins: every stratum (about a block apart) once before any twice, so their use differs by at most one
    origins = np.stack([rows[::8, ::8].ravel(), cols[::8, ::8].ravel()], axis=1)
    stratum, count = stratum_of(origins, (48, 40), 8)
    counts = np.bincount(stratum, minlength=count)
    assert counts.max() - counts.min() <= 1, counts
    i_i_d = np.random.default_rng(0).integers(0, count, len(origins))
    assert np.bincount(i_i_d).max() - np.bincount(i_i_d, minlength=count).min() > 1
    assert kc.block_side((192, 200), -1) == 32 and kc.block_side((64, 64), -1) == 16
    assert kc.block_side((20, 30), 24) == 20


def piece_edge_cost(sources, features, block, wrap):
    """Mean seam cost over the edges between pieces (both continuation terms, as the start scores them)."""
    eh, ew = features.shape[:2]
    rows, cols = np.divmod(sources, ew)
    padded = edge_padded(features)
    total = []
    for axis, (dy, dx) in ((1, (0, 1)), (0, (1, 0))):
        a_r, a_c = rows, cols
        c_r, c_c = np.roll(rows, -1, axis=axis), np.roll(cols, -1, axis=axis)
        edge = (np.arange(rows.shape[axis]) + 1) % block == 0
        if not wrap:
            edge[-1] = False
        pick = (slice(None), edge) if axis == 1 else (edge, slice(None))
        a_r, a_c, c_r, c_c = a_r[pick], a_c[pick], c_r[pick], c_c[pick]
        cost = ((beside(padded, (eh, ew), a_r, a_c, dy, dx) - features[c_r, c_c]) ** 2).sum(-1)
        cost += ((features[a_r, a_c] - beside(padded, (eh, ew), c_r, c_c, -dy, -dx)) ** 2).sum(-1)
        total.append(cost.ravel())
    return np.concatenate(total).mean()


@pytest.mark.parametrize("wrap", [False, True])
def test_matched_pieces_continue_the_colour_areas_they_meet(wrap):
    """Smooth colour areas (a sum of slow waves): random pieces meet as unrelated colours; matched ones continue
    what is beside them, across the output's edges too when it wraps."""
    yy, xx = np.mgrid[0:64, 0:64].astype(np.float32)
    features = np.stack([np.sin(xx / 5.0 + yy / 9.0), np.cos(yy / 6.0 - xx / 11.0), np.sin((xx + yy) / 7.0)], -1)
    costs = {}
    for candidates in (1, 384):
        sources = block_start.matched_blocks(np.random.default_rng(3), features, (96, 96), 16, candidates, wrap)
        costs[candidates] = piece_edge_cost(sources.reshape(96, 96), features, 16, wrap)
    # a wrapping output's last row and column must continue two laid sides at once (the last piece four)
    assert costs[384] < (0.35 if wrap else 0.2) * costs[1], costs


def test_the_start_budget_brings_in_a_busy_half_the_seam_cost_avoids():
    """Half fine noise, half a plain ground: pieces of the ground continue each other best, so the seam cost picks
    origins whose pieces lie in the ground wherever their strata allow (a third of the output from the noise).
    Within the copy budget of 0.5 (the default for a 128 x 128 output from 96 x 96) the noise gets more of its
    half (measured: 0.34 -> 0.41, seeds 0-2)."""
    rng = np.random.default_rng(0)
    features = 0.5 + 0.01 * rng.standard_normal((96, 96, 3)).astype(np.float32)
    features[:, :48] = rng.random((96, 48, 3), dtype=np.float32)
    share = {budget: np.median([(kc.synthesize(features, (128, 128), seed=seed, budget=budget).coords[..., 1] < 48)
                                .mean() for seed in range(3)]) for budget in (0.0, 0.5)}
    assert share[0.5] > share[0.0] + 0.04, share
    assert share[0.5] > 0.38, share


def test_the_stage_starts_within_the_automatic_budget(material, monkeypatch):
    """The stage passes the automatic budget to its start: none for 48 x 48 from 32 x 32 (2.25 x the exemplar's
    texels), 0.5 for 40 x 40 (1.56 x)."""
    seen = []
    real = kc.synthesize
    monkeypatch.setattr(kc, "synthesize", lambda *a, **kw: seen.append(kw["budget"]) or real(*a, **kw))
    for size in ([48, 48], [40, 40]):
        kc.kcoherence(exemplar=material, size=size, seed=0, refine=0)
    assert seen == [0.0, 0.5]


def test_block_start_is_exact_on_a_constant_exemplar():
    features = np.ones((20, 20, 2), np.float32)
    sources = block_start.matched_blocks(np.random.default_rng(0), features, (33, 17), 8, 64, True)
    assert sources.shape == (33 * 17,) and sources.min() >= 0 and sources.max() < 400


def test_cell_excess_counts_use_beyond_the_fair_share():
    level = kc.analyse_exemplar(np.random.default_rng(0).random((10, 8, 2)).astype(np.float32), k=1,
                                neighborhood=3, levels=1)[0]
    # cells of 4: rows 4, 4, 2 by columns 4, 4; 80 sources over 80 texels give each texel a fair share of 1
    sources = np.zeros(80, np.int64)   # every source in cell 0 (16 texels): 64 beyond its share of 16
    excess = kc.cell_excess(sources, level, 4)
    assert excess.shape == (6,)
    np.testing.assert_allclose(excess, [64 / 16, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(kc.cell_excess(np.arange(80), level, 4), np.zeros(6, np.float32))


def test_coverage_evens_out_the_use_of_the_exemplar(material):
    features = texel_features(material)
    analysis = kc.analyse_exemplar(features, k=6, neighborhood=5, levels=2)
    spread = []
    for coverage in (0.0, 1.0):
        coords = kc.synthesize(features, (64, 64), k=6, neighborhood=5, levels=2, seed=3, analysis=analysis,
                               corrections=2, coverage=coverage).coords
        excess = kc.cell_excess(coords[..., 0].ravel() * 32 + coords[..., 1].ravel(), analysis[0], kc.COVERAGE_CELL)
        spread.append(float(excess.sum()))
    assert spread[1] < spread[0], spread


@pytest.mark.parametrize("order", ["single", "launch"])
def test_both_causal_pass_schedules_match_numpy(material, order, monkeypatch):
    monkeypatch.setattr(kc, "CAUSAL_ORDER", order)
    features = texel_features(material)
    args = dict(k=3, neighborhood=5, levels=2, wrap=True, seed=9)
    a = kc.synthesize(features, (45, 38), **args)
    b = kc.synthesize(features, (45, 38), engine="numpy", **args)
    np.testing.assert_array_equal(a.coords, b.coords)


@pytest.mark.parametrize("case", ["constant", "one-dim", "huge"])
def test_whole_pipeline_matches_numpy_on_hard_exemplars(case):
    rng = np.random.default_rng(4)
    if case == "constant":
        features = np.full((16, 16, 3), 0.7, np.float32)
    elif case == "one-dim":
        features = rng.random((16, 18, 1)).astype(np.float32)
    else:
        features = (rng.normal(size=(16, 16, 4)) * 1e30).astype(np.float32)
    args = dict(k=3, neighborhood=5, levels=2, seed=2)
    a = kc.synthesize(features, (20, 24), **args)
    b = kc.synthesize(features, (20, 24), engine="numpy", **args)
    np.testing.assert_array_equal(a.coords, b.coords)
    assert a.coords.min() >= 0 and a.coords[..., 0].max() < 16 and a.coords[..., 1].max() < features.shape[1]
    if case == "constant":
        assert a.levels[0].textons.count == 1


# --------------------------------------------------------------------------------------------- the stage


def test_output_shape_range_and_determinism(material):
    ctx = StageContext(node="kc", quiet=True)
    out = kcoherence(ctx=ctx, exemplar=material, size=[40, 52], k=4, levels=2, seed=7)["coords"]
    assert isinstance(out, CoordMap)
    assert out.coords.shape == (40, 52, 2) and out.coords.dtype == np.int32
    assert out.source_size == (32, 32)
    assert out.coords.min() >= 0 and out.coords.max() < 32
    again = kcoherence(exemplar=material, size=[40, 52], k=4, levels=2, seed=7)["coords"]
    np.testing.assert_array_equal(out.coords, again.coords)
    other = kcoherence(exemplar=material, size=[40, 52], k=4, levels=2, seed=8)["coords"]
    assert (other.coords != out.coords).any()
    for key in ("textons", "texton_error", "kset_distance", "coherent_fraction", "seconds_analysis"):
        assert key in ctx.notes
    assert len(ctx.notes["textons"]) == 1  # blocks (the default): only the finest level is analysed
    hierarchical = StageContext(node="kc", quiet=True)
    kcoherence(ctx=hierarchical, exemplar=material, size=[40, 52], k=4, levels=2, seed=7, blocks=0)
    assert len(hierarchical.notes["textons"]) == 2


def test_wrap_makes_the_seam_as_coherent_as_the_interior(material):
    features = textons.normalise_features(texel_features(material))
    analysis = kc.analyse_exemplar(features, k=6, neighborhood=5, levels=2)
    stats = {}
    for wrap in (False, True):
        runs = [kc.synthesize(features, (64, 64), levels=2, wrap=wrap, seed=s, analysis=analysis, blocks=0).coords
                for s in range(3)]
        coherence = np.mean([pair_coherence(c) for c in runs], axis=0)
        mismatch = np.mean([seam_mismatch(c, features) for c in runs], axis=0)
        stats[wrap] = coherence, mismatch
    (coh_open, mis_open), (coh_wrap, mis_wrap) = stats[False], stats[True]
    interior, seam = coh_wrap[:2].mean(), coh_wrap[2:].mean()
    # Appearance: neighbours across the seam differ no more than interior neighbours (without wrap: a random cut).
    assert mis_wrap[1] < 1.5 * mis_wrap[0], stats
    assert mis_open[1] > 3 * mis_open[0], stats
    # Coherent copies: the seam is where the scanline order meets itself, so fewer pairs there are exact copies
    # than in the interior (about half), but far more than without wrap (none).
    assert seam > 0.4 * interior, stats
    assert seam > coh_open[2:].mean() + 0.15, stats


def test_wrap_repairs_the_wrap_seam_like_the_block_seams(material):
    """With blocks (16 here, multiples of which the 64-texel output's edges are), the wrap-around seam is one
    more block seam: repaired as well as the inner ones with wrap, left as cut without."""
    features = textons.normalise_features(texel_features(material))

    def mismatch(coords):
        f = features[coords[..., 0], coords[..., 1]].astype(np.float64)
        dh = ((np.roll(f, -1, axis=1) - f) ** 2).sum(-1)
        dv = ((np.roll(f, -1, axis=0) - f) ** 2).sum(-1)
        inner = np.arange(15, 63, 16)
        return np.concatenate([dh[:, inner].ravel(), dv[inner].ravel()]).mean(), np.concatenate([dh[:, -1], dv[-1]]).mean()

    # keep 1: every seam pixel may change to any cheaper candidate (the default 0.5 leaves this tiny exemplar's
    # seams, inner and wrap-around alike, partly as cut, which hides what wrap does)
    stats = {wrap: np.mean([mismatch(kc.synthesize(features, (64, 64), wrap=wrap, seed=s, blocks=16,
                                                   keep=1.0).coords)
                            for s in range(3)], axis=0) for wrap in (False, True)}
    (inner_open, seam_open), (inner_wrap, seam_wrap) = stats[False], stats[True]
    assert seam_wrap < 1.5 * inner_wrap, stats
    assert seam_open > 2 * inner_open, stats


def test_periodic_tile_is_reproduced_in_large_coherent_patches():
    exemplar = tiled_exemplar(period=16, copies=3)
    coords = kcoherence(exemplar=exemplar, size=[80, 80], k=3, levels=2, seed=1)["coords"].coords
    fractions = pair_coherence(coords, period=16)
    assert np.mean(fractions[:2]) > 0.8, fractions


def test_relights_consistently_through_materialize():
    rng = np.random.default_rng(6)
    coeffs = rng.normal(0, 0.1, (24, 20, 3, 6)).astype(np.float32)
    coeffs[..., 5] += 0.6
    model = PTMModel(coeffs, np.zeros((24, 20, 0), np.float32))
    coords = kcoherence(exemplar=model, size=[30, 34], k=3, levels=2, seed=3)["coords"]
    lights = np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86]])
    relit = materialize(coords=coords, source=model)["output"].evaluate(lights)
    exemplar_relit = model.evaluate(lights)
    r, c = coords.coords[..., 0], coords.coords[..., 1]
    expected = exemplar_relit[:, :, r, c]
    if coords.blend_weight.size:   # a linear rgb PTM mixes as radiance: a feathered texel relights as the blend
        w = coords.blend_weight[None, None, :, :, None]
        partner = exemplar_relit[:, :, coords.blend_coords[..., 0], coords.blend_coords[..., 1]]
        expected = (1 - w) * expected + w * partner
    np.testing.assert_allclose(relit, expected, rtol=1e-5, atol=1e-6)
    stack = SampleStack(exemplar_relit, lights, [[0, 0, 1]])
    replayed = materialize(coords=coords, source=stack)["output"]
    assert isinstance(replayed, SampleStack)
    np.testing.assert_allclose(replayed.samples, relit, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("params,name", [
    ({"neighborhood": 4}, "neighborhood"),
    ({"neighborhood": 1}, "neighborhood"),
    ({"k": 0}, "'k'"),
    ({"size": [0, 16]}, "size"),
    ({"levels": 4}, "levels"),     # 32 -> 4 texels at the coarsest level, smaller than 5 x 5
    ({"levels": 0}, "levels"),
])
def test_invalid_params_name_the_param(material, params, name):
    with pytest.raises(BtforgeInputError) as info:
        kcoherence(exemplar=material, **{"size": [16, 16], **params})
    assert name in str(info.value)


def test_check_params_rejects_even_windows_directly():
    with pytest.raises(BtforgeInputError, match="neighborhood"):
        synthesizer.check_params("kcoherence", (64, 64), size=(8, 8), neighborhood=6, k=2, levels=1)


@pytest.mark.parametrize("params,name", [({"k": 0}, "'k'"), ({"levels": 0}, "'levels'"), ({"size": (0, 8)}, "'size'"),
                                         ({"corrections": 9}, "'corrections'")])
def test_synthesize_checks_what_the_stage_params_bound(material, params, name):
    # Direct callers skip the stage's Param bounds: synthesize runs the same validator, with a hint.
    features = texel_features(material)
    args = {"size": (8, 8), "k": 2, "levels": 1, **params}
    with pytest.raises(BtforgeInputError) as info:
        kc.synthesize(features, args.pop("size"), engine="numpy", **args)
    assert name in str(info.value) and info.value.hint


def test_benchmark_reports_figures():
    figures = synth_bench.benchmark_kcoherence(exemplar_size=16, size=24, levels=1, repeat=1)
    for key in ("median_s", "analysis_median_s", "synthesis_median_s", "device"):
        assert key in figures
    assert figures["median_s"] > 0


def test_analysis_is_kept_per_exemplar_and_params(material):
    features = texel_features(material)
    first = kc.analyse_exemplar(features, k=4, neighborhood=5, levels=2)
    assert kc.analyse_exemplar(features.copy(), k=4, neighborhood=5, levels=2) is first   # same content
    assert kc.analyse_exemplar(features, k=3, neighborhood=5, levels=2) is not first       # other params
    changed = features.copy()
    changed[0, 0, 0] += 1
    assert kc.analyse_exemplar(changed, k=4, neighborhood=5, levels=2) is not first        # other content


def test_search_param_switches_the_engine():
    exemplar = synth_bench.benchmark_exemplar(48, lights=8)   # 2304 texels: more than the fast engine searches exactly
    features = textons.normalise_features(texel_features(exemplar))
    fast = kc.analyse_exemplar(features, k=6, neighborhood=5, levels=1, search="fast")[0]
    exact = kc.analyse_exemplar(features, k=6, neighborhood=5, levels=1, search="exact")[0]
    # the fast lists are nearly the exact ones, and never better
    same = np.mean([len(np.intersect1d(a, b)) / 5 for a, b in zip(fast.ksets[:, 1:], exact.ksets[:, 1:])])
    assert same >= 0.9
    assert (fast.kset_cost[:, -1] >= exact.kset_cost[:, -1] * (1 - 1e-5)).all()   # (sums in another order)
    coords = kcoherence(exemplar=exemplar, size=[24, 24], levels=1, search="exact")["coords"].coords
    assert coords.shape == (24, 24, 2)
    with pytest.raises(BtforgeInputError, match="search"):
        kcoherence(exemplar=exemplar, size=[24, 24], search="fastest")


def test_the_refinement_re_cuts_six_passes_with_bridging_pieces(material, monkeypatch):
    """k-coherence asks the shared refinement for :data:`RECUT_PASSES` re-cut passes (four more than the shared
    default) with three bridging pieces per run; with ``refine: 0`` there is no re-cut at all."""
    from btforge.plugins.synth import recut, refine
    asked = []
    real = recut.recut_straight_seams
    monkeypatch.setattr(refine, "recut_straight_seams", lambda *a, **k: asked.append(a[4:]) or real(*a, **k))
    kcoherence(exemplar=material, size=[48, 48], seed=2, refine=0)
    assert asked == []
    kcoherence(exemplar=material, size=[48, 48], seed=2, refine=1)
    assert asked == [(kc.RECUT_PASSES, 3)] and kc.RECUT_PASSES == recut.PASSES + 4


def test_the_coarse_scale_runs_its_own_rounds(material, monkeypatch):
    """k-coherence asks the shared refinement for :data:`COARSE_ROUNDS` rounds at its coarse scale and ``refine``
    rounds at the full resolution, then for its ``polish`` rounds (:data:`POLISH_ROUNDS`, two, by default, one more
    than the shared default); ``coarse_refine`` overrides the first, and ``polish: 0`` leaves the last out."""
    from btforge.plugins.synth import refine
    from btforge.plugins.synth.synthesizer import POLISH
    asked = []
    real = refine._refine_sources
    monkeypatch.setattr(refine, "_refine_sources", lambda *a: asked.append(a[3]) or real(*a))
    kcoherence(exemplar=material, size=[48, 48], seed=2)
    kcoherence(exemplar=material, size=[48, 48], seed=2, refine=1, coarse_refine=6, polish=0)
    rounds = kc.POLISH_ROUNDS
    assert asked == [(2, kc.COARSE_ROUNDS), (rounds, rounds), (1, 6)] and kc.COARSE_ROUNDS > 2 and rounds == POLISH + 1
