"""Straight seams re-cut by minimum cuts: exact on small cases, never costlier, pinned texels held."""
from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btforge.buffers import CoordMap, SampleStack
from btforge.plugins.demo.patterns import make_pattern
from btforge.plugins.demo.procedural import hemisphere_lights, render_lights
from btforge.plugins.synth import recut
from btforge.plugins.synth.features import edge_padded
from btforge.plugins.synth.visibility import seam_edges


def seam_energy(texels: np.ndarray, labels: np.ndarray, wrap: bool) -> float:
    """The total seam cost the re-cut lowers, over every neighbour pair of the map."""
    eh, ew, d = texels.shape
    flat = texels.reshape(-1, d)
    padded = edge_padded(texels)
    h, w = labels.shape
    flat_labels = labels.ravel()
    return float(sum(recut.seam_cost(flat, padded, (eh, ew), flat_labels[s], flat_labels[t], dy, dx).sum()
                     for s, t, dy, dx in recut._edges(h, w, wrap)))


@pytest.fixture(scope="module")
def stones():
    lights = hemisphere_lights(8)
    stack = SampleStack(render_lights(make_pattern("stones", 64, 64, seed=3), lights)[None], lights,
                        np.array([[0.0, 0.0, 1.0]]))
    features = stack.appearance_features()   # linear radiance: the re-cut's mechanics, not the vectors' scale
    return features / features.std()


def two_blocks(size: int, height: int, width: int, left: tuple[int, int], right: tuple[int, int]) -> np.ndarray:
    """Flat sources of a map whose left half copies the exemplar from ``left`` and right half from ``right``."""
    rows, cols = np.mgrid[0:height, 0:width]
    half = width // 2
    y = np.where(cols < half, left[0] + rows, right[0] + rows)
    x = np.where(cols < half, left[1] + cols, right[1] + cols - half)
    return y * size + x


def test_a_straight_seam_between_two_blocks_is_re_cut_at_less_cost(stones):
    src = two_blocks(64, 40, 40, (2, 3), (20, 30))
    out = recut.recut_straight_seams(stones, src, wrap=False)
    assert out.shape == src.shape and out.min() >= 0 and out.max() < 64 * 64
    assert seam_energy(stones, out, False) < 0.9 * seam_energy(stones, src, False)
    rows, cols = np.divmod(out, 64)
    before = seam_edges(CoordMap(np.stack(np.divmod(src, 64), -1).astype(np.int32), (64, 64)))
    after = seam_edges(CoordMap(np.stack([rows, cols], -1).astype(np.int32), (64, 64)))
    assert after.straight_count < 0.5 * before.straight_count


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_later_passes_re_cut_near_the_last_changes_and_never_cost_more(stones, seed):
    """Shuffled 12-texel blocks leave many straight runs.  A pass after the first looks only at the runs near the
    texels the pass before changed, so a third pass may change a map only there, and with straight edges weighed
    as any other more passes never raise the seam energy."""
    src = shuffled_block_sources(seed)
    one, two, three = (recut.recut_straight_seams(stones, src, wrap=False, passes=n, bridges=2, straight_weight=1)
                       for n in (1, 2, 3))
    energy = [seam_energy(stones, m, False) for m in (src, one, two, three)]
    assert energy[3] <= energy[2] <= energy[1] < energy[0]
    assert not (three != two)[~recut._near(two != one, False, recut.BAND)].any()


def shuffled_block_sources(seed: int) -> np.ndarray:
    """Flat sources of 12-texel blocks of a 64 x 64 exemplar laid at random on a 48 x 48 map."""
    from btforge.plugins.synth.visibility import shuffled_blocks
    start = shuffled_blocks((64, 64), (48, 48), block=12, seed=seed)
    return start.coords[..., 0].astype(np.int64) * 64 + start.coords[..., 1]


