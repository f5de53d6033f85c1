"""Image quilting: OpenCL kernels against their NumPy twins, the exact rejection search against brute force,
seams, periodic results, and the stage on real per-texel buffers."""
from pathlib import Path

import numpy as np
import pytest

from btforge import BtforgeInputError
from btforge.buffers import SampleStack
from btforge.context import StageContext
from btforge.plugins.ptm.model import PTMModel
from btforge.plugins.synth import materialize
from btforge.plugins.synth.features import texel_features
from btforge.plugins.synth.quilt_search import (
    QuiltSearch, haar_functions, project_dense, project_numpy, project_opencl, reject_numpy, reject_opencl,
    shape_texels, ssd_numpy, ssd_opencl, summed_area,
)
from btforge.plugins.synth.quilt_seams import min_cut
from btforge.plugins.synth.bench import benchmark_quilt, exemplar_model, smooth_fields, smooth_ptm_exemplar
from btforge.plugins.synth.quilting import axis_layout, quilt, quilt_features

BLOCK, OVERLAP = 8, 2
SMALL = dict(block=BLOCK, overlap=OVERLAP)


def fields(size=24, dims=9, seed=0, sigma=2.0):
    return smooth_fields(size, dims, seed, sigma)


def candidates(feats, block):
    h, w, _ = feats.shape
    rows, cols = np.divmod(np.arange((h - block + 1) * (w - block + 1)), w - block + 1)
    return rows, cols, (rows * w + cols).astype(np.int32)


def relative_error(a, b):
    return float(np.abs(np.asarray(a, np.float64) - b).max() / max(np.abs(b).max(), 1e-30))


# ----------------------------------------------------------------------------------------------- kernels


HARD_EXEMPLARS = {
    "random": lambda: np.random.default_rng(1).normal(size=(20, 23, 9)).astype(np.float32),
    "constant": lambda: np.full((20, 23, 9), 0.7, np.float32),
    "huge": lambda: (np.random.default_rng(2).normal(size=(20, 23, 9)) * 1e15).astype(np.float32),
    "one_dim": lambda: np.random.default_rng(3).normal(size=(20, 23, 1)).astype(np.float32),
}


@pytest.mark.parametrize("name", list(HARD_EXEMPLARS))
def test_ssd_kernel_matches_numpy(name):
    feats = HARD_EXEMPLARS[name]()
    _, _, bases = candidates(feats, BLOCK)
    dy, dx = shape_texels(BLOCK, (OVERLAP, 0, OVERLAP, 0))
    offsets = (dy * feats.shape[1] + dx).astype(np.int32)
    query = feats[5:5 + BLOCK, 7:7 + BLOCK][dy, dx] + np.float32(0.5 if name != "huge" else 1e14)
    for q in (query, feats[0:BLOCK, 0:BLOCK][dy, dx]):  # and a query equal to candidate 0: distance exactly 0
        gpu = ssd_opencl(feats, bases, offsets, q)
        ref = ssd_numpy(feats, bases, offsets, q)
        assert gpu.shape == ref.shape == (len(bases),)
        assert relative_error(gpu, ref) < 1e-5
    assert gpu[0] == 0
    if name == "constant":
        assert np.all(gpu == gpu[0])  # every candidate ties, exactly


@pytest.mark.parametrize("key", [(2, 0, 2, 0), (0, 0, 3, 0), (2, 2, 3, 3), (3, 0, 2, 2)])
def test_haar_basis_is_orthonormal(key):
    funcs = haar_functions(BLOCK, key, 3)
    dy, dx = shape_texels(BLOCK, key)
    dense = funcs.dense(dy, dx, 3)
    assert len(funcs) == len(dy) * 3  # a complete basis of the overlap
    np.testing.assert_allclose(dense.T @ dense, np.eye(len(funcs)), atol=1e-12)


