"""Ridge least squares with its weight chosen by closed-form leave-one-out (btforge.fitspace), as ptm.fit and
hsh.fit use it, and ``space: auto`` of the light-table fits (hsh, rbf, bilinear)."""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import btforge
from btforge.buffers import SampleStack, linear_to_srgb8
from btforge.errors import BtforgeInputError, BtforgeWarning
from btforge.fitspace import RIDGE_WEIGHTS, leave_one_out_errors, ridge_by_leave_one_out, ridge_solve
from btforge.plugins.ptm.model import fit_ptm, ptm_terms
from btforge.plugins.web.hsh import hsh_basis

sys.path.insert(0, str(Path(__file__).parent))
from lightsets import dome, lights_at  # noqa: E402

CONSTANT_TERM = 5  # of the PTM terms (lu^2, lv^2, lu*lv, lu, lv, 1)
FAST = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def brute_force_loo(design, samples, ridge, rcond=0.0, free=()):
    """Leave each light out, refit, predict it: the definition the closed form must equal."""
    errors = []
    for i in range(len(design)):
        keep = np.arange(len(design)) != i
        # the weight is relative to the full design's largest singular value, as in the closed form
        s_full = np.linalg.svd(design, compute_uv=False)[0]
        s_part = np.linalg.svd(design[keep], compute_uv=False)[0]
        solve = ridge_solve(design[keep], ridge * (s_full / s_part) ** 2, rcond, free)
        errors.append((design[i] @ (solve @ samples[keep]) - samples[i]) ** 2)
    return float(np.mean(errors))


@pytest.mark.parametrize("free", [(), (CONSTANT_TERM,)])
def test_closed_form_leave_one_out_equals_refitting_without_each_light(free):
    rng = np.random.default_rng(1)
    design = ptm_terms(dome(23, seed=2))
    samples = rng.uniform(0, 1, (23, 40))
    closed = leave_one_out_errors(design, samples, (0.0, 1e-3, 1e-2), free=free)
    for ridge, error in zip((0.0, 1e-3, 1e-2), closed):
        assert error == pytest.approx(brute_force_loo(design, samples, ridge, free=free), rel=1e-9)


def test_noise_asks_for_a_ridge_and_a_clean_polynomial_does_not():
    rng = np.random.default_rng(4)
    design = ptm_terms(dome(30, seed=4))
    clean = design @ rng.uniform(-0.3, 0.3, (6, 500)) + 0.5
    assert ridge_by_leave_one_out(design, clean, free=(CONSTANT_TERM,))[0] == 0.0
    noisy = rng.uniform(0, 1, (30, 500))   # nothing to predict: the more shrinkage the better
    assert ridge_by_leave_one_out(design, noisy, free=(CONSTANT_TERM,))[0] == RIDGE_WEIGHTS[-1]