def test_straight_edges_weighed_up_leave_fewer_straight_seams(stones):
    """A straight seam edge that stays costs more than its appearance difference: the cuts leave the block sides
    where another cut costs a little more per edge, so fewer seam edges stay straight, and the seam energy still
    falls well below the shuffled blocks'."""
    def straight_count(src):
        return sum(int(mask.sum()) for mask in recut.straight_edges(src, 64, False))

    plain, weighed, start_energy, energy = 0, 0, 0.0, 0.0
    for seed in range(3):
        start = shuffled_block_sources(seed)
        plain += straight_count(recut.recut_straight_seams(stones, start, wrap=False, bridges=2, straight_weight=1))
        out = recut.recut_straight_seams(stones, start, wrap=False, bridges=2)
        weighed += straight_count(out)
        start_energy += seam_energy(stones, start, False)
        energy += seam_energy(stones, out, False)
    assert weighed < 0.9 * plain
    assert energy < 0.8 * start_energy


def test_pinned_texels_keep_their_sources_and_bands_stop_at_them(stones):
    src = two_blocks(64, 40, 40, (2, 3), (20, 30))
    pinned = np.zeros(src.shape, bool)
    pinned[:, 16] = True                                  # a pinned column left of the seam (at 19 | 20)
    first, second = recut.continuations(src, (64, 64), False, np.isin(np.arange(40), [19])[None, :]
                                        & np.ones((40, 1), bool), 0, pinned)
    assert (second[:, :17] == -1).all() and (second[:, 17:28] >= 0).all()
    out = recut.recut_straight_seams(stones, src, wrap=False, pinned=pinned)
    assert np.array_equal(out[pinned], src[pinned])


def test_a_run_across_a_pinned_ring_counts_its_whole_length():
    """A Wang tile border pins two rows; a cut of 16 texels across it is split by them into runs of 7 the re-cut
    would not see alone, while the straight-seam measure counts all 16.  Its free parts are re-cut, the pinned
    edges stay out of the runs."""
    src = two_blocks(64, 16, 40, (2, 3), (20, 30))
    pinned = np.zeros(src.shape, bool)
    pinned[7:9] = True
    (vertical, _), (horizontal, _) = recut.straight_runs(src, 64, False, pinned)
    expected = np.zeros(src.shape, bool)
    expected[:, 19] = True
    expected[7:9, 19] = False
    assert np.array_equal(vertical, expected) and not horizontal.any()
    assert not recut.straight_runs(src[:11], 64, False, pinned[:11])[0][0].any()   # 11 texels: not straight


def test_runs_whose_bands_overlap_are_offered_in_separate_groups():
    runs = np.zeros((40, 60), bool)
    runs[0:14, 9] = runs[0:14, 10] = True      # the two seams of a one-texel sliver
    runs[20:34, 10] = True                      # below them: its band overlaps neither
    runs[0:14, 40] = True                       # far to the right
    groups = recut.apart_groups(runs, 0, wrap=False)
    assert np.array_equal(np.logical_or.reduce(groups), runs)
    assert sum(int(g.sum()) for g in groups) == int(runs.sum())          # every run in exactly one group
    together = [g for g in groups if g[0, 9]][0]
    assert not together[0, 10] and together[20, 10] and together[0, 40]
    wrapped = np.zeros((20, 60), bool)
    wrapped[0:14, 1] = wrapped[0:14, 58] = True                          # three columns apart across the wrap
    assert len(recut.apart_groups(wrapped, 0, wrap=True)) == 2
    assert len(recut.apart_groups(wrapped, 0, wrap=False)) == 1