@pytest.mark.parametrize("name", list(HARD_EXEMPLARS))
def test_project_kernel_matches_numpy_and_definition(name):
    feats = HARD_EXEMPLARS[name]()
    key = (OVERLAP, 0, OVERLAP, 0)
    rows, cols, bases = candidates(feats, BLOCK)
    mean = feats.reshape(-1, feats.shape[2]).astype(np.float64).mean(axis=0)
    sat = summed_area(feats.astype(np.float64) - mean)
    funcs = haar_functions(BLOCK, key, feats.shape[2])
    funcs = funcs.take(np.arange(min(40, len(funcs)))).padded(8)
    gpu = project_opencl(feats, sat, rows, cols, funcs)
    ref = project_numpy(sat, rows, cols, funcs)
    dy, dx = shape_texels(BLOCK, key)
    offsets = (dy * feats.shape[1] + dx).astype(np.int32)
    exact = project_dense(feats, bases, offsets, funcs.dense(dy, dx, feats.shape[2]), mean)
    assert gpu.shape == ref.shape == exact.shape == (len(funcs), len(bases))
    scale = max(np.abs(exact).max(), 1e-30) if name != "constant" else 1.0
    assert np.abs(gpu - ref).max() <= 1e-6 * scale
    assert np.abs(gpu - exact).max() <= 1e-6 * scale
    if name == "constant":
        assert np.abs(gpu).max() < 1e-5  # the mean is removed: nothing left to project


def _reject_case(name, seed=0):
    rng = np.random.default_rng(seed)
    feats = HARD_EXEMPLARS[name]()
    _, _, bases = candidates(feats, BLOCK)
    dy, dx = shape_texels(BLOCK, (OVERLAP, 0, OVERLAP, 0))
    offsets = (dy * feats.shape[1] + dx).astype(np.int32)
    query = feats[3:3 + BLOCK, 4:4 + BLOCK][dy, dx]
    scale = float(np.abs(feats).max()) or 1.0
    proj = (rng.normal(size=(24, len(bases))) * scale).astype(np.float32)
    qproj = (rng.normal(size=24) * scale).astype(np.float32)
    return proj, qproj, feats, bases, offsets, query, scale


@pytest.mark.parametrize("name", list(HARD_EXEMPLARS))
@pytest.mark.parametrize("limit_kind", ["typical", "zero", "infinite", "ties"])
def test_reject_kernel_matches_numpy(name, limit_kind):
    proj, qproj, feats, bases, offsets, query, scale = _reject_case(name)
    if limit_kind == "ties":  # every candidate has the same projections: all drop or survive together
        proj[:] = proj[:, :1]
    limit = {"typical": np.linspace(2, 30, 24) * scale ** 2, "zero": np.zeros(24), "infinite": np.full(24, np.inf),
             "ties": np.linspace(2, 30, 24) * scale ** 2}[limit_kind].astype(np.float32)
    used_gpu, dist_gpu = reject_opencl(proj, qproj, limit, feats, bases, offsets, query)
    used_ref, dist_ref = reject_numpy(proj, qproj, limit, feats, bases, offsets, query)
    np.testing.assert_array_equal(used_gpu, used_ref)  # same float32 operations in the same order
    assert relative_error(dist_gpu, dist_ref) < 1e-5
    alive = used_gpu > len(qproj)
    if limit_kind == "infinite":
        assert alive.all()
    if limit_kind == "zero":
        assert not alive.any() and (used_gpu <= 8).all()
    if limit_kind == "ties":
        assert len(set(used_gpu.tolist())) == 1
    # survivors carry the brute-force distance, exactly as quilt_ssd computes it
    np.testing.assert_array_equal(dist_gpu[alive], ssd_opencl(feats, bases[alive], offsets, query))


def test_projected_bound_never_exceeds_the_distance():
    feats = fields(24, 5, seed=4)
    search = QuiltSearch(feats, BLOCK, method="rejection", projections=64)
    shape = search.shape((OVERLAP, 0, OVERLAP, 0))
    dense = shape.funcs.dense(shape.dy, shape.dx, feats.shape[2])
    rng = np.random.default_rng(0)
    for _ in range(5):
        y, x = rng.integers(0, 16, 2)
        block = (feats[y:y + BLOCK, x:x + BLOCK] + rng.normal(0, 0.3, (BLOCK, BLOCK, 5))).astype(np.float32)
        query = block[shape.dy, shape.dx]
        qp, _ = search._query_projections(shape, block)
        np.testing.assert_allclose(qp, (query.reshape(-1) - np.tile(search.mean, len(shape.dy))) @ dense, atol=1e-9)
        lb = np.cumsum((project_numpy(search.sat, search.cand_rows, search.cand_cols, shape.funcs) - qp[:, None]) ** 2,
                       axis=0)
        d = ssd_numpy(feats, search.bases, shape.offsets, query)
        assert np.all(lb <= d * (1 + 1e-5) + 1e-9)


