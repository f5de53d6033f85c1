"""neural.fit and NeuralModel: a learned basis (latent code per texel, shared decoder)."""
from __future__ import annotations

import json
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



OPENLIME = {"decoder": "light", "light_order": 0, "latent": 9, "layers": 2}   # NeuralRTI's network
PROBE = np.array([[0, 0, 1.0], [0.6, 0.2, 0.77], [-0.5, -0.5, 0.71], [0.1, 0.9, 0.42], [-0.95, 0.1, 0.3]])
PROBE = PROBE / np.linalg.norm(PROBE, axis=1, keepdims=True)


def quantisation_bound(model, steps: np.ndarray) -> np.ndarray:
    """Per (light, texel, channel), how far the display value can move when every code moves by up to half its
    8-bit step: the sum over codes of the larger secant change over +-half a step (first order in each code;
    exact for a decoder linear in the codes)."""
    codes = model.codes.reshape(-1, model.latent).astype(np.float64)
    base = model.display_values(codes.astype(np.float32), PROBE).astype(np.float64)
    bound = np.zeros_like(base)
    for k, half in enumerate(steps / 2):
        moved = [model.display_values((codes + sign * half * np.eye(model.latent)[k]).astype(np.float32), PROBE)
                 for sign in (1, -1)]
        bound += np.maximum(*(np.abs(m - base) for m in moved))
    return bound


@pytest.mark.parametrize("decoder", ["harmonics", "light"])
def test_web_export_round_trips_within_the_code_quantisation(tmp_path, decoder):
    model = fitted(capture(n=20, size=(12, 10)), decoder=decoder, epochs=20)
    btforge.stage("web.export")(model=model, dir=str(tmp_path / "web"))
    back = btforge.stage("web.read")(path=str(tmp_path / "web"))["model"]
    assert isinstance(back, NeuralModel) and np.array_equal(back.weights, model.weights)   # JSON keeps float32
    assert (back.layer_sizes, back.light_order, back.decoder) == (model.layer_sizes, model.light_order, decoder)
    steps = np.ptp(model.codes, axis=(0, 1)) / 255.0
    assert np.all(np.abs(back.codes - model.codes) <= steps / 2 * (1 + 1e-5) + 1e-7)
    # the relit display values move by at most what half a step of every code can move them (1.5x for the
    # decoder's curvature across a step); clipping and the sRGB decode only shrink differences in display space
    flat = back.codes.reshape(-1, back.latent)
    moved = np.abs(back.display_values(flat, PROBE) - model.display_values(model.codes.reshape(flat.shape), PROBE))
    assert np.all(moved <= 1.5 * quantisation_bound(model, steps) + 1e-5)
    before, after = (linear_to_srgb(m.evaluate(PROBE)) for m in (model, back))
    assert np.abs(after - before).max() <= 1.5 * quantisation_bound(model, steps).max() + 1e-5
    assert 10 * np.log10(1 / np.mean((after - before) ** 2)) >= 45