def test_a_sliver_between_two_pieces_is_covered_by_the_piece_that_joins_the_other():
    """Columns 0-9 copy exemplar columns 2-11, column 10 is a sliver from column 30, columns 11-19 copy columns
    20-28, whose first two match exemplar columns 12 and 13: the left piece continued over the sliver meets the
    right piece at no cost, the right piece continued over it meets a far step.  Each of the sliver's two seams has
    its own run; the left piece's continuation is offered only when the two runs' bands are not one proposal (the
    sliver's own continuation overwrote it there)."""
    rng = np.random.default_rng(4)
    values = rng.normal(0.0, 0.1, 40)
    values[19], values[20] = values[12], values[13]     # the right piece joins the left one's continuation
    values[18] = 5.0                                    # ... and its own continuation leftwards is a far step
    texels = np.repeat(values[None, :, None], 16, axis=0)
    cols = np.concatenate([np.arange(2, 12), [30], np.arange(20, 29)])
    src = np.arange(16)[:, None] * 40 + cols[None, :]
    assert seam_energy(texels, src, False) > 1e-3
    out = recut.recut_straight_seams(texels, src, wrap=False, passes=1)
    assert seam_energy(texels, out, False) < 1e-9
    assert (out[:, 10] % 40 == 12).all()


def test_a_constant_exemplar_leaves_the_map_as_it_is():
    texels = np.ones((32, 32, 3), np.float32)
    src = two_blocks(32, 20, 20, (0, 0), (10, 12))
    assert np.array_equal(recut.recut_straight_seams(texels, src, wrap=True), src)


@st.composite
def small_cases(draw):
    d = draw(st.integers(1, 3))
    size = draw(st.integers(3, 5))
    scale = draw(st.sampled_from([1e-6, 1.0, 1e4]))
    values = draw(st.lists(st.floats(-1, 1, allow_nan=False, width=32), min_size=size * size * d,
                           max_size=size * size * d))
    texels = (np.array(values, np.float32) * scale).reshape(size, size, d)
    h, w = draw(st.integers(2, 3)), draw(st.integers(2, 3))
    labels = np.array(draw(st.lists(st.integers(0, size * size - 1), min_size=h * w, max_size=h * w))).reshape(h, w)
    proposal = np.array(draw(st.lists(st.integers(-1, size * size - 1), min_size=h * w,
                                      max_size=h * w))).reshape(h, w)
    pinned = np.array(draw(st.lists(st.booleans(), min_size=h * w, max_size=h * w))).reshape(h, w)
    return texels, labels, proposal, pinned, draw(st.booleans())


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(small_cases())
def test_an_expansion_move_is_never_costlier_and_is_exact_when_submodular(case):
    texels, labels, proposal, pinned, wrap = case
    moved = recut.expansion_move(texels, labels, proposal, wrap, pinned)
    free = (proposal >= 0) & (proposal != labels) & ~pinned
    assert np.array_equal(moved[~free], labels[~free])
    assert np.all((moved == labels) | (moved == proposal))
    before, after = seam_energy(texels, labels, wrap), seam_energy(texels, moved, wrap)
    assert np.isfinite(after) and after <= before * (1 + 1e-6) + 1e-12
    spots = np.argwhere(free)
    best = before
    for choice in itertools.product((False, True), repeat=len(spots)):
        trial = labels.copy()
        for (y, x), take in zip(spots, choice):
            if take:
                trial[y, x] = proposal[y, x]
        best = min(best, seam_energy(texels, trial, wrap))
    if _submodular(texels, labels, proposal, free, wrap):
        # capacities are rounded to 1e-6 of the largest cost: the cut is optimal within that
        scale = max(before, 1e-30)
        assert after <= best + 1e-4 * scale + 1e-12