# ----------------------------------------------------------------------------------------------- exactness


@pytest.mark.parametrize("wrap", [False, True])
@pytest.mark.parametrize("seam", ["cut", "blend"])
def test_rejection_picks_exactly_what_brute_force_picks(wrap, seam):
    for seed, size, ex in ((0, (48, 48), fields(24, 9, 1)), (7, (40, 54), fields(24, 9, 2, sigma=1.0)),
                           (3, (48, 36), fields(28, 9, 3, sigma=4.0))):
        kwargs = dict(search="brute", seam=seam, wrap=wrap, seed=seed, **SMALL)
        brute = quilt_features(ex, size, **kwargs)
        rejection = quilt_features(ex, size, **{**kwargs, "search": "rejection"})
        np.testing.assert_array_equal(rejection.coords.coords, brute.coords.coords)
        np.testing.assert_array_equal(rejection.coords.blend_weight, brute.coords.blend_weight)
        np.testing.assert_array_equal(rejection.coords.blend_coords, brute.coords.blend_coords)
        assert rejection.stats["full_distance_fraction"] < 0.5  # and it did reject most candidates


@pytest.mark.parametrize("budget", [1.0, 2.0])
def test_rejection_keeps_exactness_within_the_copy_budget(budget):
    """Only blocks within the budget are eligible: the rejection's threshold comes from them, so it still picks
    exactly what brute force picks among them."""
    for seed, ex in ((0, fields(24, 9, 1)), (5, sparse_features())):
        kwargs = dict(search="brute", seed=seed, spread=True, budget=budget, **SMALL)
        brute = quilt_features(ex, (48, 48), **kwargs)
        rejection = quilt_features(ex, (48, 48), **{**kwargs, "search": "rejection"})
        np.testing.assert_array_equal(rejection.coords.coords, brute.coords.coords)


@pytest.mark.parametrize("budget", [0.01, 0.5, 0.99])
def test_a_budget_below_one_still_lets_the_least_used_blocks_through(budget):
    """Below a budget of 1 every block's area can be copied more than the budget allows; the least-used blocks stay
    eligible instead of none (a ValueError from an empty choice, as `--set synth.budget=0.5` once gave)."""
    from btforge.plugins.synth.visibility import evenness
    result = quilt_features(sparse_features(), (64, 64), search="brute", seed=0, spread=True, budget=budget, **SMALL)
    assert result.coords.coords.shape == (64, 64, 2) and evenness(result.coords) > 0.3


def sparse_features(size=48, seed=0):
    """A plain ground (faint noise) with a few bright marks."""
    rng = np.random.default_rng(seed)
    ex = rng.normal(0.0, 0.01, (size, size, 3)).astype(np.float32)
    for y, x in ((6, 30), (26, 8), (36, 36)):
        ex[y:y + 5, x:x + 5] += np.float32(3.0)
    return ex


def test_copy_budget_uses_all_of_an_object_on_a_plain_ground():
    """A 192 x 192 crop of the painted icon: a face on a smooth ground.  The ground's blocks continue each other
    almost exactly, so without a budget only ground blocks are within tolerance of the best and the output is
    ground; within the budget the face's parts are used too."""
    from btforge.plugins.synth.visibility import evenness
    model = exemplar_model(str(Path(__file__).parents[1] / "graphs/data/icon_san_michele/dirs.lp"), 192)
    features = texel_features(model)
    even = {budget: evenness(quilt_features(features, (256, 256), block=32, overlap=5, tolerance=0.5, seed=0,
                                            spread=True, budget=budget).coords)
            for budget in (0.0, 2.0)}
    assert even[0.0] < 0.3 and even[2.0] >= 0.5, even


