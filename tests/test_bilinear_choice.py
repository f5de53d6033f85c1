"""bilinear.fit's automatic grid side: leave-one-light-out in closed form (plugins/bases/lightout.py) against
refits without each light, and its PCA table from the samples' moments against the table of the responses."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btforge.buffers import SampleStack, linear_to_srgb
from btforge.plugins.bases.fit import (bilinear_light_out_error, fit_bilinear, grid_samples, pca_table, unit_lights,
                                       ycc_split)
from btforge.plugins.bases.lightfuncs import resample_matrix, smooth_resample_matrix
from btforge.plugins.bases.lightout import moment_table, sample_moments, table_factors

sys.path.insert(0, str(Path(__file__).parent))
from test_web_export import capture  # noqa: E402


def random_lights(rng, n):
    z = rng.uniform(0.15, 1, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    return np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)


def projector(vectors):
    flat = vectors.reshape(len(vectors), -1)
    return flat.T @ flat


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2 ** 31 - 1), n_light=st.integers(10, 30), side=st.integers(3, 7),
       colorspace=st.sampled_from(["rgb", "ycc"]), scale=st.sampled_from([1e-3, 1.0, 1e3]))
def test_the_table_from_moments_is_the_table_of_the_responses(seed, n_light, side, colorspace, scale):
    rng = np.random.default_rng(seed)
    planes = 6 if colorspace == "rgb" else 8
    ycc = ycc_split(planes, 0) if colorspace == "ycc" else (0, 0, 0)
    # a clear spectrum (components of decreasing strength, faint noise), so the leading components are unique;
    # a scale far from display values moves the clipped mean and the moments' magnitudes
    strength = scale * 0.5 ** np.arange(12)
    samples = (0.5 + np.einsum("nk,k,klc->nlc", rng.normal(size=(400, 12)), strength,
                               rng.normal(size=(12, n_light, 3)) / np.sqrt(n_light))
               + scale * 1e-6 * rng.normal(size=(400, n_light, 3)))
    resample = smooth_resample_matrix(random_lights(rng, n_light), side, 0.003)
    want = pca_table(np.einsum("dl,nlc->ndc", resample, samples), planes, colorspace, ycc)
    mean, second = sample_moments(samples)
    got = moment_table(mean, table_factors(second, colorspace), resample, planes, colorspace, ycc)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got[0], want[0], atol=1e-9 * max(scale, 1.0))
    if colorspace == "rgb":
        np.testing.assert_allclose(projector(got[1:]), projector(want[1:]), atol=1e-3)
    else:
        for comp in range(3):
            used = [p for p in range(planes) if np.any(want[p + 1, :, comp])]
            np.testing.assert_allclose(projector(got[1:, :, comp][used]), projector(want[1:, :, comp][used]),
                                       atol=1e-3)


def test_components_beyond_the_samples_rank_are_zero_not_blown_up():
    rng = np.random.default_rng(3)
    samples = 0.5 + 0.1 * rng.normal(size=(50, 4, 3))          # 12 sample dimensions, 13 with the constant
    resample = smooth_resample_matrix(random_lights(rng, 4), 6, 0.003)
    mean, second = sample_moments(samples)
    table = moment_table(mean, table_factors(second, "rgb"), resample, 40, "rgb", (0, 0, 0))
    norms = np.linalg.norm(table[1:].reshape(40, -1), axis=1)
    assert np.all(np.isfinite(table)) and np.all(norms <= 1 + 1e-9) and np.count_nonzero(norms > 0.5) <= 13


@pytest.mark.parametrize("space,side,colorspace,planes,coefficients,resampling", [
    ("srgb", 5, "rgb", 6, "projection", "smooth"), ("linear", 6, "ycc", 8, "projection", "smooth"),
    ("srgb", 4, "rgb", 6, "lsq", "smooth"), ("srgb", 5, "rgb", 6, "projection", "relight")])
def test_the_closed_form_is_the_refit_without_each_light(space, side, colorspace, planes, coefficients, resampling):
    stack = capture(n=14, size=(6, 5), seed=2)
    lights = unit_lights(stack.lights)
    ycc = ycc_split(planes, 0) if colorspace == "ycc" else (0, 0, 0)

    def make_resample(subset, grid_side):
        if resampling == "smooth":
            return smooth_resample_matrix(subset, grid_side, 0.003)
        return resample_matrix(subset, grid_side, 0.125, 0.1)
    closed = bilinear_light_out_error(grid_samples(stack, space), grid_samples(stack, "srgb"), lights, space, side,
                                      {"planes": planes, "colorspace": colorspace, "ycc": ycc,
                                       "resample": make_resample, "coefficients": coefficients})
    total = 0.0
    for index in range(stack.n_light):
        keep = np.arange(stack.n_light) != index
        part = SampleStack(np.ascontiguousarray(stack.samples[:, keep]), stack.lights[keep], stack.views,
                           stack.channels, stack.encoding)
        model = fit_bilinear(part, planes, side, colorspace, coefficients=coefficients, resampling=resampling,
                             space=space)[0]
        predicted = linear_to_srgb(model.evaluate(stack.lights[index:index + 1])[0, 0]).astype(np.float64)
        total += float(np.sum((predicted - stack.samples[0, index] / 255.0) ** 2))
    # the refits' PCA runs in float32 and the kernels evaluate in float32: agreement to ~1e-5 relative
    assert closed == pytest.approx(total / (stack.n_light * stack.height * stack.width * 3), rel=1e-4)