def test_openlime_layout_of_neuralrti_networks(tmp_path):
    model = fitted(capture(n=20, size=(8, 6)), **OPENLIME)
    btforge.stage("web.export")(model=model, dir=str(tmp_path / "nrti"), format="jpg")
    info = json.loads((tmp_path / "nrti" / "info.json").read_text())
    assert sorted(p.name for p in (tmp_path / "nrti").iterdir()) == ["info.json", "plane_1.jpg", "plane_2.jpg",
                                                                       "plane_3.jpg"]
    assert (info["type"], info["colorspace"], info["planes"], info["samples"]) == ("neural", "rgb", 9, 16)
    assert np.array(info["min"]).shape == (3, 3) and np.array(info["max"]).shape == (3, 3)
    # ShaderNeural's uniforms: layer1 c x n, layer2 n x n, layer3 3 x n (c = 9 + 2 padded to 12, n = 16)
    assert [len(w) for w in info["weights"]] == [16 * 12, 16 * 16, 3 * 16]
    assert [len(b) for b in info["biases"]] == [16, 16, 3] and info["btforge"]["openlime"]
    w1 = np.array(info["weights"][0]).reshape(16, 12)   # output-major: row o holds the inputs of unit o
    np.testing.assert_array_equal(w1[:, :11], model.layers()[0][0].T)
    assert not w1[:, 11:].any()
    # ShaderNeural's evaluation, from info.json and the images alone: inputs (9 codes, light x, y, 0), vec4 row
    # i * c / 4 + j of layer1_weights against inputs[j] (so weights[0] is [n, c] row-major), ELU, ..., linear out
    from PIL import Image
    pixels = np.concatenate([np.asarray(Image.open(tmp_path / "nrti" / f"plane_{j}.jpg").convert("RGB"))
                             for j in (1, 2, 3)], axis=2) / 255.0
    low, high = np.array(info["min"]).reshape(-1), np.array(info["max"]).reshape(-1)
    codes = (pixels * (high - low) + low).reshape(-1, 9)
    light = PROBE[1]
    x = np.hstack([codes, np.tile([light[0], light[1], 0.0], (len(codes), 1))])
    elu = lambda v: np.where(v > 0, v, np.expm1(np.minimum(v, 0)))  # noqa: E731
    for i, (rows, cols) in enumerate([(16, 12), (16, 16), (3, 16)]):
        x = x @ np.array(info["weights"][i]).reshape(rows, cols).T + np.array(info["biases"][i])
        x = elu(x) if i < 2 else x
    back = btforge.stage("web.read")(path=str(tmp_path / "nrti"))["model"]
    expected = back.display_values(back.codes.reshape(-1, 9), light[None])[0]
    np.testing.assert_allclose(x, expected, atol=1e-5)
    harmonics = fitted(capture(n=20, size=(8, 6)))
    btforge.stage("web.export")(model=harmonics, dir=str(tmp_path / "sh"))
    assert not json.loads((tmp_path / "sh" / "info.json").read_text())["btforge"]["openlime"]


def test_a_layout_without_btforge_fields_reads_as_neuralrti(tmp_path):
    model = fitted(capture(n=20, size=(8, 6)), **OPENLIME)
    btforge.stage("web.export")(model=model, dir=str(tmp_path / "w"))
    info = json.loads((tmp_path / "w" / "info.json").read_text())
    del info["btforge"]
    (tmp_path / "w" / "info.json").write_text(json.dumps(info))
    back = btforge.stage("web.read")(path=str(tmp_path / "w"))["model"]
    assert (back.decoder, back.light_order, back.layer_sizes) == ("light", 0, (11, 16, 16, 3))
    assert np.array_equal(back.weights, model.weights)


code_values = st.floats(-1e30, 1e30, allow_nan=False, allow_infinity=False)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(["constant", "huge", "mixed", "tiny"]), value=code_values, seed=st.integers(0, 99))
def test_code_quantisation_is_exact_to_half_a_step_and_finite_on_hard_codes(tmp_path, kind, value, seed):
    import tempfile
    from btforge.plugins.web.layout import read_web, write_web
    rng = np.random.default_rng(seed)
    codes = {"constant": np.full((3, 4, 5), value),
             "huge": rng.uniform(-1, 1, (3, 4, 5)) * abs(value),
             "mixed": np.concatenate([np.full((3, 4, 2), value), rng.normal(0, 1e6, (3, 4, 3))], axis=2),
             "tiny": value * 1e-35 + rng.normal(0, 1e-30, (3, 4, 5))}[kind].astype(np.float32)
    layers = [[rng.normal(0, 0.3, (5, 8)).astype(np.float32), np.zeros(8, np.float32)],
              [rng.normal(0, 0.3, (8, 12)).astype(np.float32), np.full(12, 0.1, np.float32)]]
    from btforge.plugins.neural.network import pack_layers
    model = NeuralModel(codes, pack_layers(layers), (5, 8, 12), 2, "harmonics")
    with tempfile.TemporaryDirectory(dir=tmp_path) as folder:
        write_web(model, folder)
        back = read_web(folder)
    span = np.ptp(codes.astype(np.float64), axis=(0, 1))
    assert np.isfinite(back.codes).all()
    # half a step, plus float32 rounding of the code and of min + byte / 255 * span
    tolerance = span / 510 + 4 * np.finfo(np.float32).eps * np.abs(codes.astype(np.float64)).max(axis=(0, 1)) + 1e-37
    assert np.all(np.abs(back.codes.astype(np.float64) - codes) <= tolerance)
    if kind == "constant":
        assert np.array_equal(back.codes, codes)
    relit = back.evaluate(PROBE)
    assert np.isfinite(relit).all() and relit.min() >= 0 and relit.max() <= 1