def quilted_share(model, mask: np.ndarray, seed: int, **params) -> float:
    """The share of a 256 x 256 ``synth.quilt`` output of ``model`` (at ``params``) copied from texels in ``mask``."""
    from btforge import stage
    coords = stage("synth.quilt")(exemplar=model, size=[256, 256], seed=seed, **params)["coords"].coords
    return float(mask[coords[..., 0], coords[..., 1]].mean())


def test_a_tight_budget_gives_an_object_its_share_of_a_large_output():
    """The quilting demo's 96 x 96 patch of the icon (a dark object on a light ground, about half of it dark by a
    mid-luminance threshold) grown to 256 x 256, seven times its area.  The ground's blocks match each other best,
    so the budget decides how much of the object comes through: at 2 (version 10's default) about a seventh of the
    output is dark, at the default 1.5 more, at 1 (the demo graph's setting) about the patch's own share."""
    from btforge import stage
    from btforge.plugins.stackio.images import load_stack
    capture = load_stack(Path(__file__).parents[1] / "graphs/data/icon_san_michele/dirs.lp")
    patch = stage("synth.crop")(input=capture, origin=[240, 60], size=[96, 96])["output"]
    model = stage("ptm.fit")(stack=patch, variant="lrgb", basis="orthonormal")["model"]
    luminance = texel_features(model)[..., 0]
    dark = luminance < (luminance.min() + luminance.max()) / 2

    for seed in (0, 1):
        shares = {"2": quilted_share(model, dark, seed, budget=2.0), "default": quilted_share(model, dark, seed),
                  "1": quilted_share(model, dark, seed, budget=1.0)}
        assert shares["2"] < 0.2 < shares["default"] < shares["1"], shares
        assert abs(shares["1"] - dark.mean()) < 0.1, (shares, float(dark.mean()))


def test_the_automatic_budget_is_tight_only_where_the_output_is_at_most_twice_the_exemplar():
    """A budget under 1 stays above the running fair share only up to 1 / (1 - budget) copies: 0.5 up to twice the
    exemplar's texels, the synthesizer's own beyond (quilting 1.5, k-coherence's start none); a budget given (0
    included) is kept."""
    from btforge.plugins.synth.kcoherence import LARGE_BUDGET
    from btforge.plugins.synth.quilting import BUDGET
    from btforge.plugins.synth.synthesizer import SMALL_OUTPUT_BUDGET, auto_budget
    assert auto_budget(-1.0, (256, 256), (192, 192), BUDGET) == SMALL_OUTPUT_BUDGET == 0.5
    assert auto_budget(-1.0, (256, 256), (182, 182), BUDGET) == SMALL_OUTPUT_BUDGET   # 1.98 x
    assert auto_budget(-1.0, (256, 256), (180, 180), BUDGET) == BUDGET == 1.5         # 2.02 x
    assert auto_budget(-1.0, (256, 256), (128, 128), BUDGET) == BUDGET
    assert auto_budget(-1.0, (256, 256), (128, 128), LARGE_BUDGET) == 0.0             # k-coherence's start: no limit
    assert [auto_budget(b, (256, 256), (192, 192), BUDGET) for b in (0.0, 1.0, 2.0)] == [0.0, 1.0, 2.0]


def test_the_automatic_overlap_is_wider_on_a_smooth_exemplar():
    """``overlap: 0`` gives a smooth exemplar (fields smoothed over 8 texels, grain about 0.2) a quarter of the block
    and a grainy one (white noise) Efros & Freeman's sixth, never less as the exemplar grows smoother, and always a
    valid overlap; the stage notes the one it used, and an overlap given is kept."""
    from btforge.plugins.synth.feather import grain
    from btforge.plugins.synth.quilting import auto_overlap
    smooth = smooth_ptm_exemplar(48, sigma=8.0)
    noise = np.random.default_rng(0).standard_normal((48, 48, 9)).astype(np.float32)
    assert grain(texel_features(smooth)) < 0.25 < 0.5 < grain(noise)
    assert auto_overlap(32, grain(texel_features(smooth))) == 8 and auto_overlap(32, grain(noise)) == 32 // 6
    for block in range(3, 65):
        overlaps = [auto_overlap(block, g) for g in np.linspace(0.0, 1.0, 21)]
        assert all(1 <= o and 2 * o < block for o in overlaps)
        assert all(a >= b for a, b in zip(overlaps, overlaps[1:]))
    for overlap, noted in ((0, 4), (3, 3)):
        ctx = StageContext(node="quilt")
        quilt(ctx=ctx, exemplar=smooth, size=[48, 48], seed=0, block=16, overlap=overlap, refine=0, feather=0)
        assert ctx.notes["overlap"] == noted


