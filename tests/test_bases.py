"""relight's bases (hsh.fit, rbf.fit, bilinear.fit): kernels against their NumPy twins, numerical stability on
hard light sets and texels, saving, the web layout, synthesis and the representation bench."""
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
from btforge.plugins.bases.fit import RIDGE, least_squares, project_numpy, project_opencl
from btforge.plugins.bases.lightfuncs import bilinear_weights, octa_directions, rbf_weights
from btforge.plugins.bases.model import LightTableModel, evaluate_numpy, evaluate_opencl

sys.path.insert(0, str(Path(__file__).parent))
from test_web_export import capture  # noqa: E402

FITS = [("hsh.fit", {"planes": 12}), ("hsh.fit", {}), ("hsh.fit", {"colorspace": "ycc"}),
        ("rbf.fit", {}), ("rbf.fit", {"colorspace": "ycc", "planes": 12}),
        ("rbf.fit", {"sigma": 0.125, "table": "responses", "coefficients": "projection"}),
        ("bilinear.fit", {}), ("bilinear.fit", {"resolution": 6, "resampling": "smooth", "space": "srgb"}),
        ("bilinear.fit", {"colorspace": "ycc", "planes": 12, "resolution": 0}),
        ("bilinear.fit", {"colorspace": "ycc", "planes": 0}),
        ("bilinear.fit", {"resolution": 8, "resampling": "relight"})]


def fitted(stage, params, stack=None):
    return btforge.stage(stage)(stack=stack if stack is not None else capture(n=40, size=(12, 10)), **params)["model"]


def display(model, lights):
    return linear_to_srgb(model.evaluate(np.asarray(lights, np.float64))[0])


# ----------------------------------------------------------------------------------------------- kernels


def test_projection_kernel_matches_its_twin_on_random_and_hard_samples():
    rng = np.random.default_rng(0)
    n_light, n_texel, n_plane = 37, 301, 11
    proj = rng.normal(0, 1, (n_plane, n_light, 3))
    offset = rng.normal(0, 1, n_plane)
    hard = np.zeros((n_light, 3, 3), np.uint8)  # black, saturated, and alternating texels
    hard[:, 1] = 255
    hard[::2, 2] = 255
    samples = np.concatenate([rng.integers(0, 256, (n_light, n_texel - 3, 3)), hard], axis=1).astype(np.uint8)
    # bytes: the kernel multiplies bytes by proj / 255; float32 sums of 3 L terms of size <= 255 |proj|
    want = project_numpy(samples.astype(np.float64), proj / 255.0, offset)
    got = project_opencl(samples, proj / 255.0, offset)
    bound = 1e-5 * (np.abs(proj).sum(axis=(1, 2)) + np.abs(offset))
    assert np.all(np.abs(got - want) <= bound)
    floats = (rng.normal(0, 10, (n_light, n_texel, 3)) * (rng.random((1, n_texel, 1)) < 0.5)).astype(np.float32)
    want = project_numpy(floats, proj, offset)
    got = project_opencl(floats, proj, offset)
    bound = 1e-5 * (np.einsum("ltk,plk->tp", np.abs(floats), np.abs(proj)) + np.abs(offset))
    assert np.all(np.abs(got - want) <= bound)


def test_evaluation_kernel_matches_its_twin_on_random_and_hard_coefficients():
    rng = np.random.default_rng(1)
    n_texel, n_plane, n_light = 257, 13, 9
    coeffs = rng.normal(0, 2, (n_texel, n_plane)).astype(np.float32)
    coeffs[:5] = 0.0                                      # the mean alone
    coeffs[5:10] *= 1e3                                   # far outside [0, 1]: clipped both ways
    lw = rng.normal(0, 0.3, (n_light, n_plane + 1, 3)).astype(np.float32)
    lw[:, 0] = rng.uniform(-0.2, 1.2, (n_light, 3))       # means below 0 and above 1 as well
    want = evaluate_numpy(coeffs, lw)
    got = evaluate_opencl(coeffs, lw)
    # float32 sums of P terms (relative 1e-6 of the sum of magnitudes), through the sRGB curve (slope <= 2.4, the
    # kernel's 4097-point table within 1e-7 of it)
    magnitude = np.abs(lw[:, None, 0]) + np.einsum("tp,lpk->ltk", np.abs(coeffs), np.abs(lw[:, 1:]))
    assert np.all(np.abs(got - want) <= 2.4 * 2e-6 * magnitude + 1e-6)
    assert got.min() >= 0.0 and got.max() <= 1.0


