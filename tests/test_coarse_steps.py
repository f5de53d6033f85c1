"""Straight-step visibility: brightness steps along straight edges between pieces, checked on constructed maps
whose answer is known (a periodic copy, shuffled blocks, two halves swapped along a jagged line) and on hard
inputs (constant images, maps too narrow for a line)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btforge.buffers import CoordMap
from btforge.plugins.synth import materialize
from btforge.plugins.synth.coarse_steps import coarse_offsets, straight_step_visibility
from btforge.plugins.synth.scoring import score
from btforge.plugins.synth.visibility import shuffled_blocks

SIZE, OUT = 64, 192


@pytest.fixture(scope="module")
def tileable(tileable_stack):
    return tileable_stack(SIZE, 14)


def measured(exemplar, coords) -> float | None:
    output = materialize(coords=coords, source=exemplar)["output"]
    return score(output=output, exemplar=exemplar, coords=coords)["scores"].values["straight_step_visibility"]


def periodic_copy(size: int, out: int) -> CoordMap:
    rows, cols = np.mgrid[0:out, 0:out]
    return CoordMap(np.stack([rows % size, cols % size], axis=-1).astype(np.int32), (size, size))


def test_periodic_copy_of_a_tileable_exemplar_shows_no_steps(tileable):
    assert 0.7 <= measured(tileable, periodic_copy(SIZE, OUT)) <= 1.3


def gradient_with_grain(size: int, seed: int = 0) -> np.ndarray:
    """``[2, size, size, 3]`` images: a smooth brightness ramp down the rows with a faint 1-texel grain."""
    rng = np.random.default_rng(seed)
    ramp = np.linspace(0.2, 0.8, size)[:, None, None]
    grain = 0.01 * rng.standard_normal((size, size, 1))
    image = np.broadcast_to(ramp + grain, (size, size, 3))
    return np.stack([image, 0.7 * image]).astype(np.float32)


def swapped_halves(size: int, jagged: bool, seed: int = 0) -> CoordMap:
    """A map whose upper half copies the exemplar's lower half and whose lower half its upper half, so the ramp
    steps down along the middle row; with ``jagged``, the line wanders by up to 2 texels and small pieces from
    elsewhere are scattered along it (the edge is broken into many small seams, none straight)."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:size, 0:size]
    middle = np.full(size, size // 2)
    if jagged:
        middle = middle + rng.integers(-2, 3, size)
    upper = rows < middle[None, :]
    src_rows = np.where(upper, rows + size // 2, rows - size // 2) % size
    coords = np.stack([src_rows, cols], axis=-1).astype(np.int32)
    if jagged:
        for _ in range(size // 2):   # 2 x 2 pieces from anywhere, on the line
            r, c = size // 2 + rng.integers(-3, 2), rng.integers(0, size - 2)
            coords[r:r + 2, c:c + 2] = rng.integers(0, size - 2, 2) + np.stack(np.mgrid[0:2, 0:2], -1)
    return CoordMap(coords, (size, size))


def replayed(images: np.ndarray, coords: CoordMap) -> np.ndarray:
    return images[:, coords.coords[..., 0], coords.coords[..., 1]]


def test_shuffled_blocks_show_steps():
    images = gradient_with_grain(96)
    for seed in range(2):
        coords = shuffled_blocks((96, 96), (192, 192), block=32, seed=seed)
        assert straight_step_visibility(replayed(images, coords), images, coords) > 1.3


@pytest.mark.parametrize("jagged", [False, True])
def test_halves_swapped_across_a_gradient_show_a_step(jagged):
    images = gradient_with_grain(96)
    coords = swapped_halves(96, jagged)
    found = straight_step_visibility(replayed(images, coords), images, coords)
    assert found is not None and found > 2.0


def test_copied_content_edges_are_not_steps():
    """A sharp edge the exemplar has, copied whole beside a seam, is the exemplar's own step: about 1."""
    images = gradient_with_grain(96)
    images[:, :, 40:] += 0.3                       # a straight content edge down column 40
    rows, cols = np.mgrid[0:96, 0:96]
    coords = np.stack([(rows + 48) % 96, cols], axis=-1).astype(np.int32)   # one seam, across the rows at 48
    coords = CoordMap(coords, (96, 96))
    ramp = gradient_with_grain(96)
    found = straight_step_visibility(replayed(images, coords), images, coords)
    across_ramp = straight_step_visibility(replayed(ramp, coords), ramp, coords)
    assert found == pytest.approx(across_ramp, rel=0.1)


def test_small_pieces_are_absorbed_into_their_neighbours():
    coords = np.stack(np.mgrid[0:64, 0:64], axis=-1).astype(np.int32)
    coords[10:13, 10:13] += 20                     # a 3 x 3 piece from elsewhere inside one large piece
    coarse = coarse_offsets(coords)
    assert (coarse == 0).all()
    assert coarse_offsets(np.random.default_rng(0).integers(0, 64, (64, 64, 2))) is None   # no large piece


@settings(max_examples=25, deadline=None)
@given(height=st.integers(1, 48), width=st.integers(1, 48), value=st.sampled_from([0.0, 1e-6, 0.5, 1e4]),
       seed=st.integers(0, 2 ** 16))
def test_results_are_finite_and_bounded_on_hard_inputs(height, width, value, seed):
    """Constant and extreme images, maps down to one texel wide, random maps: None or a finite number >= 0."""
    rng = np.random.default_rng(seed)
    exemplar = np.full((2, 40, 40, 3), value, np.float32)
    exemplar[:, rng.integers(0, 40), :] = rng.uniform(0, 2 * value + 1e-3)
    coords = rng.integers(0, 40, (height, width, 2)).astype(np.int32)
    if seed % 2:  # a map of whole pieces
        coords = (np.stack(np.mgrid[0:height, 0:width], axis=-1) + rng.integers(0, 8, 2)) % 40
    coords = CoordMap(coords.astype(np.int32), (40, 40))
    found = straight_step_visibility(replayed(exemplar, coords), exemplar, coords)
    assert found is None or (np.isfinite(found) and found >= 0.0)
    assert straight_step_visibility(exemplar * 0, exemplar * 0, CoordMap(np.zeros((48, 48, 2), np.int32),
                                                                         (40, 40))) is None