@pytest.mark.shared_data
def test_the_default_budget_gives_a_paintings_pale_ground_its_share(shared_data):
    """RealRTI's item5 (figures on a pale ground), its central 192 x 192 texels grown to 256 x 256 (1.8 x the
    area): at a budget of 1.5 the dark figures, whose blocks continue each other best, took 71 % of the output
    (half of the exemplar is darker than its median); at the default 0.5 every part is copied about equally."""
    model = exemplar_model(str(shared_data / "rti/realrti/item5/dirs.lp"), 192)
    luminance = texel_features(model)[..., 0]
    dark = luminance < np.median(luminance)
    default, loose = quilted_share(model, dark, 0), quilted_share(model, dark, 0, budget=1.5)
    assert abs(default - 0.5) < 0.1 and loose > 0.65, (default, loose)


def tiled(period=6, reps=4, dims=3, seed=0):
    tile = np.random.default_rng(seed).normal(size=(period, period, dims)).astype(np.float32)
    return np.tile(tile, (reps, reps, 1)), tile


HARD_RUNS = {
    "constant (all tie)": lambda: np.full((24, 24, 2), 0.25, np.float32),
    "repeated tile (exact matches)": lambda: tiled()[0],
    "one dimension": lambda: fields(24, 1, 5),
    "huge values": lambda: fields(24, 3, 6) * np.float32(1e15),
    "overflowing distances": lambda: fields(24, 3, 6) * np.float32(1e19),
    "tiny values": lambda: fields(24, 3, 7) * np.float32(1e-18),
    "large offset": lambda: fields(24, 3, 8) * np.float32(1e-3) + np.float32(1e3),
}


@pytest.mark.parametrize("name", list(HARD_RUNS))
@pytest.mark.parametrize("tolerance", [0.0, 0.1, 2.0])
def test_rejection_equals_brute_on_hard_exemplars(name, tolerance):
    ex = HARD_RUNS[name]()
    for wrap in (False, True):
        kwargs = dict(search="brute", seed=11, tolerance=tolerance, wrap=wrap, **SMALL)
        brute = quilt_features(ex, (36, 36), **kwargs).coords.coords
        rejection = quilt_features(ex, (36, 36), **{**kwargs, "search": "rejection"}).coords.coords
        np.testing.assert_array_equal(rejection, brute)


def test_numpy_engine_rejection_equals_its_brute_force():
    ex = fields(20, 4, 9)
    kwargs = dict(seed=2, engine="numpy", **SMALL)
    brute = quilt_features(ex, (32, 32), search="brute", **kwargs)
    rejection = quilt_features(ex, (32, 32), search="rejection", **kwargs)
    np.testing.assert_array_equal(rejection.coords.coords, brute.coords.coords)


def test_ties_resolve_by_the_seed():
    ex = np.full((24, 24, 2), 0.25, np.float32)  # every candidate is equally good
    first = quilt_features(ex, (40, 40), seed=4, **SMALL).coords.coords
    again = quilt_features(ex, (40, 40), seed=4, **SMALL).coords.coords
    other = quilt_features(ex, (40, 40), seed=5, **SMALL).coords.coords
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)


# ----------------------------------------------------------------------------------------------- synthesis


def test_same_seed_same_result_different_seed_different():
    ex = fields(24, 9, 1)
    a = quilt_features(ex, (48, 48), seed=1, **SMALL).coords
    b = quilt_features(ex, (48, 48), seed=1, **SMALL).coords
    c = quilt_features(ex, (48, 48), seed=2, **SMALL).coords
    np.testing.assert_array_equal(a.coords, b.coords)
    assert a.content_key == b.content_key
    assert not np.array_equal(a.coords, c.coords)


