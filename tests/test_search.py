"""The shared neighbourhood search: the exact kernel against its twin and a float64 brute force, the fast
engine's recall against a stated floor, windows, similar-texel lists and bad input."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btforge.plugins.synth import bench as synth_bench
from btforge import BtforgeInputError
from btforge.plugins.synth import search
from btforge.plugins.synth.features import texel_features
from btforge.plugins.synth.quilt_search import shape_texels
from btforge.plugins.synth.textons import normalise_features


def brute_force(exemplar, queries, k):
    """Float64 reference: every distance, sorted by (distance, index)."""
    d = ((queries[:, None, :].astype(np.float64) - exemplar[None].astype(np.float64)) ** 2).sum(-1)
    order = np.lexsort((np.broadcast_to(np.arange(len(exemplar)), d.shape), d), axis=1)[:, :k]
    return order, np.take_along_axis(d, order, axis=1)


def hard_case(case, rng):
    if case == "random":
        return rng.random((700, 7)), rng.random((130, 7)), 5
    if case == "ties":        # small integers: many exactly equal distances, resolved by index
        return rng.integers(0, 3, (400, 4)), rng.integers(0, 3, (90, 4)), 9
    if case == "constant":    # every distance 0: lists are the first k rows
        return np.full((300, 5), 0.25), np.full((20, 5), 0.25), 6
    if case == "one-dim":     # one-texel-wide, one-channel features
        return rng.random((500, 1)), rng.random((64, 1)), 4
    if case == "short":       # fewer exemplar rows than k: -1 / inf at the end
        return rng.random((3, 6)), rng.random((10, 6)), 8
    if case == "huge":        # sums overflow to inf: such rows never enter a list
        e = rng.normal(size=(200, 3)) * 1e25
        e[:50] *= 1e-25
        return e, rng.normal(size=(30, 3)), 60
    if case == "tiles":       # more rows than one tile, more queries than one chunk of the twin
        return rng.random((9000, 40)), rng.random((600, 40)), 3
    raise ValueError(case)


@pytest.mark.parametrize("case", ["random", "ties", "constant", "one-dim", "short", "huge", "tiles"])
def test_exact_kernel_matches_numpy_twin(case):
    e, q, k = (np.asarray(a, np.float32) if isinstance(a, np.ndarray) else a for a in hard_case(case, np.random.default_rng(3)))
    idx_cl, d_cl = search.knn_exact_opencl(e, q, k)
    idx_np, d_np = search.knn_exact_numpy(e, q, k)
    np.testing.assert_array_equal(idx_cl, idx_np)
    np.testing.assert_array_equal(d_cl, d_np)
    assert idx_cl.dtype == np.int64 and d_cl.dtype == np.float32 and idx_cl.shape == (len(q), k)
    if case == "constant":
        assert (idx_cl == np.arange(k)).all() and (d_cl == 0).all()
    if case == "short":
        assert (idx_cl[:, 3:] == -1).all() and np.isinf(d_cl[:, 3:]).all()
    if case == "huge":
        assert (idx_cl[:, :50] < 50).all() and (idx_cl[:, 50:] == -1).all()


@pytest.mark.parametrize("case", ["random", "ties", "constant", "one-dim", "tiles"])
def test_exact_engine_equals_brute_force(case):
    e, q, k = (np.asarray(a, np.float32) if isinstance(a, np.ndarray) else a for a in hard_case(case, np.random.default_rng(4)))
    q = q[:150]
    idx, dist = search.knn(e, q, k, engine="exact")
    ref_idx, ref_d = brute_force(e, q, k)
    np.testing.assert_allclose(dist, ref_d, rtol=1e-5, atol=1e-6)
    if case in ("ties", "constant"):  # integer-valued: float32 sums are exact, so the lists are too
        np.testing.assert_array_equal(idx, ref_idx)
    else:
        assert (idx == ref_idx).mean() > 0.999


@settings(max_examples=12, deadline=None)
@given(n=st.integers(1, 90), m=st.integers(1, 40), d=st.integers(1, 12), k=st.integers(1, 12),
       levels=st.integers(1, 4), seed=st.integers(0, 2 ** 16))
def test_exact_engine_on_drawn_inputs(n, m, d, k, levels, seed):
    # few distinct values: ties everywhere
    rng = np.random.default_rng(seed)
    e = rng.integers(0, levels, (n, d)).astype(np.float32)
    q = rng.integers(0, levels, (m, d)).astype(np.float32)
    idx, dist = search.knn(e, q, k, engine="exact")
    ref_idx, ref_d = brute_force(e, q, min(k, n))
    np.testing.assert_array_equal(idx[:, :min(k, n)], ref_idx)
    np.testing.assert_array_equal(dist[:, :min(k, n)], ref_d.astype(np.float32))
    assert (idx[:, n:] == -1).all()


def test_candidate_distance_kernel_matches_numpy_twin():
    rng = np.random.default_rng(5)
    e, q = rng.random((500, 33), dtype=np.float32), rng.random((70, 33), dtype=np.float32)
    rows = rng.integers(-1, 500, (70, 13))
    a = search.candidate_distances_opencl(e, q, rows)
    b = search.candidate_distances_numpy(e, q, rows)
    np.testing.assert_array_equal(a, b)
    assert np.isinf(a[rows < 0]).all()
    # the same sums as the exact search forms
    idx, dist = search.knn_exact_numpy(e, q, 4)
    np.testing.assert_array_equal(search.candidate_distances_numpy(e, q, idx), dist)


@pytest.fixture(scope="module")
def texture_vectors():
    """5 x 5 neighbourhoods of a 48 x 48 procedural material's 9-D appearance vectors (more rows than the
    fast engine searches exactly)."""
    features = normalise_features(texel_features(synth_bench.benchmark_exemplar(48, lights=12), max_dims=9))
    return search.neighbourhood_vectors(features, search.square_window(5))


def test_fast_engine_recall_meets_the_floor(texture_vectors):
    v = texture_vectors
    assert len(v) > search.FAST_BELOW
    queries = v[::3]
    fast_idx, fast_d = search.knn(v, queries, 6)
    true_idx, true_d = search.knn(v, queries, 6, engine="exact")
    assert search.recall(fast_idx, true_idx) >= search.FAST_RECALL_FLOOR
    assert search.distance_ratio(fast_d, true_d) <= 1.05
    # distances are the full ones, sorted; never nearer than the truth
    np.testing.assert_array_equal(fast_d, search.candidate_distances_numpy(v, queries, fast_idx))
    assert (np.diff(fast_d, axis=1) >= 0).all()
    assert (fast_d[:, -1] >= true_d[:, -1]).all()
    again = search.knn(v, queries, 6)
    np.testing.assert_array_equal(again[0], fast_idx)  # deterministic


def test_fast_engine_falls_back_on_a_flat_exemplar():
    flat = np.ones((3000, 4), np.float32)
    idx, dist = search.knn(flat, flat[:5], 3)
    assert (idx >= 0).all() and (dist == 0).all()


@pytest.mark.shared_data
def test_fast_engine_recall_on_a_real_capture(shared_data):
    from btforge.plugins.synth.bench import exemplar_model
    model = exemplar_model(str(shared_data / "rti/icon_san_michele/dirs.lp"), 64)
    v = search.neighbourhood_vectors(normalise_features(texel_features(model)), search.square_window(5))
    fast_idx, fast_d = search.knn(v, v, 6)
    true_idx, true_d = search.knn(v, v, 6, engine="exact")
    assert search.recall(fast_idx, true_idx) >= search.FAST_RECALL_FLOOR
    assert search.distance_ratio(fast_d, true_d) <= 1.05


# --------------------------------------------------------------------------------------------- windows


def test_windows():
    sq = search.square_window(3)
    assert sq.tolist()[4] == [0, 0] and len(sq) == 9
    causal = search.causal_window(5)
    assert len(causal) == 12 and all(dy < 0 or (dy == 0 and dx < 0) for dy, dx in causal)
    l_shape = search.l_shaped_window(8, 2)
    assert len(l_shape) == 8 * 8 - 6 * 6
    # quilting's overlap shapes are the band window
    rows, cols = shape_texels(10, (2, 0, 3, 1))
    np.testing.assert_array_equal(np.column_stack([rows, cols]), search.band_window(10, 2, 0, 3, 1))
    with pytest.raises(BtforgeInputError):
        search.square_window(4)


@pytest.mark.parametrize("boundary", ["edge", "wrap", "reflect"])
def test_neighbourhood_vectors_follow_the_window(boundary):
    rng = np.random.default_rng(6)
    f = rng.random((7, 9, 2), dtype=np.float32)
    window = search.causal_window(5)
    v = search.neighbourhood_vectors(f, window, boundary=boundary).reshape(7, 9, len(window), 2)
    padded = np.pad(f, ((2, 2), (2, 2), (0, 0)), mode=boundary)
    for y, x in [(0, 0), (3, 4), (6, 8)]:
        for i, (dy, dx) in enumerate(window):
            np.testing.assert_array_equal(v[y, x, i], padded[y + 2 + dy, x + 2 + dx])


# --------------------------------------------------------------------------------------------- similar texels


@pytest.mark.parametrize("exclude,masked", [(0, False), (1, False), (2, True), (-1, False)])
def test_similar_texels_exact_matches_twin_and_rules(exclude, masked):
    rng = np.random.default_rng(7)
    features = rng.integers(0, 3, (13, 11, 2)).astype(np.float32)
    allowed = rng.random((13, 11)) < 0.6 if masked else None
    a = search.similar_texels(features, 3, 4, exclude=exclude, allowed=allowed, search="exact")
    b = search.similar_texels(features, 3, 4, exclude=exclude, allowed=allowed, search="exact", device="numpy")
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    idx, cost = a
    ys, xs = np.divmod(np.arange(13 * 11), 11)
    real = idx >= 0
    ty, tx = np.divmod(np.where(real, idx, 0), 11)
    assert (np.maximum(np.abs(ty - ys[:, None]), np.abs(tx - xs[:, None]))[real] > exclude).all()
    if masked:
        assert allowed.ravel()[idx[real]].all()
    # against the brute force over every allowed, far-enough texel
    v = search.neighbourhood_vectors(features, search.square_window(3)).astype(np.float64)
    full = ((v[:, None] - v[None]) ** 2).sum(-1)
    far = np.maximum(np.abs(ys[:, None] - ys[None]), np.abs(xs[:, None] - xs[None])) > exclude
    ok = far & (True if allowed is None else allowed.ravel()[None, :])
    expected = np.sort(np.where(ok, full, np.inf), axis=1)[:, :4]
    np.testing.assert_array_equal(cost, expected.astype(np.float32))


def test_bad_input_is_reported_at_once():
    with pytest.raises(BtforgeInputError) as info:
        search.knn(np.zeros((4, 3), np.float32), np.zeros((2, 2), np.float32), 0, engine="fastest")
    text = str(info.value)
    assert "engine" in text and "[4, 3]" in text and "k:" in text
    with pytest.raises(BtforgeInputError, match="finite"):
        search.knn(np.full((4, 3), np.nan, np.float32), np.zeros((2, 3), np.float32), 1)


# --------------------------------------------------------------------------------------------- self-join


def _selfjoin_features(case, rng, h, w):
    if case == "random":      # 5 features, radius 1: 15 floats a window row (one chunk of 8, then 7 singly)
        return rng.random((h, w, 5), dtype=np.float32), 1
    if case == "nine":        # 9 features, radius 2: 45 floats a row (five chunks, then 5), as a PTM's
        return rng.random((h, w, 9), dtype=np.float32), 2
    if case == "ties":        # two values per feature: equal distances everywhere, resolved by index
        return rng.integers(0, 2, (h, w, 3)).astype(np.float32), 1
    if case == "constant":    # every distance 0
        return np.full((h, w, 4), 0.5, np.float32), 1
    if case == "one-channel":  # rows shorter than a chunk
        return rng.random((h, w, 1), dtype=np.float32), 2
    if case == "huge":        # sums overflow to inf: such candidates never enter a list
        return (rng.normal(size=(h, w, 2)) * 1e22).astype(np.float32), 1
    raise ValueError(case)


@pytest.mark.parametrize("case,h,w", [("random", 17, 23), ("nine", 13, 11), ("ties", 17, 23), ("constant", 9, 14),
                                      ("one-channel", 19, 7), ("huge", 11, 12), ("random", 40, 1)])
def test_selfjoin_kernel_matches_numpy_twin(case, h, w):
    from btforge.plugins.synth import selfjoin
    rng = np.random.default_rng(11)
    f, radius = _selfjoin_features(case, rng, h, w)
    image = selfjoin.padded_image(f, radius)
    allowed = rng.random(h * w) < 0.8
    start = (np.full((h * w, 6), -1, np.int32), np.full((h * w, 6), np.inf, np.float32), np.ones(h * w, bool))
    lists = {"n": start, "c": start}
    seeds = rng.integers(-1, h * w, (h * w, 5)).astype(np.int32)
    for step, seeded, n_random, settle in [(0, True, 9, False), (1, False, 3, False), (2, False, 0, True),
                                           (3, False, 0, True)]:
        s = seeds if seeded else np.zeros((h * w, 0), np.int32)
        args = (image, h, w, radius, 1, allowed)
        lists["n"] = selfjoin.improve_numpy(*args, *lists["n"], s, 7, step, n_random, settle, 4, 3)
        lists["c"] = selfjoin.improve_opencl(*args, *lists["c"], s, 7, step, n_random, settle, 4, 3)
        for got, want in zip(lists["c"], lists["n"]):
            np.testing.assert_array_equal(got, want)
    idx, dist, _ = lists["c"]
    ys, xs = np.divmod(np.arange(h * w), w)
    ty, tx = np.divmod(np.maximum(idx, 0), w)
    found = idx >= 0
    assert allowed[idx[found]].all()
    assert (np.maximum(np.abs(ty - ys[:, None]), np.abs(tx - xs[:, None]))[found] > 1).all()
    assert all(len(set(r[r >= 0])) == (r >= 0).sum() for r in idx)          # no texel twice
    key = np.where(idx < 0, 2 ** 40, idx).astype(np.float64)
    with np.errstate(invalid="ignore"):                                       # inf - inf at the lists' ends
        step_d = np.diff(dist, axis=1)
    assert ((step_d > 0) | ((step_d == 0) & (np.diff(key, axis=1) > 0)) | np.isinf(dist[:, 1:])).all()
    if case != "huge":
        assert found[:, 0].all() or w == 1


def test_selfjoin_window_distances_are_the_windows_distances():
    from btforge.plugins.synth import selfjoin
    rng = np.random.default_rng(3)
    f = rng.random((12, 10, 9), dtype=np.float32)
    v = search.neighbourhood_vectors(f, search.square_window(5)).astype(np.float64)
    rows = np.arange(120)
    cand = rng.integers(-1, 120, (120, 7))
    got = selfjoin.window_distances_numpy(selfjoin.padded_image(f, 2), 10, 2, rows, cand)
    want = ((v[:, None] - v[np.maximum(cand, 0)]) ** 2).sum(-1)
    np.testing.assert_allclose(got[cand >= 0], want[cand >= 0], rtol=2e-6)
    assert np.isinf(got[cand < 0]).all()


def test_settled_steps_skip_only_texels_whose_candidates_repeat():
    # a step that skips settled texels gives the lists a full step gives
    from btforge.plugins.synth import selfjoin
    rng = np.random.default_rng(5)
    h, w = 21, 19
    f = rng.random((h, w, 3), dtype=np.float32)
    image = selfjoin.padded_image(f, 1)
    allowed = np.ones(h * w, bool)
    lists = (np.full((h * w, 6), -1, np.int32), np.full((h * w, 6), np.inf, np.float32), np.ones(h * w, bool))
    none = np.zeros((h * w, 0), np.int32)
    lists = selfjoin.improve_opencl(image, h, w, 1, 1, allowed, *lists, none, 7, 0, 12, False, 4, 3)
    for step in range(1, 5):
        full = selfjoin.improve_opencl(image, h, w, 1, 1, allowed, *lists, none, 7, step, 0, False, 4, 3)
        skip = selfjoin.improve_opencl(image, h, w, 1, 1, allowed, *lists, none, 7, step, 0, True, 4, 3)
        for a, b in zip(full, skip):
            np.testing.assert_array_equal(a, b)
        assert (full[1] <= lists[1]).all()                                  # lists only improve
        lists = full


def test_coherent_selfjoin_recall_meets_the_floor():
    # 48 x 48 texels: more than are searched exactly, so similar_texels runs the self-join seeded at random
    features = normalise_features(texel_features(synth_bench.benchmark_exemplar(48, lights=12), max_dims=9))
    fast_idx, fast_d = search.similar_texels(features, 5, 5, exclude=1, search="coherent")
    true_idx, true_d = search.similar_texels(features, 5, 5, exclude=1, search="exact")
    assert search.recall(fast_idx, true_idx) >= search.FAST_RECALL_FLOOR
    assert search.distance_ratio(fast_d, true_d) <= 1.05
    assert (fast_d[:, -1] >= true_d[:, -1] * (1 - 1e-5)).all()
    twin_idx, twin_d = search.similar_texels(features, 5, 5, exclude=1, search="coherent", device="numpy")
    np.testing.assert_array_equal(twin_idx, fast_idx)
    np.testing.assert_array_equal(twin_d, fast_d)


# --------------------------------------------------------------------------------------------- fast self-join


@pytest.fixture(scope="module")
def texture_features():
    return normalise_features(texel_features(synth_bench.benchmark_exemplar(48, lights=12), max_dims=9))


@pytest.mark.parametrize("masked", [False, True])
def test_fast_similar_texels_recall_meets_the_floor(texture_features, masked):
    # 48 x 48 texels: more than are searched exactly, so the kd-tree seeds and the steps repair
    from btforge.plugins.synth import selfjoin
    f = texture_features
    allowed = np.random.default_rng(8).random(f.shape[:2]) < 0.7 if masked else None
    fast_idx, fast_d = search.similar_texels(f, 5, 5, exclude=1, allowed=allowed)
    true_idx, true_d = search.similar_texels(f, 5, 5, exclude=1, allowed=allowed, search="exact")
    assert search.recall(fast_idx, true_idx) >= search.SELF_RECALL_FLOOR
    assert search.distance_ratio(fast_d, true_d) <= 1.01
    assert (fast_d[:, -1] >= true_d[:, -1] * (1 - 1e-5)).all()             # never nearer than the truth
    h, w, _ = f.shape
    image = selfjoin.padded_image(f, 2)
    np.testing.assert_array_equal(fast_d, selfjoin.window_distances_numpy(image, w, 2, np.arange(h * w), fast_idx))
    ys, xs = np.divmod(np.arange(h * w), w)
    ty, tx = np.divmod(fast_idx, w)
    assert (np.maximum(np.abs(ty - ys[:, None]), np.abs(tx - xs[:, None])) > 1).all()
    if masked:
        assert allowed.ravel()[fast_idx].all()
    assert all(len(set(r)) == len(r) for r in fast_idx)
    twin = search.similar_texels(f, 5, 5, exclude=1, allowed=allowed, device="numpy")
    np.testing.assert_array_equal(twin[0], fast_idx)
    np.testing.assert_array_equal(twin[1], fast_d)


def test_fast_similar_texels_on_a_flat_exemplar_fills_every_list():
    flat = np.full((50, 50, 2), 0.3, np.float32)
    idx, dist = search.similar_texels(flat, 3, 4, exclude=1)
    exact = search.similar_texels(flat, 3, 4, exclude=1, search="exact")
    assert (dist == 0).all() and (idx >= 0).all()
    np.testing.assert_array_equal(dist, exact[1])
