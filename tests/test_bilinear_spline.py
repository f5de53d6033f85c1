"""bilinear.fit's spline resampling: the smoothing spline over the sphere of directions (constants exact, affine
responses nearly so, finite and bounded on hard light sets), its leave-one-out choice (exact), the grid side
choice, the PCA solved in the lights' span (the same table as the explicit one), the plane count choice
(``planes: 0``), and held-out accuracy between rings of a dome against the other resamplings."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btforge.buffers import SampleStack, linear_to_srgb, linear_to_srgb8
from btforge.plugins.bases.fit import (AUTO_PLANES, SPLINE_SIDE_TOLERANCE, SPLINE_SIDES, fit_bilinear, nested_split,
                                      pca_table, spline_settings, spline_side, truncation_errors)
from btforge.plugins.bases.lightfuncs import octa_directions, smooth_resample_matrix, spline_weights

sys.path.insert(0, str(Path(__file__).parent))
from test_bases import light_sets  # noqa: E402


def hemisphere(n: int, seed: int, low: float = 0.2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(low, 1, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)


def dome(elevations_deg, per_ring: int, offset: float = 0.0) -> np.ndarray:
    rings = []
    for k, elevation in enumerate(np.radians(elevations_deg)):
        phi = np.linspace(0, 2 * np.pi, per_ring, endpoint=False) + offset + 0.3 * k
        rings.append(np.stack([np.cos(elevation) * np.cos(phi), np.cos(elevation) * np.sin(phi),
                               np.full(per_ring, np.sin(elevation))], 1))
    return np.vstack(rings)


# ----------------------------------------------------------------------------------------------- the spline


@pytest.mark.parametrize("smoothness", [1e-3, 1e-2, 1e-1])
def test_spline_reproduces_constants_exactly_and_affine_responses_nearly(smoothness):
    lights, queries = hemisphere(40, 0), hemisphere(200, 1)
    weights = spline_weights(lights, queries, smoothness)
    np.testing.assert_allclose(weights.sum(axis=1), 1.0, atol=1e-9)   # the constant term is not penalised
    slope = np.array([0.3, -0.2, 0.8])
    # the slope's faint ridge (SLOPE_RIDGE) shrinks an affine response by a few thousandths at most
    assert np.abs(weights @ (lights @ slope) - queries @ slope).max() < 5e-3


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lights=light_sets(), smoothness=st.sampled_from([1e-3, 1e-2, 1e-1]), seed=st.integers(0, 1000))
def test_spline_is_finite_and_bounded_on_few_clustered_and_grazing_lights(lights, smoothness, seed):
    rng = np.random.default_rng(seed)
    samples = rng.uniform(0, 1, (len(lights), 5))
    samples[:, 0], samples[:, 1] = 0.0, 1.0                                # black and saturated texels
    queries = np.vstack([lights, hemisphere(50, seed, low=0.0), [[0, 0, 1.0], [1.0, 0, 0]]])
    weights = spline_weights(lights, queries, smoothness)
    assert np.isfinite(weights).all()
    values = weights @ samples
    np.testing.assert_allclose(values[:, 0], 0.0, atol=1e-9)
    np.testing.assert_allclose(values[:, 1], 1.0, atol=1e-9)
    # bounded: far from a tight cluster of lights (2 degrees across) the spline extrapolates the noise it follows
    # there; the smoothing bounds that, |S|_inf within 26 / sqrt(smoothness) over 60 such clusters (a weak bound:
    # evaluation clips what it relights to [0, 1], and the fit's leave-one-out choice prefers larger weights there)
    assert np.abs(values).max() <= 30.0 / np.sqrt(smoothness)
    # at the lights themselves it is a smoothing of the samples: within their range up to the smoothing's overshoot
    assert values[:len(lights)].min() > -0.5 and values[:len(lights)].max() < 1.5


def test_leave_one_out_of_the_spline_is_exact():
    lights = hemisphere(25, 3)
    y = np.random.default_rng(4).uniform(0, 1, (25, 3))
    for smoothness in (1e-3, 3e-2):
        hat = spline_weights(lights, lights, smoothness)
        closed_form = y - (y - hat @ y) / (1.0 - np.diag(hat))[:, None]
        for i in range(0, 25, 6):
            keep = np.arange(25) != i
            refit = spline_weights(lights[keep], lights[i:i + 1], smoothness) @ y[keep]
            np.testing.assert_allclose(closed_form[i], refit[0], atol=1e-8)


# ----------------------------------------------------------------------------------------------- choices


def lambert_capture(lights: np.ndarray, size=(16, 16), seed: int = 0, spread: float = 0.25) -> SampleStack:
    rng = np.random.default_rng(seed)
    normal = rng.normal(0, spread, size + (3,)) + [0, 0, 1]
    normal /= np.linalg.norm(normal, axis=2, keepdims=True)
    albedo = rng.uniform(0.2, 0.9, size + (3,))
    shade = np.clip(np.einsum("hwk,lk->lhw", normal, lights), 0, None)[..., None] * albedo
    return SampleStack(linear_to_srgb8(shade)[None], lights, [[0, 0, 1]], encoding="srgb8")


def test_leave_one_out_picks_linear_radiance_for_lambertian_shading_and_a_constant_needs_the_coarsest_grid():
    lights = dome([15, 35, 55, 75], 12)
    space, smoothness = spline_settings(lambert_capture(lights), ("srgb", "linear"), 0.0)
    assert space == "linear" and smoothness > 0
    constant = SampleStack(np.full((1, len(lights), 4, 4, 3), 128, np.uint8), lights, [[0, 0, 1]], encoding="srgb8")
    assert spline_side(constant, "srgb", 1e-2) == SPLINE_SIDES[0]


@pytest.mark.parametrize("colorspace,ycc", [("rgb", (0, 0, 0)), ("ycc", (6, 3, 3))])
def test_pca_in_the_lights_span_gives_the_table_of_the_resampled_responses(colorspace, ycc):
    rng = np.random.default_rng(5)
    lights = hemisphere(30, 6)
    samples = (rng.random((3000, 30, 3)) * 1.3 - 0.1).astype(np.float32)    # beyond [0, 1]: the mean is clipped
    for resample in (spline_weights(lights, hemisphere(64, 7), 1e-2), smooth_resample_matrix(lights, 8, 0.003)):
        resampled = np.einsum("dl,nlc->ndc", resample, samples).astype(np.float32)
        explicit = pca_table(resampled, 12, colorspace, ycc)
        # float32 second moments of values up to ~1: agreement to ~1e-6 (eigenvectors of well-separated values)
        np.testing.assert_allclose(pca_table(samples, 12, colorspace, ycc, resample), explicit, atol=2e-5)


# ----------------------------------------------------------------------------------------------- planes: 0


def test_nested_split_follows_relights_plane_order():
    # (Y, Co, Cg) triplets while chroma planes last, then luma planes; a count ending inside a triplet is no split
    assert [nested_split((15, 6, 6), n) for n in (3, 4, 18, 19, 27)] == [(1, 1, 1), None, (6, 6, 6), (7, 6, 6),
                                                                          (15, 6, 6)]
    assert nested_split((15, 6, 6), 28) is None


def component_capture(lights, components: int, seed: int = 3, size: int = 24) -> SampleStack:
    """Texels mixing ``components`` smooth light responses (powers of n . l for random normals, each its own
    colour) with random weights: every texel lies in a ``components``-dimensional space of responses."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(0, 0.4, (components, 3)) + [0, 0, 1]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    shading = np.clip(lights @ normals.T, 0, None) ** rng.uniform(1, 3, components)          # [L, K]
    colours = rng.uniform(0.2, 1, (components, 3))
    weights = rng.uniform(0, 1.5 / components, (size, size, components))   # not summing to 1: K dims about the mean
    values = np.einsum("lk,hwk,kc->lhwc", shading, weights, colours)
    return SampleStack(np.rint(255 * linear_to_srgb(values))[None].astype(np.uint8), lights, [[0, 0, 1]],
                       encoding="srgb8")