@pytest.mark.parametrize("size", [(48, 48), (37, 53), (8, 8)])
def test_output_shape_and_coords_inside_the_exemplar(size):
    ex = fields(24, 9, 1)[:20, :23]
    coords = quilt_features(ex, size, seed=3, **SMALL).coords
    assert coords.coords.shape == (*size, 2) and coords.coords.dtype == np.int32
    assert coords.source_size == (20, 23)
    assert coords.coords[..., 0].min() >= 0 and coords.coords[..., 0].max() < 20
    assert coords.coords[..., 1].min() >= 0 and coords.coords[..., 1].max() < 23


def _wrap_seam_error(feats_out):
    """Mean squared feature difference across the periodic boundary (rows and columns), and between all interior
    neighbours (which includes every interior block seam)."""
    across = np.concatenate([((feats_out[-1] - feats_out[0]) ** 2).sum(-1),
                             ((feats_out[:, -1] - feats_out[:, 0]) ** 2).sum(-1)])
    inside = np.concatenate([((feats_out[1:] - feats_out[:-1]) ** 2).sum(-1).ravel(),
                             ((feats_out[:, 1:] - feats_out[:, :-1]) ** 2).sum(-1).ravel()])
    return across.mean(), inside.mean()


def test_wrap_makes_the_result_tile_seamlessly():
    ex = fields(32, 3, 12, sigma=3.0)
    errors = {}
    for wrap in (False, True):
        per_seed = []
        for seed in range(3):
            coords = quilt_features(ex, (48, 48), seed=seed, wrap=wrap, block=12, overlap=3).coords
            assert coords.wrap == wrap
            per_seed.append(_wrap_seam_error(ex[coords.coords[..., 0], coords.coords[..., 1]]))
        errors[wrap] = np.mean(per_seed, axis=0)
    across_wrap, inside_wrap = errors[True]
    across_plain, _ = errors[False]
    assert across_wrap < 3 * inside_wrap           # the periodic seam is like any interior seam
    assert across_plain > 5 * across_wrap          # and far better than an unwrapped result's


def test_wrap_layout_tiles_the_period_exactly():
    for size in (48, 50, 61, 512):
        layout = axis_layout(size, 32 if size == 512 else 8, 6 if size == 512 else 2, True)
        block = 32 if size == 512 else 8
        ends = [s + block for s in layout.starts]
        assert layout.canvas == size and layout.starts[0] == 0
        assert all(b > 0 for b in layout.before[1:]) and layout.after[-1] > 0
        assert ends[-1] - size == layout.after[-1]  # the last block overlaps the first across the boundary


def _overlap_mask(size, block, overlap):
    count = np.zeros(size, int)
    ly, lx = axis_layout(size[0], block, overlap, False), axis_layout(size[1], block, overlap, False)
    for y in ly.starts:
        for x in lx.starts:
            count[y:y + block, x:x + block] += 1
    return count > 1


def test_cut_has_no_blend_record_and_blend_weights_lie_in_overlaps():
    ex = fields(24, 9, 1)
    cut = quilt_features(ex, (48, 48), seam="cut", seed=0, **SMALL).coords
    assert cut.blend_weight.size == 0 and cut.blend_coords.size == 0
    blend = quilt_features(ex, (48, 48), seam="blend", seed=0, **SMALL).coords
    w = blend.blend_weight
    assert w.shape == (48, 48) and w.dtype == np.float32
    assert w.min() >= 0 and w.max() <= 1
    assert (w > 0).any()
    assert not (w > 0)[~_overlap_mask((48, 48), BLOCK, OVERLAP)].any()


def test_min_cut_follows_the_valley():
    err = np.ones((6, 4))
    valley = [2, 2, 1, 1, 2, 3]
    err[np.arange(6), valley] = 0
    np.testing.assert_array_equal(min_cut(err), valley)
    np.testing.assert_array_equal(min_cut(np.zeros((5, 3))), [0] * 5)  # ties: the smallest column


