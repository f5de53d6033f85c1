"""``space: auto`` of the PTM fit scored in closed form (``ptm_held_out_errors``) against its definition: fit each
fold in each space with ``fit_ptm`` (``ridge: auto``), evaluate the model at the lights held out, and score the
display values (``btforge.fitspace.best_held_out``)."""
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btforge.buffers import SampleStack, linear_to_srgb8
from btforge.fitspace import AUTO_HOLD_EVERY, best_held_out, held_out_grid
from btforge.plugins.ptm.model import fit_ptm, ptm_held_out_errors

from lightsets import dome, lights_at

FAST = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ICON = Path(__file__).resolve().parents[1] / "graphs" / "data" / "icon_san_michele" / "dirs.lp"
# The definition fits and evaluates in float32 (coefficients, the kernel's sums, a 4097-entry table from display
# values to linear and back), the closed form in float64: mean squared errors of display values in [0, 1] then
# differ by float32 rounding of values near 1, about 1e-7 of the error on real captures (measured 5e-7 at most);
# 1e-4 of it, or 1e-9 absolute for fits that are nearly exact, leaves room for every light set drawn below.
RTOL, ATOL = 1e-4, 1e-9


def by_definition(grid: np.ndarray, stack: SampleStack, variant: str, engine: str) -> tuple[str, dict]:
    def predict(fit, space, lights, views):
        return fit_ptm(fit, variant, space, engine=engine)[0].evaluate(lights, engine=engine)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return best_held_out(grid, stack, ("srgb", "linear"), predict)


def assert_same_scores(grid: np.ndarray, stack: SampleStack, variant: str, engine: str = "numpy") -> None:
    best, errors = ptm_held_out_errors(grid, stack, variant)
    expected_best, expected = by_definition(grid, stack, variant, engine)
    for space in ("srgb", "linear"):
        assert np.isfinite(errors[space]) and 0.0 <= errors[space] <= 1.0, errors
        assert errors[space] == pytest.approx(expected[space], rel=RTOL, abs=ATOL), (errors, expected)
    if abs(expected["srgb"] - expected["linear"]) > RTOL * max(expected.values()) + 2 * ATOL:
        assert best == expected_best, (errors, expected)


def byte_stack(samples: np.ndarray, lights: np.ndarray) -> SampleStack:
    return SampleStack(samples[None], lights.astype(np.float32), [[0.0, 0.0, 1.0]], ("R", "G", "B"), "srgb8")


def shaded(lights: np.ndarray, size: int, seed: int, gloss: float) -> np.ndarray:
    """8-bit display values ``[L, size, size, 3]`` of a bumpy surface: Lambert shading plus a highlight."""
    rng = np.random.default_rng(seed)
    normals = rng.normal([0, 0, 1], 0.35, (size, size, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    cosine = np.einsum("hwi,li->lhw", normals, lights)
    half = lights + [0.0, 0.0, 1.0]
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    highlight = gloss * np.maximum(np.einsum("hwi,li->lhw", normals, half), 0) ** 40
    radiance = (0.7 * np.maximum(cosine, 0) + highlight)[..., None] * rng.uniform(0.3, 1.0, (1, size, size, 3))
    return linear_to_srgb8(radiance)


def grazing(n: int, seed: int) -> np.ndarray:
    low = dome(n, seed, min_el=2) * [1.0, 1.0, 0.2]
    return low / np.linalg.norm(low, axis=1, keepdims=True)


LIGHT_SETS = {
    "dome": lambda n, seed: dome(n, seed),
    "grazing": grazing,
    "one elevation": lambda n, seed: lights_at(np.full(n, 35.0), np.linspace(0, 360, n, endpoint=False)),
    "clustered": lambda n, seed: lights_at(np.random.default_rng(seed).uniform(60, 70, n),
                                           np.random.default_rng(seed + 1).uniform(0, 40, n)),
}


@FAST
@given(kind=st.sampled_from(sorted(LIGHT_SETS)), n_light=st.integers(10, 40), size=st.integers(1, 9),
       gloss=st.sampled_from([0.0, 0.5, 4.0]), variant=st.sampled_from(["rgb", "lrgb"]), seed=st.integers(0, 99))
def test_closed_form_scores_equal_fitting_each_fold_on_hard_light_sets(kind, n_light, size, gloss, variant, seed):
    lights = LIGHT_SETS[kind](n_light, seed)
    stack = byte_stack(shaded(lights, size, seed, gloss), lights)   # gloss 4: saturated highlights
    assert_same_scores(stack.samples, stack, variant)


@FAST
@given(n_light=st.integers(10, 30), fill=st.sampled_from(["random", "black", "white", "constant"]),
       variant=st.sampled_from(["rgb", "lrgb"]), seed=st.integers(0, 99))
def test_closed_form_scores_equal_fitting_each_fold_on_hard_samples(n_light, fill, variant, seed):
    rng = np.random.default_rng(seed)
    samples = {"random": rng.integers(0, 256, (n_light, 4, 5, 3)), "black": np.zeros((n_light, 4, 5, 3)),
               "white": np.full((n_light, 4, 5, 3), 255), "constant": np.full((n_light, 4, 5, 3), 37)}[fill]
    lights = dome(n_light, seed)
    stack = byte_stack(samples.astype(np.uint8), lights)
    assert_same_scores(stack.samples, stack, variant)


@pytest.mark.parametrize("variant", ["rgb", "lrgb"])
def test_closed_form_scores_equal_the_kernels_fits_on_a_real_capture(variant):
    from btforge.plugins.stackio.images import load_stack
    stack = load_stack(ICON)
    grid = held_out_grid(stack)
    assert grid.shape[2] * grid.shape[3] > 1000 and stack.n_light > AUTO_HOLD_EVERY
    best, _ = ptm_held_out_errors(grid, stack, variant)
    assert best == "srgb"                       # real captures fit better as display values (test_ptm_fit)
    assert_same_scores(grid, stack, variant, engine="opencl")


def test_a_texel_grid_larger_than_the_ridges_is_scored_like_its_folds():
    """A grid of more than ``AUTO_TEXELS`` texels: each fold's ridge is judged on every other row and column of it,
    as ``fit_ptm`` of the fold judges its ridge on its own grid."""
    lights = dome(20, 4)
    stack = byte_stack(shaded(lights, 70, 4, 0.5), lights)
    assert_same_scores(stack.samples, stack, "rgb")