@pytest.mark.parametrize("components", [1, 3, 5])
def test_planes_auto_keeps_the_components_a_capture_is_built_from(components):
    stack = component_capture(dome([15, 35, 55, 75], 12), components)
    model, stats = fit_bilinear(stack, planes=0, space="linear", resolution=0)
    # linear radiance mixes the responses linearly: the components and, at most, the direction the clipped mean
    # leaves out; 8-bit rounding is far below the half-level tolerance
    assert components <= stats["planes"] <= components + 1
    fixed = fit_bilinear(stack, planes=stats["planes"] + 4, space="linear", resolution=0)[0]
    lights = stack.lights
    assert np.abs(model.evaluate(lights) - fixed.evaluate(lights)).max() < 4 * SPLINE_SIDE_TOLERANCE


def test_truncation_errors_vanish_with_every_plane_and_stay_finite_on_black_and_saturated_texels():
    rng = np.random.default_rng(2)
    lights = hemisphere(20, 4)
    y = rng.uniform(0, 1, (20, 50, 3))
    y[:, 0], y[:, 1] = 0.0, 1.0                                              # black and saturated texels
    side = 3                                                                  # 9 nodes: 27 planes hold the grid
    resample = spline_weights(lights, octa_directions(side), 1e-2)
    table = pca_table(y.transpose(1, 0, 2).astype(np.float32), 27, "rgb", (0, 0, 0), resample)
    args = {"kind": "bilinear", "table": table, "colorspace": "rgb", "yccplanes": (0, 0, 0), "resolution": side,
            "space": "srgb"}
    errors = truncation_errors(table, args, resample, y, lights, "srgb")
    assert errors.shape == (28,) and np.isfinite(errors).all() and errors[0] > 0.05
    assert errors[-1] < 1e-5                      # every component: the grid itself (float32 table)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lights=light_sets(), seed=st.integers(0, 1000), colorspace=st.sampled_from(["rgb", "ycc"]))