@pytest.mark.parametrize("stage,params", FITS)
def test_fits_evaluate_the_same_on_opencl_and_numpy(stage, params):
    model = fitted(stage, params)
    lights = capture(n=7, seed=3).lights
    np.testing.assert_allclose(model.evaluate(lights), model.evaluate(lights, engine="numpy"), atol=2e-5)
    texels = model.evaluate_texels(np.array([0, 3, 11]), np.array([0, 7, 9]), lights[:3])
    full = model.evaluate(lights[:3])[0]
    np.testing.assert_allclose(texels, full[[0, 1, 2], [0, 3, 11], [0, 7, 9]], atol=2e-5)


# ----------------------------------------------------------------------------------------------- correctness


@pytest.mark.parametrize("stage,params", FITS)
def test_fits_reproduce_a_smooth_capture(stage, params):
    stack = capture(n=60, size=(12, 10), seed=2)
    model = fitted(stage, params, stack)
    error = display(model, stack.lights) - stack.samples[0] / 255.0
    psnr = -10 * np.log10(np.mean(error ** 2))
    floor = 24 if params.get("planes") == 12 and stage == "hsh.fit" else 27  # order-2 HSH is coarse on n . l
    assert psnr > floor, psnr


def test_hsh_fit_recovers_exact_hsh_coefficients():
    from btforge.plugins.web.hsh import hsh_basis
    rng = np.random.default_rng(4)
    stack = capture(n=50, size=(5, 4), seed=5, encoding="linear")
    truth = rng.normal(0, 0.05, (5, 4, 3, 9)) + np.array([1.2] + [0.0] * 8)
    display_values = np.einsum("hwck,lk->lhwc", truth, hsh_basis(stack.lights, 9))
    from btforge.buffers import srgb_to_linear
    exact = SampleStack(srgb_to_linear(np.clip(display_values, 0, 1)).astype(np.float32)[None], stack.lights,
                        [[0, 0, 1]])
    model = fitted("hsh.fit", {}, exact)
    np.testing.assert_allclose(model.coeffs.reshape(5, 4, 9, 3).transpose(0, 1, 3, 2), truth, atol=2e-3)


def test_rbf_weights_stay_finite_far_from_every_light_and_bilinear_weights_sum_to_one():
    lights = np.array([[0, 0, 1.0], [0.1, 0, 0.995]])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    far = np.array([[0, 0, -1.0], [1.0, 0, 0]])
    w = rbf_weights(far, lights, 0.01)        # every exp(-d^2 / sigma^2) underflows
    assert np.isfinite(w).all() and np.allclose(w.sum(axis=1), 1)
    grid = octa_directions(7)
    assert np.allclose(np.linalg.norm(grid, axis=1), 1) and grid[:, 2].min() >= 0
    b = bilinear_weights(np.vstack([grid, far, [[0.6, 0.8, 0.0]]]), 7)
    assert np.allclose(b.sum(axis=1), 1) and b.min() >= 0
    assert np.allclose(b[:49], np.eye(49), atol=1e-9)  # a node's own direction weighs only that node


# ----------------------------------------------------------------------------------------------- hard cases


def light_sets():
    def unit(v):
        v = np.asarray(v, np.float64)
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    few = st.integers(3, 8).flatmap(lambda n: st.lists(st.tuples(st.floats(-0.9, 0.9), st.floats(-0.9, 0.9)),
                                                      min_size=n, max_size=n))
    few = few.map(lambda xy: unit([[x, y, 1.0] for x, y in xy]))
    clustered = st.tuples(st.integers(10, 30), st.floats(0, 6.28), st.floats(0.3, 1.4), st.integers(0, 99)).map(
        lambda a: unit(np.array([np.cos(a[1]) * np.sin(a[2]), np.sin(a[1]) * np.sin(a[2]), np.cos(a[2])])
                       + np.random.default_rng(a[3]).normal(0, 0.02, (a[0], 3))))
    grazing = st.tuples(st.integers(10, 40), st.floats(0.005, 0.09), st.integers(0, 99)).map(
        lambda a: unit(np.stack([np.cos(np.linspace(0, 6.2, a[0])), np.sin(np.linspace(0, 6.2, a[0])),
                                 np.full(a[0], a[1]) + np.random.default_rng(a[2]).uniform(0, 0.02, a[0])], 1)))
    return st.one_of(few, clustered, grazing)


