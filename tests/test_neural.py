"""neural.fit and NeuralModel: a learned basis (latent code per texel, shared decoder)."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import btforge
from btforge import BtforgeInputError
from btforge.buffers import SampleStack, linear_to_srgb
from btforge.plugins.neural import NeuralModel
from btforge.plugins.neural.network import (decoder_backward, decoder_forward, init_layers, mlp_backward,
                                            mlp_forward)

sys.path.insert(0, str(Path(__file__).parent))
from test_bases import hard_stack, light_sets  # noqa: E402
from test_web_export import capture  # noqa: E402

SMALL = {"latent": 6, "hidden": 16, "layers": 2, "light_order": 3, "epochs": 4, "texels": 200}


def fitted(stack, **params):
    return btforge.stage("neural.fit")(stack=stack, **{**SMALL, **params})["model"]


def test_gradients_match_finite_differences():
    rng = np.random.default_rng(1)
    encoder, decoder = init_layers(rng, (12, 7, 3)), init_layers(rng, (3 + 2, 6, 6, 3))
    x, features, target = rng.normal(size=(4, 12)), rng.normal(size=(5, 2)), rng.normal(size=(4 * 5, 3))
    to64 = [[a.astype(np.float64) for a in layer] for layer in encoder + decoder]
    encoder, decoder = to64[:2], to64[2:]

    def loss():
        codes = mlp_forward(encoder, x)[-1]
        return float(((decoder_forward(decoder, codes, features)[1][-1] - target) ** 2).sum())
    enc_outs = mlp_forward(encoder, x)
    first, outs = decoder_forward(decoder, enc_outs[-1], features)
    grad_dec, grad_codes = decoder_backward(decoder, enc_outs[-1], features, first, outs, 2 * (outs[-1] - target))
    grad_enc, _ = mlp_backward(encoder, enc_outs, grad_codes)
    for layer, grads in zip(encoder + decoder, grad_enc + grad_dec):
        for param, grad in zip(layer, grads):
            index = tuple(rng.integers(0, s) for s in param.shape)
            param[index] += 1e-6
            up = loss()
            param[index] -= 2e-6
            down = loss()
            param[index] += 1e-6
            assert grad[index] == pytest.approx((up - down) / 2e-6, rel=1e-4, abs=1e-6)


def test_fits_a_lambertian_capture_and_predicts_lights_between_its_own():
    stack = capture(n=40, size=(24, 20))
    train, test = (SampleStack(stack.samples[:, m], stack.lights[m], stack.views, encoding="srgb8")
                   for m in (np.arange(40) % 5 != 0, np.arange(40) % 5 == 0))
    model = fitted(train, latent=8, hidden=32, layers=3, light_order=4, epochs=200, texels=480)
    error = linear_to_srgb(model.evaluate(test.lights)[0]) - test.samples[0] / 255.0
    psnr = 10 * np.log10(1 / np.mean(error ** 2))
    assert psnr > 30, psnr


@pytest.mark.parametrize("decoder", ["harmonics", "light"])
def test_model_files_round_trip_exactly(tmp_path, decoder):
    model = fitted(capture(n=20, size=(8, 6)), decoder=decoder)
    btforge.stage("models.write")(model=model, path=str(tmp_path / "m.btfm"))
    back = btforge.stage("models.read")(path=str(tmp_path / "m.btfm"))["model"]
    assert isinstance(back, NeuralModel) and back.content_key == model.content_key
    assert np.array_equal(back.codes, model.codes) and np.array_equal(back.weights, model.weights)
    assert (back.layer_sizes, back.light_order, back.decoder, back.channel_names) == \
        (model.layer_sizes, model.light_order, model.decoder, model.channel_names)
    lights = [[0.3, 0.2, 0.93], [0, 0, 1]]
    assert np.array_equal(back.evaluate(lights), model.evaluate(lights))


def test_fits_are_deterministic_and_the_seed_matters():
    stack = capture(n=20, size=(8, 6))
    first, again, other = fitted(stack), fitted(stack), fitted(stack, seed=1)
    assert first.content_key == again.content_key
    assert first.content_key != other.content_key


@pytest.mark.parametrize("decoder,light_order", [("harmonics", 2), ("harmonics", 4), ("light", 0), ("light", 3)])
def test_per_texel_evaluation_matches_the_grid(decoder, light_order):
    model = fitted(capture(n=20, size=(8, 6)), decoder=decoder, light_order=light_order)
    rng = np.random.default_rng(0)
    rows, cols = rng.integers(0, 8, 30), rng.integers(0, 6, 30)
    lights = rng.normal(size=(30, 3)) + [0, 0, 2]
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    grid = model.evaluate(lights)[0]
    expected = grid[np.arange(30), rows, cols]
    assert np.allclose(model.evaluate_texels(rows, cols, lights), expected, atol=1e-5)


@pytest.mark.parametrize("decoder", ["harmonics", "light"])
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lights=light_sets(), seed=st.integers(0, 1000))
def test_hard_light_sets_and_texels_give_finite_bounded_models(decoder, lights, seed):
    model = fitted(hard_stack(lights, seed), decoder=decoder, epochs=30, texels=12, seed=seed)
    assert np.isfinite(model.codes).all() and np.isfinite(model.weights).all()
    probe = np.vstack([lights, [[0, 0, 1.0], [1.0, 0, 0], [0, -1.0, 0], [0.6, 0, -0.8]]])
    relit = model.evaluate(probe)
    assert np.isfinite(relit).all() and relit.min() >= 0 and relit.max() <= 1


def test_a_single_light_and_a_black_capture_fit_to_finite_models():
    black = SampleStack(np.zeros((1, 1, 4, 4, 3), np.uint8), [[0, 0, 1.0]], [[0, 0, 1]], encoding="srgb8")
    model = fitted(black)
    assert np.isfinite(model.codes).all() and model.evaluate([[0.5, 0, 0.866]]).max() <= 0.01


def test_bad_parameters_and_damaged_models_are_refused_with_the_reason():
    with pytest.raises(BtforgeInputError, match="light_order"):
        fitted(capture(n=10, size=(4, 4)), light_order=1)
    with pytest.raises(BtforgeInputError, match="light_order"):
        fitted(capture(n=10, size=(4, 4)), light_order=0)   # x, y is an input of the light decoder only
    model = fitted(capture(n=10, size=(4, 4)))
    with pytest.raises(BtforgeInputError, match="weights"):
        NeuralModel(model.codes, model.weights[:-1], model.layer_sizes, model.light_order, model.decoder)
    with pytest.raises(BtforgeInputError, match="layer_sizes"):
        NeuralModel(model.codes[..., :-1], model.weights, model.layer_sizes, model.light_order, model.decoder)



def test_web_export_refuses_the_model_with_the_reason(tmp_path):
    with pytest.raises(BtforgeInputError, match="NeuralModel"):
        btforge.stage("web.export")(model=fitted(capture(n=10, size=(4, 4))), dir=str(tmp_path / "web"))


def test_relight_stage_and_synthesis_take_the_model():
    from btforge.context import StageContext
    from btforge.plugins.synth import materialize
    from btforge.plugins.synth.quilting import quilt
    model = fitted(capture(n=20, size=(16, 16)))
    lights = [[0.3, 0.2, 0.93], [0, 0, 1.0]]
    relit = btforge.stage("relight.images")(model=model, lights=lights)["stack"]
    assert np.array_equal(relit.samples, model.evaluate(lights))
    coords = quilt(ctx=StageContext(node="quilt"), exemplar=model, size=[24, 24], seam="cut", seed=1, block=8,
                   overlap=2)["coords"]
    grown = materialize(coords=coords, source=model)["output"]
    assert isinstance(grown, NeuralModel) and grown.codes.shape == (24, 24, model.latent)
    rows, cols = coords.coords[..., 0], coords.coords[..., 1]
    np.testing.assert_allclose(grown.evaluate(lights), model.evaluate(lights)[:, :, rows, cols], atol=1e-6)