def test_planes_auto_is_a_valid_count_on_few_clustered_and_grazing_lights(lights, seed, colorspace):
    stack = component_capture(lights, 3, seed, size=6)
    samples = stack.samples.copy()
    samples[0, :, 0, 0], samples[0, :, 0, 1] = 0, 255                          # black and saturated texels
    stack = SampleStack(samples, lights, [[0, 0, 1]], encoding="srgb8")
    model, stats = fit_bilinear(stack, planes=0, colorspace=colorspace)
    assert 1 <= stats["planes"] <= AUTO_PLANES and model.n_plane == stats["planes"]
    if colorspace == "ycc":
        assert sum(model.yccplanes) == stats["planes"] and model.yccplanes[1] == model.yccplanes[2]
    relit = model.evaluate(np.vstack([lights, [[0, 0, 1.0], [1.0, 0, 0]]]))
    assert np.isfinite(relit).all() and relit.min() >= 0 and relit.max() <= 1


# ----------------------------------------------------------------------------------------------- accuracy


def test_spline_resampling_predicts_lights_between_a_domes_rings_better_than_the_grid_resamplings():
    fit_lights = dome([10, 30, 50, 70], 12)
    test_lights = dome([20, 40, 60], 8, offset=0.2)
    # gently tilted normals: little attached shadow, so the shading between the rings is smooth (about 47 dB with
    # the spline, 35 dB with either grid resampling, which follow where the grid lines fall against the rings)
    full = lambert_capture(np.vstack([fit_lights, test_lights]), size=(24, 24), seed=1, spread=0.1)
    fit = SampleStack(full.samples[:, :len(fit_lights)], fit_lights, full.views, encoding="srgb8")
    truth = full.samples[0, len(fit_lights):] / 255.0

    def psnr(**params):
        model = fit_bilinear(fit, planes=9, resolution=params.pop("resolution", 0), **params)[0]
        predicted = linear_to_srgb(model.evaluate(test_lights)[0])
        return -10 * np.log10(np.mean((predicted - truth) ** 2))
    spline = psnr()
    assert spline > 42.0
    assert spline > psnr(resampling="smooth", space="srgb") + 5.0
    assert spline > psnr(resampling="relight", resolution=8, space="srgb") + 5.0