def broken_layout(tmp_path, change) -> Path:
    model = fitted(capture(n=10, size=(6, 5)))
    folder = tmp_path / "w"
    btforge.stage("web.export")(model=model, dir=str(folder))
    info = json.loads((folder / "info.json").read_text())
    change(info, folder)
    (folder / "info.json").write_text(json.dumps(info))
    return folder


@pytest.mark.parametrize("change,expected", [
    (lambda info, f: info.pop("weights"), ["'weights': expected 3 lists", "found none"]),
    (lambda info, f: info["weights"][1].pop(), ["'weights[1]': expected 256 finite numbers", "16 outputs x 16 inputs",
                                                 "found 255 values"]),
    (lambda info, f: info["btforge"].update(layer_sizes=[6, 16, 16, 3]),
     ["btforge.layer_sizes", "27 outputs, found 6 to 3"]),
    (lambda info, f: info.update(planes=7, samples="fifty"), ["'planes'", "'samples'"]),
    (lambda info, f: info["biases"][0].__setitem__(3, "x"), ["'biases[0]': expected 16 finite numbers",
                                                            "found 'x' at index 3"]),
    (lambda info, f: info.update(min=[[0, 0, 0]]), ["'min': expected 2 [r, g, b] triples"]),
])
def test_malformed_neural_layouts_are_named_with_the_fix(tmp_path, change, expected):
    from btforge.plugins.web.layout import read_web
    folder = broken_layout(tmp_path, change)
    with pytest.raises(BtforgeInputError) as err:
        read_web(folder)
    text = str(err.value)
    assert str(folder / "info.json") in text and "export the model again" in text
    for part in expected:
        assert part in text, (part, text)


def test_a_code_image_of_the_wrong_size_is_named(tmp_path):
    from PIL import Image
    from btforge.plugins.web.layout import read_web
    folder = broken_layout(tmp_path, lambda info, f: Image.new("RGB", (3, 3)).save(f / "plane_2.png"))
    with pytest.raises(BtforgeInputError, match=r"plane_2.png.*expected 5 x 6 pixels.*found 3 x 3"):
        read_web(folder)
    (folder / "plane_2.png").unlink()
    with pytest.raises(BtforgeInputError, match="plane_2.png"):
        read_web(folder)


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


def exact_relight(model, lights) -> np.ndarray:
    """The model's relighting ``[L, T, C]`` evaluated in float64 (the reference both float32 engines round)."""
    from btforge.plugins.neural.model import decode_display
    layers = [[a.astype(np.float64) for a in layer] for layer in model.layers()]
    display = model.display_values(model.codes.reshape(-1, model.latent).astype(np.float64), lights, layers)
    return decode_display(display).astype(np.float64), display


def random_model(rng, decoder, light_order, latent, sizes, codes):
    from btforge.plugins.neural.network import init_layers
    layers = init_layers(rng, sizes)
    for layer in layers:
        layer[1][:] = rng.normal(0, 0.2, layer[1].shape)
    return NeuralModel(codes.astype(np.float32), np.concatenate([a.reshape(-1) for l in layers for a in l]),
                       sizes, light_order, decoder)


GRAZING = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, -1.0, 0], [0.6, 0, -0.8], [0.7, 0.7, 0.01], [0.3, -0.2, 0.93]])


@pytest.mark.parametrize("decoder,light_order,latent,hidden", [("harmonics", 4, 12, 50), ("harmonics", 2, 5, 7),
                                                               ("light", 0, 9, 50), ("light", 3, 12, 21)])
