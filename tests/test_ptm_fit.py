"""PTM fit and evaluation: OpenCL kernels against NumPy, exact recovery, and hard light sets."""
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btforge import BtforgeInputError, BtforgeWarning
from btforge.buffers import SampleStack
from btforge.plugins.ptm.model import (PTMModel, evaluate_ptm_numpy, evaluate_ptm_opencl, fit_ptm, ptm_solver,
                                      ptm_terms)

from lightsets import dome, lights_at

FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def stack_of(samples, lights, encoding="linear"):
    return SampleStack(samples, lights, [[0, 0, 1]], encoding=encoding)


def relative_error(a, b):
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12))


@pytest.mark.parametrize("variant", ["rgb", "lrgb"])
@pytest.mark.parametrize("encoding,space", [("linear", "linear"), ("srgb8", "srgb"), ("srgb8", "linear"), ("linear", "srgb")])
def test_opencl_fit_matches_numpy(variant, encoding, space):
    rng = np.random.default_rng(3)
    lights = dome(24)
    if encoding == "linear":
        samples = rng.uniform(0, 1.5, (1, 24, 19, 23, 3)).astype(np.float32)
    else:
        samples = rng.integers(0, 256, (1, 24, 19, 23, 3), dtype=np.uint8)
    s = stack_of(samples, lights, encoding)
    gpu, _ = fit_ptm(s, variant, space)
    ref, _ = fit_ptm(s, variant, space, engine="numpy")
    assert relative_error(gpu.coeffs, ref.coeffs) < 1e-4
    if variant == "lrgb":
        assert relative_error(gpu.albedo, ref.albedo) < 1e-4


def test_fit_equals_independent_least_squares():
    rng = np.random.default_rng(5)
    lights = dome(30, seed=5)
    samples = rng.uniform(0, 1, (1, 30, 6, 7, 3)).astype(np.float32)
    model, _ = fit_ptm(stack_of(samples, lights), "rgb", ridge=0.0)
    design = ptm_terms(lights)
    target = samples[0].reshape(30, -1).astype(np.float64)
    solution, *_ = np.linalg.lstsq(design, target, rcond=None)          # [6, H*W*C]
    expected = solution.reshape(6, 6, 7, 3).transpose(1, 2, 3, 0)
    assert relative_error(model.coeffs, expected.astype(np.float32)) < 1e-4


def test_fit_streams_in_bands_with_identical_result():
    rng = np.random.default_rng(8)
    s = stack_of(rng.uniform(0, 1, (1, 16, 40, 9, 3)).astype(np.float32), dome(16, 8))
    whole, _ = fit_ptm(s, "rgb", "srgb")  # a linear stack fitted in display space goes band by band
    banded, _ = fit_ptm(s, "rgb", "srgb", budget_bytes=16 * 9 * 3 * 8 * 27)  # three rows per band
    assert banded.coeffs.shape == whole.coeffs.shape
    # Exact by construction: each texel's sums run inside its own work-item, over the lights in one fixed order,
    # whatever the band; no host BLAS (whose order may follow the matrix width) touches them.
    np.testing.assert_array_equal(whole.coeffs, banded.coeffs)


@pytest.mark.parametrize("variant", ["rgb", "lrgb"])
def test_data_generated_by_a_ptm_is_recovered(variant):
    rng = np.random.default_rng(11)
    lights = dome(20, 11, min_el=20)
    coeffs = rng.normal(0, 0.1, (8, 9, 1 if variant == "lrgb" else 3, 6)).astype(np.float32)
    coeffs[..., 5] += 1.0  # keep the generated radiance positive (evaluation clips negatives)
    albedo = rng.uniform(0.2, 1.0, (8, 9, 3 if variant == "lrgb" else 0)).astype(np.float32)
    truth = PTMModel(coeffs, albedo, variant, "linear")
    flat = coeffs.reshape(-1, coeffs.shape[2], 6)
    values = ptm_terms(lights) @ flat.reshape(-1, 6).T  # [L, N*K]
    values = values.reshape(20, 8, 9, -1)
    samples = (albedo[None] * values if variant == "lrgb" else values).astype(np.float32)
    model, _ = fit_ptm(stack_of(samples[None], lights), variant)
    assert relative_error(model.evaluate(lights, engine="numpy")[0], samples) < 1e-4
    if variant == "rgb":
        assert relative_error(model.coeffs, truth.coeffs) < 1e-3