def test_repeated_tile_exemplar_gives_tile_consistent_output():
    ex, tile = tiled(period=6, reps=4)
    period = tile.shape[0]
    for seam in ("cut", "blend"):
        coords = quilt_features(ex, (48, 48), seam=seam, seed=5, **SMALL).coords
        yy, xx = np.indices((48, 48))
        if seam == "cut":  # every copied texel continues the pattern with one global phase
            phase_y = np.unique((coords.coords[..., 0] - yy) % period)
            phase_x = np.unique((coords.coords[..., 1] - xx) % period)
            assert len(phase_y) == 1 and len(phase_x) == 1
        # and what is shown - blends included - is the tile itself
        out = materialize_features(ex, coords)
        ref = tile[(yy + (coords.coords[0, 0, 0] % period)) % period, (xx + (coords.coords[0, 0, 1] % period)) % period]
        np.testing.assert_allclose(out, ref, atol=1e-5)


def materialize_features(feats, coords):
    rows, cols = coords.coords[..., 0], coords.coords[..., 1]
    out = feats[rows, cols]
    if coords.blend_weight.size:
        w = coords.blend_weight[..., None]
        out = (1 - w) * out + w * feats[coords.blend_coords[..., 0], coords.blend_coords[..., 1]]
    return out


# ----------------------------------------------------------------------------------------------- the stage


def ptm_exemplar(size=24, seed=0):
    f = fields(size, 9, seed)
    coeffs = (f[..., :6] * np.array([0.15, 0.08, 0.08, 0.05, 0.04, 0.04], np.float32))[:, :, None, :]
    coeffs[..., 5] += 0.8  # raw constant term: positive radiance
    albedo = np.clip(0.5 + 0.2 * f[..., 6:], 0, 1).astype(np.float32)
    return PTMModel(coeffs.astype(np.float32), albedo, "lrgb", "linear")


LIGHTS = np.array([[0, 0, 1], [0.5, 0.2, 0.84], [-0.6, 0.3, 0.74], [0.1, -0.7, 0.7]], np.float64)


@pytest.mark.parametrize("seam", ["cut", "blend"])
def test_stage_on_a_ptm_and_materialize_relights_consistently(seam):
    model = ptm_exemplar()
    ctx = StageContext(node="quilt")
    feather = 0 if seam == "cut" else 1
    coords = quilt(ctx=ctx, exemplar=model, size=[48, 48], seam=seam, seed=1, **{**SMALL, "feather": feather})["coords"]
    assert coords.coords.shape == (48, 48, 2) and coords.source_size == (24, 24)
    fractions = ctx.notes["rejected_after_projection"]
    assert isinstance(fractions, list) and fractions and all(0 <= f <= 1 for f in fractions)
    assert fractions == sorted(fractions)  # cumulative
    assert ctx.notes["candidates"] == 17 * 17 and ctx.notes["queries"] == ctx.notes["blocks"] - 1
    out = materialize(coords=coords, source=model)["output"]
    assert isinstance(out, PTMModel) and (out.height, out.width) == (48, 48)
    relit = out.evaluate(LIGHTS)
    source = model.evaluate(LIGHTS)
    rows, cols = coords.coords[..., 0], coords.coords[..., 1]
    if seam == "cut":
        assert not coords.blend_weight.size and out.variant == "lrgb"
        np.testing.assert_allclose(relit, source[:, :, rows, cols], rtol=1e-5, atol=1e-6)
        return
    # A linear lrgb texel is colour x polynomial: its blends replay exactly through the rgb PTM of the same
    # functions, whose radiance (positive here, so no clamp intervenes) is the blend of the two sources'.
    assert model.variant == "lrgb" and out.variant == "rgb" and (coords.blend_weight > 0).any()
    w = coords.blend_weight[None, None, :, :, None]
    other = source[:, :, coords.blend_coords[..., 0], coords.blend_coords[..., 1]]
    np.testing.assert_allclose(relit, (1 - w) * source[:, :, rows, cols] + w * other, rtol=1e-5, atol=1e-6)