def hard_stack(lights, seed):
    """3 x 4 texels: mixtures of two random light responses (so six principal components hold every texel),
    and a black, a saturated and a flickering texel."""
    rng = np.random.default_rng(seed)
    patterns = rng.uniform(0, 0.5, (2, len(lights), 1, 1, 3))
    mix = rng.uniform(0, 1, (2, 1, 3, 4, 1))
    samples = np.rint(255 * (mix * patterns).sum(axis=0))[None].astype(np.uint8)
    samples[0, :, 0, 0] = 0        # black texel
    samples[0, :, 0, 1] = 255      # saturated texel
    samples[0, :, 0, 2] = 255 * (np.arange(len(lights)) % 2)[:, None]   # flickering texel
    return SampleStack(samples, lights, [[0, 0, 1]], encoding="srgb8")


HARD_FITS = [("hsh.fit", {}), ("hsh.fit", {"colorspace": "ycc"}), ("rbf.fit", {"planes": 6}),
             ("rbf.fit", {"planes": 6, "table": "responses", "coefficients": "projection", "sigma": 0.125}),
             ("bilinear.fit", {"planes": 6, "resolution": 4}), ("bilinear.fit", {"planes": 6, "resolution": 0}),
             ("bilinear.fit", {"planes": 6, "resolution": 0, "resampling": "smooth"}),
             ("bilinear.fit", {"planes": 6, "resolution": 8, "resampling": "relight"}),
             ("bilinear.fit", {"planes": 0}), ("bilinear.fit", {"planes": 0, "colorspace": "ycc"})]


@pytest.mark.parametrize("stage,params", HARD_FITS)
@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lights=light_sets(), seed=st.integers(0, 1000))
def test_hard_light_sets_and_texels_give_finite_bounded_correct_models(stage, params, lights, seed):
    stack = hard_stack(lights, seed)
    if stage != "hsh.fit" and params["planes"] > 3 * len(lights):
        params = {**params, "planes": 3}
    model = btforge.stage(stage)(stack=stack, **params)["model"]
    assert np.isfinite(model.coeffs).all() and np.isfinite(model.table).all()
    # the ridge bounds every coefficient vector by |y - g0| / (2 RIDGE s_max) <= sqrt(3 L) / (2 RIDGE s_max)
    lw = model.light_weights(lights).astype(np.float64)
    s_max = np.linalg.svd(lw[:, 1:].transpose(0, 2, 1).reshape(-1, model.n_plane), compute_uv=False)[0]
    # (relight's projection, bilinear's default, is no least-squares fit: its coefficients are the resampled grid's,
    # which a spline extrapolates far from a tight cluster of lights - see docs/guide/limitations.md)
    if params.get("coefficients", "projection" if stage == "bilinear.fit" else "lsq") != "projection":
        bound = (np.sqrt(3 * len(lights)) * (1 + np.abs(lw[:, 0]).max())) / (2 * RIDGE * s_max)
        assert np.linalg.norm(model.coeffs, axis=2).max() <= bound * 1.001
    probe = np.vstack([lights, [[0, 0, 1.0], [1.0, 0, 0], [0, -1.0, 0], [0.6, 0, -0.8]]])
    relit = model.evaluate(probe)
    assert np.isfinite(relit).all() and relit.min() >= 0 and relit.max() <= 1
    # correct: the black texel stays dark and the saturated one bright at the capture's lights
    at_lights = display(model, lights)
    assert at_lights[:, 0, 0].mean() < 0.05 and at_lights[:, 0, 1].mean() > 0.95


# ----------------------------------------------------------------------------------------------- files