def test_fewer_than_six_lights_is_a_clear_error():
    s = stack_of(np.zeros((1, 5, 2, 2, 3), np.float32), dome(5))
    with pytest.raises(BtforgeInputError, match="at least 6 lights"):
        fit_ptm(s, "rgb")


def test_multi_view_stack_is_refused():
    s = SampleStack(np.zeros((2, 8, 2, 2, 3), np.float32), dome(8), [[0, 0, 1], [0.5, 0, 0.8]])
    with pytest.raises(BtforgeInputError, match="single-view"):
        fit_ptm(s, "rgb")


@pytest.mark.parametrize("name,lights", [
    ("one elevation", lights_at(np.full(12, 40.0), np.linspace(0, 330, 12))),
    ("clustered within 3 degrees", lights_at(60 + np.random.default_rng(1).uniform(-1.5, 1.5, 12),
                                             120 + np.random.default_rng(2).uniform(-1.5, 1.5, 12))),
    ("grazing 80-89 degrees from zenith", lights_at(np.random.default_rng(3).uniform(1, 10, 12),
                                                    np.random.default_rng(4).uniform(0, 360, 12))),
])
def test_ill_conditioned_lights_warn_and_stay_bounded(name, lights):
    import btforge
    rng = np.random.default_rng(0)
    samples = rng.uniform(0, 1, (1, len(lights), 5, 5, 3)).astype(np.float32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model = btforge.stage("ptm.fit")(stack=stack_of(samples, lights))["model"]
    messages = [str(w.message) for w in caught if issubclass(w.category, BtforgeWarning)]
    assert any("condition number" in m for m in messages), name
    assert np.isfinite(model.coeffs).all()
    relit = model.evaluate(lights)
    assert np.isfinite(relit).all() and relit.max() < 10  # bounded at the measured lights
    # and elsewhere: noise along a direction the lights barely span is not amplified by 1 / rcond (a 3-degree
    # cluster still extrapolates its slopes, so it gets a looser bound)
    elsewhere = model.evaluate(dome(40, 3, min_el=5))
    assert np.isfinite(elsewhere).all() and elsewhere.max() < (30 if name.startswith("clustered") else 3), name


@FAST
@given(
    n_light=st.integers(6, 40),
    kind=st.sampled_from(["black", "constant", "saturated", "noise", "exact-six"]),
    seed=st.integers(0, 2**16),
    variant=st.sampled_from(["rgb", "lrgb"]),
)
def test_fit_is_finite_and_bounded_on_hard_texels(n_light, kind, seed, variant):
    rng = np.random.default_rng(seed)
    if kind == "exact-six":
        n_light = 6
    lights = dome(n_light, seed, min_el=5)
    shape = (1, n_light, 3, 4, 3)
    samples = {"black": np.zeros(shape), "constant": np.full(shape, 0.37), "saturated": np.ones(shape),
               "noise": rng.uniform(0, 1, shape), "exact-six": rng.uniform(0, 1, shape)}[kind].astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BtforgeWarning)
        # plain least squares (ridge 0), whose answer is exact; the ridge is tested in test_ridge_loo.py
        model, _ = fit_ptm(stack_of(samples, lights), variant, ridge=0.0)
        ref, _ = fit_ptm(stack_of(samples, lights), variant, engine="numpy", ridge=0.0)
    assert np.isfinite(model.coeffs).all() and np.isfinite(model.albedo).all()
    assert np.allclose(model.coeffs, ref.coeffs, rtol=1e-4, atol=1e-5)
    relit = model.evaluate(lights)[0]
    assert np.isfinite(relit).all()
    if kind in ("black", "constant", "saturated"):  # these have an exact answer ...
        solver = ptm_solver(lights)
        expected = samples[0]
        if solver.clamped:  # ... unless the light set is too ill-conditioned: then that of the regularised fit,
            # the samples projected onto the singular directions that were kept
            projection = solver.design.astype(np.float64) @ solver.solve.astype(np.float64)
            expected = np.maximum(np.einsum("lm,mhwc->lhwc", projection, samples[0]), 0)
        np.testing.assert_allclose(relit, expected, atol=1e-4)


@FAST
@given(seed=st.integers(0, 2**16), variant=st.sampled_from(["rgb", "lrgb"]), space=st.sampled_from(["linear", "srgb"]),
       magnitude=st.sampled_from([1e-3, 1.0, 50.0]))