@pytest.mark.parametrize("codes_kind", ["random", "zero", "large", "huge"])
def test_opencl_kernel_matches_its_numpy_twin(decoder, light_order, latent, hidden, codes_kind):
    from btforge.plugins.neural.lightinput import n_light_features
    rng = np.random.default_rng(7)
    shape = (9, 13, latent)   # 117 texels: not a multiple of the kernel's 8 lanes
    codes = {"random": rng.normal(0, 1, shape), "zero": np.zeros(shape), "large": rng.normal(0, 1e4, shape),
             "huge": rng.normal(0, 1e15, shape)}[codes_kind]
    n_in = latent + (n_light_features(light_order) if decoder == "light" else 0)
    n_out = 3 if decoder == "light" else 3 * light_order ** 2
    model = random_model(rng, decoder, light_order, latent, (n_in, hidden, hidden, hidden, n_out), codes)
    lights = np.vstack([GRAZING, rng.normal(size=(4, 3))])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    kernel, twin = (model.evaluate(lights, engine=e)[0].reshape(len(lights), -1, 3) for e in ("opencl", "numpy"))
    assert np.isfinite(kernel).all() and kernel.min() >= 0 and kernel.max() <= 1
    # both are float32 evaluations of one network, summing in their own order: the kernel may stray from the
    # float64 value by a few times as much as the twin does, plus a few ulps of expm1 / powr (OpenCL allows 16)
    exact, display = exact_relight(model, lights)
    twin_error = np.abs(twin - exact).max()
    assert np.abs(kernel - exact).max() <= 4 * twin_error + 16 * np.finfo(np.float32).eps
    # where the value is clipped beyond doubt, both give the clipped value exactly
    sure = np.abs(display - 0.5) > 0.5 + 1e-3
    assert np.array_equal(kernel[sure], twin[sure])
    if codes_kind == "zero":   # every texel decodes the same code
        assert np.ptp(kernel, axis=1).max() == 0


def test_bench_times_both_engines_on_a_capture(tmp_path, capsys):
    from btforge.plugins.neural.bench import bench_neural
    from btforge.plugins.ptm.bench import make_synthetic_capture
    lp = make_synthetic_capture(tmp_path, 16, 12)
    assert bench_neural([str(lp), "--lights", "3", "--repeat", "1", "--epochs", "1",
                         "--json", str(tmp_path / "f.json")]) == 0
    figures = json.loads((tmp_path / "f.json").read_text())
    assert figures["size"] == [16, 16] and figures["lights"] == 3
    for decoder in ("harmonics", "light"):
        row = figures[decoder]
        assert row["numpy"]["cpu_s_per_mp"] >= 0 and row["opencl"]["wall_s_per_mp"] > 0
        assert row["max_abs_difference"] < 1e-4
    assert "relit megapixel" in capsys.readouterr().out


@settings(max_examples=20, deadline=None)
@given(lights=light_sets(), scale=st.sampled_from([0.0, 1e-30, 1.0, 30.0, 1e4, 1e30]),
       decoder=st.sampled_from(["harmonics", "light"]), seed=st.integers(0, 99))
def test_kernel_stays_finite_bounded_and_with_its_twin_on_hard_lights_and_codes(lights, scale, decoder, seed):
    rng = np.random.default_rng(seed)
    n_in, n_out = (6, 27) if decoder == "harmonics" else (6 + 8, 3)
    model = random_model(rng, decoder, 3, 6, (n_in, 12, 12, n_out), rng.normal(0, 1, (5, 7, 6)) * scale)
    kernel, twin = (model.evaluate(lights, engine=e)[0].reshape(len(lights), -1, 3) for e in ("opencl", "numpy"))
    assert np.isfinite(kernel).all() and kernel.min() >= 0 and kernel.max() <= 1
    exact, display = exact_relight(model, lights)
    finite = np.isfinite(display)   # 1e30 codes overflow float32 on the way: NaN or inf, then clipped
    assert np.abs(kernel - exact)[finite].max(initial=0) <= 4 * np.abs(twin - exact)[finite].max(initial=0) + \
        16 * np.finfo(np.float32).eps
    sure = finite & (np.abs(display - 0.5) > 0.5 + 1e-3)
    assert np.array_equal(kernel[sure], twin[sure])