@pytest.mark.parametrize("stage,params", FITS)
def test_model_files_round_trip_exactly(tmp_path, stage, params):
    model = fitted(stage, params)
    btforge.stage("models.write")(model=model, path=str(tmp_path / "m.btfm"))
    back = btforge.stage("models.read")(path=str(tmp_path / "m.btfm"))["model"]
    assert isinstance(back, LightTableModel) and back.content_key == model.content_key
    for name in ("coeffs", "table", "table_lights"):
        assert np.array_equal(getattr(back, name), getattr(model, name))
    assert (back.kind, back.colorspace, back.sigma, back.resolution, back.yccplanes) == \
        (model.kind, model.colorspace, model.sigma, model.resolution, model.yccplanes)


@pytest.mark.parametrize("stage,params", FITS)
def test_web_layout_round_trips_to_8_bits(tmp_path, stage, params):
    import json
    model = fitted(stage, params)
    btforge.stage("web.export")(model=model, dir=str(tmp_path / "web"))
    info = json.loads((tmp_path / "web" / "info.json").read_text())
    assert info["type"] == {"hsh.fit": "hsh", "rbf.fit": "rbf", "bilinear.fit": "bilinear"}[stage]
    back = btforge.stage("web.read")(path=str(tmp_path / "web"))["model"]
    lights = capture(n=25, seed=6).lights
    assert back.space == model.space
    # in the space the planes hold (display values, or linear radiance for a linear fit)
    shown = display if model.space == "srgb" else lambda m, l: m.evaluate(np.asarray(l, np.float64))[0]
    diff = np.abs(shown(back, lights) - shown(model, lights))
    # planes and basis are 8-bit: a relit value moves by a few half-steps of 1/255 at most, far less on average
    assert diff.max() <= 4 / 255 and diff.mean() <= 0.6 / 255


def test_web_read_refuses_a_damaged_basis(tmp_path):
    import json
    model = fitted("rbf.fit", {})
    btforge.stage("web.export")(model=model, dir=str(tmp_path / "web"))
    info = json.loads((tmp_path / "web" / "info.json").read_text())
    info["basis"] = info["basis"][:-3]
    (tmp_path / "web" / "info.json").write_text(json.dumps(info))
    with pytest.raises(BtforgeInputError, match="basis"):
        btforge.stage("web.read")(path=str(tmp_path / "web"))


# ----------------------------------------------------------------------------------------------- bad input, bench


def test_bad_parameters_are_refused_with_the_reason():
    stack = capture(n=12, size=(4, 4))
    with pytest.raises(BtforgeInputError, match="12 or 27"):
        btforge.stage("hsh.fit")(stack=stack, planes=15)
    with pytest.raises(BtforgeInputError, match="planes"):
        btforge.stage("rbf.fit")(stack=stack, planes=40)
    with pytest.raises(BtforgeInputError, match="yplanes"):
        btforge.stage("rbf.fit")(stack=stack, planes=9, colorspace="ycc", yplanes=4)
    with pytest.raises(BtforgeInputError, match="resolution"):
        btforge.stage("bilinear.fit")(stack=stack, resolution=1)


def test_synthesis_takes_a_fitted_basis_as_exemplar():
    from btforge.context import StageContext
    from btforge.plugins.synth import materialize
    from btforge.plugins.synth.quilting import quilt
    model = fitted("rbf.fit", {}, capture(n=30, size=(24, 24), seed=7))
    coords = quilt(ctx=StageContext(node="quilt"), exemplar=model, size=[40, 40], seam="cut", seed=1, block=8,
                   overlap=2)["coords"]
    out = materialize(coords=coords, source=model)["output"]
    assert isinstance(out, LightTableModel) and (out.height, out.width) == (40, 40)
    lights = capture(n=4, seed=8).lights
    rows, cols = coords.coords[..., 0], coords.coords[..., 1]
    np.testing.assert_allclose(out.evaluate(lights), model.evaluate(lights)[:, :, rows, cols], atol=1e-6)