def light_set(kind: str, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "clustered":
        return lights_at(rng.uniform(60, 62, n), rng.uniform(0, 3, n))
    if kind == "grazing":
        return lights_at(rng.uniform(1, 4, n), rng.uniform(0, 360, n))
    if kind == "one-elevation":
        return lights_at(np.full(n, 30.0), rng.uniform(0, 360, n))
    return dome(n, seed)


@FAST
@given(kind=st.sampled_from(["dome", "clustered", "grazing", "one-elevation"]), n=st.integers(6, 30),
       texel=st.sampled_from(["black", "saturated", "constant", "noise"]), seed=st.integers(0, 2 ** 16),
       basis=st.sampled_from(["ptm", "hsh"]))
def test_ridge_choice_is_finite_bounded_and_exact_on_constant_texels(kind, n, texel, seed, basis):
    rng = np.random.default_rng(seed)
    lights = light_set(kind, n, seed)
    design = ptm_terms(lights) if basis == "ptm" else hsh_basis(lights, 9)
    free = (CONSTANT_TERM,) if basis == "ptm" else (0,)
    samples = {"black": np.zeros((n, 8)), "saturated": np.ones((n, 8)), "constant": np.full((n, 8), 0.37),
               "noise": rng.uniform(0, 1, (n, 8))}[texel]
    errors = leave_one_out_errors(design, samples, RIDGE_WEIGHTS, free=free)
    assert not np.isnan(errors).any() and (errors >= 0).all()
    assert np.isfinite(errors[1:]).all()           # a positive weight always leaves every light a test
    ridge, _ = ridge_by_leave_one_out(design, samples, free=free)
    assert ridge in RIDGE_WEIGHTS
    coeffs = ridge_solve(design, ridge, 0.0, free) @ samples
    assert np.isfinite(coeffs).all()
    if texel != "noise" and n >= design.shape[1]:  # the free constant term fits a constant texel exactly
        np.testing.assert_allclose(design @ coeffs, samples, atol=1e-6)
    # the ridge keeps the fit at the lights near the samples (which lie in [0, 1])
    assert np.abs(design @ coeffs).max() < 10.0


def test_ptm_fit_ridge_param_is_checked_and_used():
    rng = np.random.default_rng(2)
    lights = dome(20, seed=3)
    stack = SampleStack(rng.uniform(0, 1, (1, 20, 5, 6, 3)).astype(np.float32), lights, [[0, 0, 1]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BtforgeWarning)
        _, plain = fit_ptm(stack, "rgb", "linear", ridge=0.0)
        _, chosen = fit_ptm(stack, "rgb", "linear")
    assert plain.ridge == 0.0 and chosen.ridge == RIDGE_WEIGHTS[-1]   # uniform noise: the strongest weight
    for bad in (-1.0, 2.0, "high", True):
        with pytest.raises(BtforgeInputError, match="ridge"):
            fit_ptm(stack, "rgb", "linear", ridge=bad)


def relief_capture(display_linear: bool, n: int = 40, size=(24, 24), seed=0) -> SampleStack:
    """An 8-bit capture of a matte relief: radiance linear in n . l (then sRGB-encoded, as a renderer writes it),
    or display values linear in n . l (as a camera's tone curve makes them)."""
    rng = np.random.default_rng(seed)
    lights = dome(n, seed, min_el=20)
    slope = rng.normal(0, 0.35, size + (2,))
    normals = np.concatenate([slope, np.ones(size + (1,))], axis=-1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    albedo = rng.uniform(0.3, 0.9, size + (3,))
    shading = np.clip(np.einsum("hwk,lk->lhw", normals, lights), 0, None)[..., None] * albedo   # [L, h, w, 3]
    if display_linear:
        from btforge.buffers import srgb_to_linear
        shading = srgb_to_linear(np.clip(shading, 0, 1))
    return SampleStack(linear_to_srgb8(shading.astype(np.float32))[None], lights, [[0, 0, 1]], encoding="srgb8")


@pytest.mark.parametrize("stage,params", [("hsh.fit", {}), ("bilinear.fit", {"resolution": 4, "space": "auto"}),
                                          ("rbf.fit", {"sigma": 0.3})])
def test_space_auto_picks_linear_for_a_rendered_relief_and_display_for_a_tone_mapped_one(stage, params):
    for display_linear, expected in ((False, "linear"), (True, "srgb")):
        model = btforge.stage(stage)(stack=relief_capture(display_linear), **params)["model"]
        assert model.space == expected, (stage, display_linear)
        assert np.isfinite(model.evaluate(dome(7, seed=9))).all()


def test_hsh_leaves_out_lights_below_its_clamp_elevation_while_enough_remain():
    from btforge.plugins.bases.fit import fitting_light_weights, hsh_args
    lights = np.vstack([lights_at([3.0, 5.0], [10.0, 200.0]), dome(20, seed=1, min_el=20)])
    weights = fitting_light_weights(hsh_args(27, "rgb"), lights)
    assert not weights[:2].any() and np.abs(weights[2:]).sum(axis=(1, 2)).min() > 0
    few = fitting_light_weights(hsh_args(27, "rgb"), lights[:12])   # 10 above the clamp: fewer than 2 per term
    assert np.abs(few).sum(axis=(1, 2)).min() > 0
    # the grazing samples do not move the fit: a texel whose grazing samples are wild fits as one without them
    rng = np.random.default_rng(0)
    samples = rng.integers(60, 200, (1, 22, 4, 5, 3)).astype(np.uint8)
    wild = samples.copy()
    wild[0, :2] = 255
    fit = [btforge.stage("hsh.fit")(stack=SampleStack(s, lights, [[0, 0, 1]], encoding="srgb8"), space="srgb",
                                    ridge=0.001)["model"] for s in (samples, wild)]
    np.testing.assert_allclose(fit[0].coeffs, fit[1].coeffs, atol=1e-5)


@FAST
@given(n=st.integers(6, 30), kind=st.sampled_from(["dome", "clustered", "grazing", "one-elevation"]),
       level=st.sampled_from([0.0, 0.37, 1.0]), seed=st.integers(0, 2 ** 16), variant=st.sampled_from(["rgb", "lrgb"]))
def test_ptm_ridge_keeps_flat_texels_close_and_the_kernel_equal_to_its_twin(n, kind, level, seed, variant):
    lights = light_set(kind, n, seed)
    stack = SampleStack(np.full((1, n, 3, 4, 3), level, np.float32), lights, [[0, 0, 1]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BtforgeWarning)
        model, solver = fit_ptm(stack, variant, "linear")
        ref, _ = fit_ptm(stack, variant, "linear", engine="numpy")
    assert np.isfinite(model.coeffs).all() and solver.ridge in RIDGE_WEIGHTS
    np.testing.assert_allclose(model.coeffs, ref.coeffs, rtol=1e-4, atol=1e-5)
    relit = model.evaluate(lights)[0]
    # the ridge shrinks the coefficients towards zero: a flat texel stays within a few percent of its level
    # (the constant term carries a flat response, so the samples leave the ridge little to shrink)
    np.testing.assert_allclose(relit, level, atol=0.03 * level + 1e-5)


@pytest.mark.parametrize("space", ["srgb", "linear"])
def test_light_table_evaluation_kernel_matches_its_twin_in_both_spaces(space):
    from btforge.plugins.bases.model import evaluate_numpy, evaluate_opencl
    rng = np.random.default_rng(7)
    coeffs = np.concatenate([rng.normal(0, 1, (50, 9)), np.full((3, 9), 1e3), np.zeros((3, 9))]).astype(np.float32)
    lw = rng.normal(0, 0.5, (11, 10, 3)).astype(np.float32)
    want, got = evaluate_numpy(coeffs, lw, space), evaluate_opencl(coeffs, lw, space)
    assert np.isfinite(got).all() and got.min() >= 0 and got.max() <= 1   # clipped to [0, 1] in both spaces
    # the kernel interpolates a 4096-step table of the decode; float32 sums of values of order 10
    np.testing.assert_allclose(got, want, atol=2e-5)
