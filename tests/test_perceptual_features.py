"""The synthesizers' appearance vectors of linear exemplars: texels compared as a screen shows them.

A stack, or a model of light only fitted to linear radiance, is compared through its display values at probe
lights (each light exposed by the exemplar's white point, sRGB-encoded); a model fitted to display values keeps
its own coefficients.  Checked against the encoding written out, on the property the change is for (a step in a
shadow counts as the eye sees it), and on hard radiance (black, tiny, huge, negative) with Hypothesis."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btforge.buffers import SampleStack
from btforge.plugins.ptm.model import PTMModel
from btforge.plugins.synth.features import (PERCEPTUAL_DIMS, WHITE_PERCENTILE, encoded, perceptual_samples,
                                            probe_lights, texel_features, white_points)


def linear_ptm(coeffs: np.ndarray, space: str = "linear") -> PTMModel:
    return PTMModel(coeffs.astype(np.float32), np.zeros(coeffs.shape[:2] + (0,), np.float32), "rgb", space)


def smooth_coeffs(seed: int, size: int = 12) -> np.ndarray:
    rng = np.random.default_rng(seed)
    coeffs = rng.normal(0, 0.05, (size, size, 3, 6))
    coeffs[..., 5] += rng.uniform(0.05, 0.9, (size, size, 3))   # the constant term: a brightness per texel
    return coeffs


def srgb(y: np.ndarray) -> np.ndarray:
    """The sRGB curve, unclipped above 1, written out."""
    return np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.maximum(y, 0) ** (1 / 2.4) - 0.055)


def test_a_linear_model_is_seen_at_probe_lights_exposed_and_encoded():
    model = linear_ptm(smooth_coeffs(0))
    seen = perceptual_samples(model)
    lights = probe_lights()
    radiance = model.evaluate(lights)[0].astype(np.float64)                     # [L, H, W, C]
    white = np.array([np.percentile(frame, WHITE_PERCENTILE) for frame in radiance])
    expected = srgb(np.maximum(radiance / white[:, None, None, None], 0))
    assert seen.shape == (12, 12, len(lights) * 3)
    np.testing.assert_allclose(seen, np.moveaxis(expected, 0, 2).reshape(12, 12, -1), rtol=1e-4, atol=1e-5)
    assert texel_features(model).shape == (12, 12, PERCEPTUAL_DIMS)
    assert texel_features(model, max_dims=5).shape == (12, 12, 5)


def test_a_model_of_display_values_keeps_its_coefficients():
    model = linear_ptm(smooth_coeffs(1), space="srgb")
    assert perceptual_samples(model) is None
    np.testing.assert_array_equal(texel_features(model, max_dims=None), model.appearance_features())


def test_an_8_bit_stack_is_seen_through_its_decoded_radiance():
    rng = np.random.default_rng(2)
    samples = rng.integers(0, 256, (1, 4, 6, 5, 3), dtype=np.uint8)
    lights = np.array([[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8]])
    stack = SampleStack(samples, lights, [[0, 0, 1]], encoding="srgb8")
    linear = stack.linear()[0]
    seen = perceptual_samples(stack)
    expected = encoded(linear, white_points(linear), "srgb")
    np.testing.assert_array_equal(seen, np.moveaxis(expected, 0, 2).reshape(6, 5, -1))


def test_a_step_in_the_shadows_counts_as_the_eye_sees_it():
    """Two pairs of texels with the same linear step, one pair dark and one bright: in radiance they are equally
    far apart, as a screen shows them the dark pair is much further apart."""
    coeffs = np.zeros((1, 4, 3, 6))
    coeffs[0, :, :, 5] = np.array([0.01, 0.03, 0.80, 0.82])[:, None]
    model = linear_ptm(coeffs)
    linear = model.appearance_features()[0]
    seen = perceptual_samples(model)[0]
    assert np.linalg.norm(linear[1] - linear[0]) == pytest.approx(np.linalg.norm(linear[3] - linear[2]), rel=1e-3)
    assert np.linalg.norm(seen[1] - seen[0]) > 4 * np.linalg.norm(seen[3] - seen[2])


@settings(max_examples=40, deadline=None)
@given(scale=st.sampled_from([0.0, 1e-30, 1e-6, 1.0, 1e6, 1e30]), negative=st.booleans(),
       constant=st.booleans(), seed=st.integers(0, 2 ** 16))
def test_hard_radiance_gives_finite_bounded_vectors(scale, negative, constant, seed):
    """Black, tiny, huge or constant radiance and polynomials that dip below zero between the lights: every
    vector is finite, in [0, the encoding of the brightest texel over its white], and a black image is 0."""
    coeffs = smooth_coeffs(seed, 8)
    if constant:
        coeffs[:] = coeffs[0, 0]
    if negative:
        coeffs[..., 0] -= 2.0      # a steep slope in lu: negative radiance on one side of the hemisphere
    model = linear_ptm(coeffs * scale)
    seen = perceptual_samples(model)
    assert np.isfinite(seen).all()
    radiance = model.evaluate(probe_lights())[0]
    ceiling = srgb(np.max(radiance / white_points(radiance)[:, None, None, None], initial=0.0))
    assert seen.min() >= 0.0 and seen.max() <= ceiling * (1 + 1e-5) + 1e-6
    if scale == 0.0:
        assert not seen.any()
    reduced = texel_features(model)
    assert np.isfinite(reduced).all() and reduced.shape == (8, 8, PERCEPTUAL_DIMS)