def weighed_energy(texels, labels, before, straight, weight, wrap) -> float:
    """The seam cost of ``labels``, an edge of ``straight`` (per direction, at its first texel) counting ``weight``
    times where both its texels keep their labels of ``before``."""
    eh, ew, d = texels.shape
    flat, padded = texels.reshape(-1, d), edge_padded(texels)
    now, kept = labels.ravel(), (labels == before).ravel()
    total = 0.0
    for s, t, dy, dx in recut._edges(*labels.shape, wrap):
        cost = recut.seam_cost(flat, padded, (eh, ew), now[s], now[t], dy, dx)
        heavy = straight[0 if dx else 1].ravel()[s] & kept[s] & kept[t]
        total += float(np.where(heavy, weight * cost, cost).sum())
    return total


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(small_cases(), st.sampled_from([1.5, 3.0]), st.data())
def test_a_weighed_expansion_move_lowers_its_own_energy_and_is_exact_when_submodular(case, weight, data):
    texels, labels, proposal, pinned, wrap = case
    shape = labels.shape
    straight = tuple(np.array(data.draw(st.lists(st.booleans(), min_size=labels.size, max_size=labels.size)))
                     .reshape(shape) for _ in range(2))
    moved = recut.expansion_move(texels, labels, proposal, wrap, pinned,
                                 keep_weights=recut.straight_weights(straight, weight))
    free = (proposal >= 0) & (proposal != labels) & ~pinned
    assert np.array_equal(moved[~free], labels[~free]) and np.all((moved == labels) | (moved == proposal))
    before = weighed_energy(texels, labels, labels, straight, weight, wrap)
    after = weighed_energy(texels, moved, labels, straight, weight, wrap)
    assert np.isfinite(after) and after <= before * (1 + 1e-6) + 1e-12
    best = before
    for choice in itertools.product((False, True), repeat=int(free.sum())):
        trial = labels.copy()
        trial[free] = np.where(choice, proposal[free], labels[free])
        best = min(best, weighed_energy(texels, trial, labels, straight, weight, wrap))
    if _submodular(texels, labels, proposal, free, wrap, straight, weight):
        assert after <= best + 1e-4 * max(before, 1e-30) + 1e-12


def _submodular(texels, labels, proposal, free, wrap, straight=None, weight=1.0) -> bool:
    """Whether every pair of free neighbours has submodular costs (then the minimum cut is exact)."""
    eh, ew, d = texels.shape
    flat = texels.reshape(-1, d)
    padded = edge_padded(texels)
    h, w = labels.shape
    now, then, ok = labels.ravel(), np.where(free, proposal, labels).ravel(), free.ravel()
    for s, t, dy, dx in recut._edges(h, w, wrap):
        both = ok[s] & ok[t]
        if not both.any():
            continue
        cost = [recut.seam_cost(flat, padded, (eh, ew), a[s[both]], b[t[both]], dy, dx)
                for a, b in ((now, now), (then, then), (now, then), (then, now))]
        if straight is not None:
            cost[0] = np.where(straight[0 if dx else 1].ravel()[s[both]], weight * cost[0], cost[0])
        if np.any(cost[0] + cost[1] > cost[2] + cost[3] + 1e-6 * np.abs(cost).max()):
            return False
    return True


