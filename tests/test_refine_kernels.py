"""The refinement's OpenCL kernels (refine.cl) against their NumPy twins, on random and hard inputs."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btforge.errors import BtforgeInputError
from btforge.plugins.synth import refine
from btforge.plugins.synth.refine import (_correct_numpy, _correct_opencl, _rank_numpy, _rank_opencl,
                                          _sweeps_numpy, _sweeps_opencl, candidate_costs, exemplar_window_energy,
                                          refine_map, window_energy, window_index)
from btforge.plugins.synth.visibility import seam_masks, shuffled_blocks

D = 6


def random_texels(rng, eh, ew, kind):
    """Exemplar texels: random, constant (every distance ties), or few levels (many exact ties)."""
    if kind == "constant":
        return np.full((eh, ew, D), 0.25, np.float32)
    if kind == "levels":
        return rng.integers(0, 3, (eh, ew, D)).astype(np.float32)
    return rng.standard_normal((eh, ew, D)).astype(np.float32)


# ------------------------------------------------------------------------------------------------ rf_rank

@pytest.mark.parametrize("contrast", [0.0, 16.0])
@pytest.mark.parametrize("kind", ["random", "constant", "levels"])
@pytest.mark.parametrize("patch", [4, 8])
def test_rank_kernel_matches_numpy(kind, patch, contrast):
    rng = np.random.default_rng(patch)
    index = window_index(random_texels(rng, 21, 26, kind), patch)
    gy, gx = index.grid
    n, width = 300, 9
    cand = rng.integers(0, gy * gx, (n, width))
    cand[:20, :] = gy * gx - 1                      # the last window (bottom right border) only
    cand[20:40, 0] = 0                              # the first window (top left border)
    query = rng.standard_normal((n, patch * patch * D)).astype(np.float32)
    if kind != "random":                            # queries copied from windows: exact zeros and ties
        query = window_pixels(index, rng.integers(0, gy * gx, n))
    penalty = np.where(rng.random(gy * gx) < 0.5, 0.0, rng.random(gy * gx) * 10)
    extra = candidate_costs(index, query, cand, penalty, contrast)
    a_origin, a_dist = _rank_opencl(index, query, cand, extra)
    b_origin, b_dist = _rank_numpy(index, query, cand, extra)
    # the same float32 sums in the same order, and the first of equal costs: the same windows and distances
    assert np.array_equal(a_origin, b_origin) and np.array_equal(a_dist, b_dist)
    # and the chosen window is the cheapest up to float32 rounding of 384 squares (relative 384 x 2^-24 < 3e-5)
    costs = np.stack([window_distances(index, query, cand[:, c]) + extra[:, c] for c in range(width)], axis=1)
    chosen = costs[np.arange(n), np.argmax(cand == a_origin[:, None], axis=1)]
    np.testing.assert_allclose(chosen, costs.min(axis=1), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(a_dist, window_distances(index, query, a_origin), rtol=1e-4, atol=1e-4)
    if kind == "constant":                          # every cost ties without a penalty: the first candidate wins
        for rank in (_rank_opencl, _rank_numpy):
            origin, dist = rank(index, query, cand, np.zeros(cand.shape, np.float32))
            assert np.array_equal(origin, cand[:, 0]) and np.all(dist == 0)


@pytest.mark.parametrize("kind", ["random", "constant", "levels"])
def test_window_energy_by_box_sums_matches_each_window_and_is_zero_on_flat_windows(kind):
    """The exemplar's window energies (box sums) against :func:`window_energy` of each window gathered; a constant
    exemplar has none."""
    rng = np.random.default_rng(3)
    index = window_index(random_texels(rng, 17, 19, kind), 4)
    gy, gx = index.grid
    origins = np.arange(gy * gx)
    gathered = window_energy(window_pixels(index, origins), D)
    np.testing.assert_array_equal(index.energy, exemplar_window_energy(index.texels, 4))
    np.testing.assert_allclose(index.energy, gathered, rtol=1e-4, atol=1e-3)
    assert np.all(np.isfinite(index.energy)) and np.all(index.energy >= 0)
    if kind == "constant":
        assert np.all(index.energy == 0)


def test_contrast_charges_only_candidates_flatter_than_the_query():
    """Without contrast the extra cost is the penalty alone; with it, a candidate with less variation than the
    query costs contrast x the shortfall more, and one with as much or more costs nothing more."""
    rng = np.random.default_rng(5)
    index = window_index(random_texels(rng, 20, 20, "random"), 4)
    gy, gx = index.grid
    cand = rng.integers(0, gy * gx, (50, 6))
    query = window_pixels(index, rng.integers(0, gy * gx, 50))
    penalty = rng.random(gy * gx)
    plain = candidate_costs(index, query, cand, penalty, 0.0)
    np.testing.assert_array_equal(plain, penalty[cand].astype(np.float32))
    charged = candidate_costs(index, query, cand, penalty, 4.0)
    shortfall = np.maximum(window_energy(query, D)[:, None] - index.energy[cand], 0)
    np.testing.assert_allclose(charged - plain, 4.0 * shortfall, rtol=1e-5, atol=1e-4)
    assert np.all(charged >= plain) and np.any(charged > plain) and np.any(charged == plain)


def window_pixels(index, origins):
    p = index.patch
    wy, wx = np.divmod(origins, index.grid[1])
    windows = index.texels[wy[:, None, None] + np.arange(p)[:, None], wx[:, None, None] + np.arange(p)[None, :]]
    return np.ascontiguousarray(windows.reshape(len(origins), -1), np.float32)


def window_distances(index, query, origins):
    diff = window_pixels(index, origins).astype(np.float64) - query
    return (diff * diff).sum(axis=1)


# ------------------------------------------------------------------------------------------------ rf_sweep

def random_vote(rng, texels, h, w, slots, covered=0.9):
    """Votes (some -1, with infinite data cost) and data costs as :func:`refine._vote` builds them."""
    eh, ew, _ = texels.shape
    votes = rng.integers(0, eh * ew, (h, w, slots))
    data = rng.random((h, w, slots)).astype(np.float32)
    missing = rng.random((h, w, slots)) > covered
    missing[..., -1] = False                        # the last slot: the current source, always a candidate
    votes[missing] = -1
    data[missing] = np.inf
    # coherent proposals: neighbours' candidates that continue each other (seam cost 0)
    rows, cols = np.mgrid[0:h, 0:w]
    votes[..., 0] = ((rows + 3) % eh) * ew + (cols + 5) % ew
    data[..., 0] = np.where(rng.random((h, w)) < 0.3, np.float32(0.5), data[..., 0])   # exact ties with slot 1
    data[..., 1] = np.where(data[..., 0] == np.float32(0.5), np.float32(0.5), data[..., 1])
    votes[..., 1] = np.where(votes[..., 1] < 0, 0, votes[..., 1])
    labels = votes[..., -1].copy()
    return votes, data, labels


@pytest.mark.parametrize("wrap", [False, True])
@pytest.mark.parametrize("kind", ["random", "constant", "levels"])
@pytest.mark.parametrize("shape", [(16, 16), (7, 9), (1, 5)])
def test_sweep_kernel_matches_numpy(wrap, kind, shape):
    rng = np.random.default_rng(hash((wrap, kind, shape)) % 2**32)
    texels = random_texels(rng, 11, 13, kind)
    h, w = shape
    votes, data, labels = random_vote(rng, texels, h, w, slots=6)
    a = _sweeps_opencl(texels, votes, data, labels, wrap, lambda labels: labels)
    b = _sweeps_numpy(texels, votes, data, labels, wrap, lambda labels: labels)
    # the same float32 sums in the same order, and the first of equal costs: the same labels
    assert np.array_equal(a, b)
    assert np.isin(a, votes).all()


@pytest.mark.parametrize("seam_weight", [0.0, 0.3, 2.5, 4.0, 1e6])
def test_sweep_kernel_matches_numpy_at_any_seam_weight(seam_weight):
    rng = np.random.default_rng(int(seam_weight * 10) % 2**32)
    texels = random_texels(rng, 11, 13, "random")
    votes, data, labels = random_vote(rng, texels, 15, 17, slots=6)
    a = _sweeps_opencl(texels, votes, data, labels, True, lambda labels: labels, seam_weight)
    b = _sweeps_numpy(texels, votes, data, labels, True, lambda labels: labels, seam_weight)
    assert np.array_equal(a, b)
    if seam_weight == 0.0:      # no seam cost: every texel takes its least data cost (the first of equal ones)
        assert np.array_equal(a, np.take_along_axis(votes, data.argmin(axis=2)[..., None], 2)[..., 0])


def test_a_seam_cost_leaves_fewer_seams_than_none():
    rng = np.random.default_rng(5)
    texels = random_texels(rng, 12, 12, "random")
    votes, data, labels = random_vote(rng, texels, 24, 24, slots=6)

    def seams(labels):
        return sum(int(mask.sum()) for mask in seam_masks(*np.divmod(labels, 12), wrap=False))
    none, *weighed = [seams(_sweeps_numpy(texels, votes, data, labels, False, lambda labels: labels, w))
                      for w in (0.0, 1.0, 8.0)]
    # iterated conditional modes stops at a local minimum, so heavier weights need not leave fewer still
    assert all(count < 0.7 * none for count in weighed)


def test_sweep_kernel_keeps_pinned_texels():
    rng = np.random.default_rng(3)
    texels = random_texels(rng, 12, 12, "random")
    votes, data, labels = random_vote(rng, texels, 20, 18, slots=5)
    pinned = rng.random((20, 18)) < 0.3
    start = labels.copy()

    def keep(new):
        return np.where(pinned, start, new)
    a = _sweeps_opencl(texels, votes, data, labels, False, keep)
    b = _sweeps_numpy(texels, votes, data, labels, False, keep)
    assert np.array_equal(a, b)
    assert np.array_equal(a[pinned], start[pinned]) and (a[~pinned] != start[~pinned]).any()


# ------------------------------------------------------------------------------------------------ rf_correct

@pytest.mark.parametrize("kind", ["random", "constant", "levels"])
@pytest.mark.parametrize("shape", [(24, 24), (5, 7), (1, 6)])
def test_correct_kernel_matches_numpy(kind, shape):
    rng = np.random.default_rng(len(kind) + shape[0])
    texels = random_texels(rng, 10, 14, kind)
    src = rng.integers(0, 10 * 14, shape)
    src[0, :] = np.arange(shape[1]) % 14            # sources on the exemplar's border: continuations leave it
    a = _correct_opencl(texels, src)
    b = _correct_numpy(texels, src)
    assert np.array_equal(a, b)
    if kind == "constant":                          # every neighbourhood ties: each texel keeps its own source
        assert np.array_equal(a, src)


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scale=st.sampled_from([1e-20, 1e-3, 1.0, 1e3, 1e15]), seed=st.integers(0, 10_000),
       wrap=st.booleans())
def test_kernels_stay_finite_and_agree_at_any_scale(scale, seed, wrap):
    rng = np.random.default_rng(seed)
    texels = (random_texels(rng, 9, 11, "random") * np.float32(scale)).astype(np.float32)
    src = rng.integers(0, 9 * 11, (8, 10))
    assert np.array_equal(_correct_opencl(texels, src), _correct_numpy(texels, src))
    votes, data, labels = random_vote(rng, texels, 8, 10, slots=4)
    a = _sweeps_opencl(texels, votes, data, labels, wrap, lambda labels: labels)
    assert np.array_equal(a, _sweeps_numpy(texels, votes, data, labels, wrap, lambda labels: labels))
    assert a.min() >= 0 and a.max() < 9 * 11


# ------------------------------------------------------------------------------------------------ the whole refinement

@pytest.mark.parametrize("wrap", [False, True])
def test_refinement_on_opencl_matches_the_twins(monkeypatch, wrap):
    rng = np.random.default_rng(1)
    features = np.cumsum(np.cumsum(rng.standard_normal((40, 40, 9)), axis=0), axis=1).astype(np.float32)
    start = shuffled_blocks((40, 40), (72, 72), 12, seed=2)
    start = type(start)(start.coords, start.source_size, wrap=wrap)
    maps = {}
    for engine in ("opencl", "numpy"):
        monkeypatch.setenv(refine.ENGINE_VARIABLE, engine)
        maps[engine] = refine_map(features, start, iterations=2, occurrence=1.0, seed=3, scales=1).coords
    assert np.array_equal(maps["opencl"], maps["numpy"])


def test_unknown_engine_is_named(monkeypatch):
    monkeypatch.setenv(refine.ENGINE_VARIABLE, "cuda")
    with pytest.raises(BtforgeInputError, match="BTFORGE_REFINE_ENGINE"):
        refine.engine()