def test_automatic_choices_survive_lights_too_few_for_the_held_out_split():
    stack = capture(n=10, size=(6, 6))   # 8 lights left when two are held out: too few for 27 planes
    assert fitted("rbf.fit", {"planes": 27}, stack).n_plane == 27
    model = fitted("bilinear.fit", {"planes": 27, "colorspace": "ycc", "yplanes": 9}, stack)
    assert model.n_plane == 27 and model.resolution >= 3


def test_a_graph_with_bad_parameters_names_every_problem_before_running(tmp_path, capsys):
    from btforge.cli import main
    lights = Path(__file__).resolve().parents[1] / "graphs" / "data" / "icon_san_michele" / "dirs.lp"
    graph = tmp_path / "bad.yaml"
    graph.write_text(f"""nodes:
  read: {{stage: stackio.read, params: {{path: {lights}}}}}
  hsh:  {{stage: hsh.fit, params: {{planes: 15}}, inputs: {{stack: read.stack}}}}
  rbf:  {{stage: rbf.fit, params: {{colorspace: ycc, planes: 9, yplanes: 4}}, inputs: {{stack: read.stack}}}}
  grid: {{stage: bilinear.fit, params: {{resolution: 1}}, inputs: {{stack: read.stack}}}}
""")
    assert main(["run", str(graph), "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache")]) == 2
    err = capsys.readouterr().err
    assert "3 problems" in err and "line 3, node 'hsh'" in err and "yplanes" in err and "line 5" in err
    assert "Traceback" not in err


@pytest.mark.parametrize("stage,params", FITS[::2])
def test_renders_like_relight_on_the_plane_and_refuses_bad_lookups(stage, params):
    from test_render import draw, plane_scene
    model = fitted(stage, params)
    light = np.array([[-0.4, 0.5, 0.7]]) / np.linalg.norm([-0.4, 0.5, 0.7])
    image, _ = draw(plane_scene(model.width, model.height,
                                lights=[{"type": "directional", "direction": light[0].tolist(), "intensity": 1.0}]),
                    {"stone": model})
    np.testing.assert_allclose(image, model.evaluate(light)[0, 0], rtol=2e-4, atol=2e-5)
    with pytest.raises(BtforgeInputError, match="inside the"):
        model.evaluate_texels(np.array([model.height]), np.array([0]), np.array([[0, 0, 1.0]]))
    with pytest.raises(BtforgeInputError, match=r"lights \[N, 3\]"):
        model.evaluate_texels(np.array([0, 1]), np.array([0, 1]), np.array([[0, 0, 1.0]]))


def test_the_representation_bench_sweeps_the_new_fits():
    from btforge.registry import default_registry
    names = {s.name for s in default_registry().stages_with_role("fit")}
    assert {"hsh.fit", "rbf.fit", "bilinear.fit"} <= names
    assert not least_squares(np.zeros((4, 3, 3)))[2]["rank"]  # an all-zero basis: rank 0, no division by zero


def grid_shaded_capture(side: int, n_light: int = 150, seed: int = 0) -> SampleStack:
    """An 8-bit capture whose every texel's display values are a bilinear function on a ``side x side`` grid
    of light directions (random node values, so its kinks are where that grid's lines are)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.1, 1, n_light)
    phi = rng.uniform(0, 2 * np.pi, n_light)
    lights = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    nodes = rng.uniform(0.1, 0.9, (2, side * side, 3))                 # two patterns over the grid's nodes
    mix = rng.uniform(0, 1, (6, 6, 1, 1))
    response = bilinear_weights(lights, side) @ nodes                   # [2, L, 3]
    display_values = mix * response[0] + (1 - mix) * response[1]        # [h, w, L, 3]
    samples = np.round(np.moveaxis(display_values, 2, 0) * 255).astype(np.uint8)
    return SampleStack(samples[None], lights, [[0, 0, 1]], encoding="srgb8")


@pytest.mark.parametrize("side", range(4, 13))
def test_resolution_auto_finds_the_grid_side_of_a_response_built_on_that_grid(side):
    # every side is a candidate: a capture's held-out error can jump by dB from one side to the next
    model = fitted("bilinear.fit", {"planes": 6, "resolution": 0, "resampling": "smooth", "space": "srgb"},
                   grid_shaded_capture(side))
    assert model.resolution == side