def two_colour_exemplar(size: int = 64, seed: int = 0) -> np.ndarray:
    """A ``size x size`` exemplar, one flat colour left of the middle column and another right of it, with a
    faint grain (1 % of the colours' difference)."""
    rng = np.random.default_rng(seed)
    texels = np.where(np.arange(size)[None, :, None] < size // 2, [0.2, 0.5, 0.1], [0.6, 0.3, 0.4])
    texels = texels + 0.004 * rng.standard_normal((size, size, 3))
    return np.ascontiguousarray(np.broadcast_to(texels, (size, size, 3)), dtype=np.float32)


def test_a_straight_seam_between_flat_colours_is_bridged_by_the_exemplars_own_transition():
    """Left block inside the first colour, right block inside the second, both more than a band from the
    exemplar's own transition: every cut between their continuations is as costly as the straight one, so only a
    bridging piece (the exemplar around its middle column) removes the seam."""
    texels = two_colour_exemplar()
    src = two_blocks(64, 40, 40, (4, 0), (8, 44))
    plain = recut.recut_straight_seams(texels, src, wrap=False)
    bridged = recut.recut_straight_seams(texels, src, wrap=False, bridges=3)
    straight = [seam_edges(CoordMap(np.stack(np.divmod(m, 64), -1).astype(np.int32), (64, 64))).straight_count
                for m in (src, plain)]
    assert straight[1] >= 0.9 * straight[0] > 0        # the continuations alone cannot move it
    energy = [seam_energy(texels, m, False) for m in (src, plain, bridged)]
    assert energy[1] >= 0.9 * energy[0]
    assert energy[2] < 0.01 * energy[0]                # what seams are left run through one colour's grain
    assert bridged.min() >= 0 and bridged.max() < 64 * 64



def test_a_wider_band_reaches_round_an_area_that_a_narrow_one_cannot():
    """The left block ends 10 texels before the exemplar's own transition, the right block lies inside the second
    colour: in a band of 8 no continuation reaches the transition and the cut stays as costly; in a band of 12 the
    left block's continuation carries the transition into the output, and the cut runs through one colour's grain."""
    texels = two_colour_exemplar()
    src = two_blocks(64, 40, 40, (4, 2), (8, 44))
    energy = [seam_energy(texels, m, False) for m in
              (src, *(recut.recut_straight_seams(texels, src, wrap=False, band=band) for band in (8, 12)))]
    assert energy[1] >= 0.9 * energy[0] > 0
    assert energy[2] < 0.01 * energy[0]

@settings(max_examples=40, deadline=None)
@given(st.integers(4, 20), st.integers(4, 20), st.integers(0, 10_000), st.sampled_from([1e-6, 1.0, 1e4]))
def test_region_distances_equal_the_direct_sums(rh, rw, seed, scale):
    """The FFT correlation gives every placement's masked sum of squared differences; single-precision
    transforms keep the error within 1e-4 of the sums' scale (``scale^2`` x the values summed: float32's 6e-8
    relative rounding grown by the transforms' log2(size) stages and the cancellation of three terms)."""
    from btforge.plugins.synth.bridging import ExemplarSpectrum, diamond
    rng = np.random.default_rng(seed)
    texels = (rng.standard_normal((24, 28, 3)) * scale).astype(np.float32)
    region = (rng.standard_normal((rh, rw, 3)) * scale).astype(np.float32)
    mask = rng.random((rh, rw)) < 0.7 if seed % 2 else diamond(rh // 2, rw // 2, 0)[0][:rh, :rw]
    got = ExemplarSpectrum(texels).distances(region, mask)
    exact, patch = texels.astype(np.float64), region.astype(np.float64)
    want = np.array([[(((exact[y:y + rh, x:x + rw] - patch) ** 2).sum(-1) * mask).sum()
                      for x in range(28 - rw + 1)] for y in range(24 - rh + 1)])
    assert got.shape == want.shape and np.all(np.isfinite(got))
    assert np.abs(got - want).max() <= 1e-4 * scale ** 2 * rh * rw * 3


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 10_000), st.sampled_from([1e-6, 1.0, 1e4]), st.booleans())
def test_bridging_never_raises_the_seam_cost(seed, scale, wrap):
    """Random block maps of a random or constant exemplar, at tiny and large scales: the re-cut with bridging
    pieces stays inside the exemplar and never raises the seam energy."""
    rng = np.random.default_rng(seed)
    texels = (rng.random((40, 40, 3)) * scale if seed % 3 else np.full((40, 40, 3), scale)).astype(np.float32)
    src = two_blocks(40, 32, 32, tuple(rng.integers(0, 8, 2)), tuple(rng.integers(0, 8, 2) + (0, 16)))
    out = recut.recut_straight_seams(texels, src, wrap=wrap, bridges=3)
    assert out.min() >= 0 and out.max() < 40 * 40
    before, after = seam_energy(texels, src, wrap), seam_energy(texels, out, wrap)
    assert np.isfinite(after) and after <= before * (1 + 1e-6) + 1e-12