def test_stage_on_a_sample_stack():
    rng = np.random.default_rng(3)
    base = fields(24, 3, 13)
    shading = rng.uniform(0.3, 1.0, (6, 1, 1, 1)).astype(np.float32)
    samples = (0.5 + 0.1 * base[None] * shading)[None].astype(np.float32)  # [1, 6, 24, 24, 3]
    lights = np.array([[0, 0, 1], [0.5, 0, 0.87], [0, 0.5, 0.87], [-0.5, 0, 0.87], [0, -0.5, 0.87], [0.3, 0.3, 0.9]])
    stack = SampleStack(samples, lights, [[0, 0, 1]])
    coords = quilt(exemplar=stack, size=[40, 32], search="rejection", seed=2, **SMALL)["coords"]
    brute = quilt(exemplar=stack, size=[40, 32], search="brute", seed=2, **SMALL)["coords"]
    np.testing.assert_array_equal(coords.coords, brute.coords)
    plain = quilt(exemplar=stack, size=[40, 32], search="rejection", seed=2, feather=0, **SMALL)["coords"]
    np.testing.assert_array_equal(plain.coords, coords.coords)   # feathering only adds a blend layer (a stack blends)
    assert not plain.blend_weight.size and coords.blend_weight.size
    out = materialize(coords=plain, source=stack)["output"]
    rows, cols = coords.coords[..., 0], coords.coords[..., 1]
    np.testing.assert_array_equal(out.samples, stack.samples[:, :, rows, cols])
    assert texel_features(stack).shape == (24, 24, 16)   # 6 lights x 3 channels seen, their 16 principal components


@pytest.mark.parametrize("params,named", [
    (dict(block=30), "block"),
    (dict(block=8, overlap=4), "overlap"),
    (dict(block=8, overlap=2, seam="zigzag"), "seam"),
    (dict(block=8, overlap=2, size=[6, 40]), "size"),
    (dict(block=8, overlap=3, size=[16, 40], wrap=True), "size"),
])
def test_invalid_parameters_name_the_parameter(params, named):
    kwargs = {"size": [48, 48], **params}
    with pytest.raises(BtforgeInputError) as info:
        quilt(exemplar=ptm_exemplar(), **kwargs)
    assert f"'{named}'" in str(info.value)


def test_benchmark_reports_identical_picks():
    figures = benchmark_quilt(exemplar_size=24, output_size=40, block=8, overlap=2, repeat=1)
    assert figures["identical_picks"] is True
    assert figures["features"] == 16 and figures["candidates"] == 17 * 17
    assert figures["brute_s"] > 0 and figures["rejection_s"] > 0 and figures["speedup"] > 0
    assert figures["rejected_after_projection"]


def test_the_refinement_skips_a_coarse_scale_that_keeps_too_little_of_a_grainy_exemplar(monkeypatch):
    """White noise keeps about a quarter of its variance at half resolution, under the default ``coarse_keep``:
    no round runs at the coarse scale there unless ``coarse_keep`` is 0; a smooth exemplar's coarse rounds run."""
    from scipy.ndimage import gaussian_filter

    from btforge.plugins.synth import refine
    sizes = []
    real_step = refine.optimise_step
    monkeypatch.setattr(refine, "optimise_step",
                        lambda index, *a, **k: sizes.append(index.texels.shape[0]) or real_step(index, *a, **k))
    rng = np.random.default_rng(4)
    lights = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]])
    noise = rng.uniform(0.2, 0.8, (1, 4, 64, 64, 3))
    smooth = 0.5 + 4.0 * (gaussian_filter(noise, (0, 0, 4, 4, 0), mode="wrap") - 0.5)
    few = {"size": [64, 64], "seed": 0, "refine": 1, "polish": 0}
    for samples, keep, coarse in ((noise, None, False), (noise, 0.0, True), (smooth, None, True)):
        sizes.clear()
        stack = SampleStack(np.clip(samples, 0.01, 1.0).astype(np.float32), lights, np.array([[0.0, 0.0, 1.0]]))
        quilt(exemplar=stack, **few, **({} if keep is None else {"coarse_keep": keep}))
        assert (32 in sizes) == coarse and 64 in sizes