def test_opencl_evaluation_matches_numpy(seed, variant, space, magnitude):
    rng = np.random.default_rng(seed)
    n = 57
    k = 1 if variant == "lrgb" else 3
    coeffs = (rng.normal(0, 1, (n, k, 6)) * magnitude).astype(np.float32)
    albedo = rng.uniform(0, 1, (n, 3 if variant == "lrgb" else 0)).astype(np.float32)
    lights = np.vstack([dome(9, seed, min_el=0), [[0, 0, 1], [1, 0, 0]]]).astype(np.float32)
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    a = evaluate_ptm_opencl(coeffs, albedo, lights, variant, space)
    b = evaluate_ptm_numpy(coeffs, albedo, lights, variant, space)
    assert np.isfinite(a).all() and (a >= 0).all()
    np.testing.assert_allclose(a, b, rtol=2e-5, atol=2e-5 * magnitude)


def test_kernels_are_built_once_per_context():
    from btforge.backend import get_backend
    s = stack_of(np.random.default_rng(0).uniform(0, 1, (1, 8, 3, 3, 3)).astype(np.float32), dome(8))
    fit_ptm(s, "rgb")[0].evaluate(dome(3))
    before = get_backend().builds
    fit_ptm(s, "rgb")[0].evaluate(dome(3))
    assert get_backend().builds == before


@pytest.mark.parametrize("engine", ["opencl", "numpy"])
def test_lrgb_colour_of_sparse_highlights_stays_non_negative_and_writable(engine, tmp_path):
    from btforge.plugins.ptm.ptmfile import write_ptm
    lights = dome(12, 5)
    samples = np.zeros((1, 12, 1, 1, 3), np.float32)
    samples[0, :, 0, 0, 1] = lights[:, 0] > 0.3     # green lit from +x only: the fitted mean dips below 0 ...
    samples[0, 0, 0, 0, 0] = 0.05                   # ... at light 0, where red has a faint highlight
    model, _ = fit_ptm(stack_of(samples, lights), "lrgb", engine=engine)
    assert model.albedo.min() >= 0.0 and model.albedo.max() <= 1.0
    write_ptm(tmp_path / "sparse.ptm", "lrgb", model.coeffs, model.albedo)


def test_auto_space_follows_held_out_lights():
    from btforge.buffers import linear_to_srgb8
    lights = dome(30, 2, min_el=10)
    rng = np.random.default_rng(1)
    normals = rng.normal([0, 0, 1], 0.3, (8, 8, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    radiance = 0.8 * np.maximum(np.einsum("hwi,li->lhw", normals, lights), 0)[..., None] * [1.0, 0.7, 0.5]
    lambert = stack_of(linear_to_srgb8(radiance)[None], lights, "srgb8")
    assert fit_ptm(lambert, "rgb", "auto")[0].space == "linear"       # shading is linear in radiance
    display = 0.3 + 0.4 * lights[:, 0, None, None, None] ** 2 + 0.1 * lights[:, 1, None, None, None]
    poly = stack_of(np.rint(np.broadcast_to(display, radiance.shape) * 255).astype(np.uint8)[None], lights, "srgb8")
    assert fit_ptm(poly, "rgb", "auto")[0].space == "srgb"            # display values that are a polynomial
    assert fit_ptm(stack_of(radiance[None].astype(np.float32), lights), "rgb", "auto")[0].space == "linear"


def test_auto_space_picks_linear_on_a_rendered_capture_and_srgb_on_real_ones(shared_data):
    from btforge.plugins.relight import compare_stacks
    from btforge.plugins.stackio.images import load_stack
    root = shared_data / "rti" / "synthrti" / "Single_Object1" / "material1"

    def centre(stack, size=64):
        r0, c0 = (stack.height - size) // 2, (stack.width - size) // 2
        return SampleStack(stack.samples[:, :, r0:r0 + size, c0:c0 + size], stack.lights, stack.views,
                           stack.channels, stack.encoding)
    fit, test = centre(load_stack(root / "Dome" / "dirs.lp")), centre(load_stack(root / "Test" / "dirs.lp"))
    scores = {}
    for space in ("linear", "srgb", "auto"):
        model, _ = fit_ptm(fit, "rgb", space)
        relit = SampleStack(model.evaluate(test.lights), test.lights, test.views, model.channels)
        scores[space if space != "auto" else "auto=" + model.space] = compare_stacks(relit, test)["psnr_db"]
    assert "auto=linear" in scores and scores["linear"] > scores["srgb"] + 2.0, scores
    real = centre(load_stack(shared_data / "rti" / "realrti" / "item6" / "dirs.lp"))
    assert fit_ptm(real, "rgb", "auto")[0].space == "srgb"
