"""Double spherical harmonics: basis, constrained least squares (OpenCL vs NumPy), quantization, hard inputs."""
import math
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import btforge
from btforge import BtforgeInputError, BtforgeWarning
from btforge.buffers import SampleStack, linear_to_srgb8
from btforge.context import StageContext
from btforge.plugins.sh.model import (ENERGY_SLACK, RCOND, SHModel, cls_coeffs_numpy, cls_coeffs_opencl, compression_rate,
                                      evaluate_sh_numpy, evaluate_sh_opencl, evaluate_sh_scattered_numpy,
                                      evaluate_sh_scattered_opencl, fit_sh, quantize_coeffs, real_sh, sh_solver)
from tolerances import summation_order_tolerance

FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FOUR_PI = 4 * math.pi


def lights_at(elevations_deg, azimuths_deg):
    el, az = np.radians(elevations_deg), np.radians(azimuths_deg)
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def hemisphere(n, min_z=0.0):
    """Fibonacci points uniform in solid angle over the cap z > min_z."""
    i = np.arange(n) + 0.5
    z = 1 - (1 - min_z) * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def sphere_quadrature(n):
    """Gauss-Legendre in z times uniform azimuth: exact for polynomials of degree < 2n on the sphere."""
    z, wz = np.polynomial.legendre.leggauss(n)
    phi = np.arange(2 * n) * math.pi / n
    zz, pp = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1 - zz ** 2)
    dirs = np.column_stack([(r * np.cos(pp)).ravel(), (r * np.sin(pp)).ravel(), zz.ravel()])
    return dirs, (np.repeat(wz[:, None], 2 * n, axis=1) * (math.pi / n)).ravel()


def stack_of(samples, lights, views=((0.0, 0.0, 1.0),)):
    return SampleStack(np.ascontiguousarray(samples, np.float32), np.asarray(lights), np.asarray(views))


def model_of(coeffs, light_order, view_order=1):
    k_v, k_l = view_order ** 2, light_order ** 2
    return SHModel(coeffs.astype(np.float32), np.ones((k_v, k_l), np.float32), np.zeros((k_v, k_l), np.float32),
                   light_order, view_order, False, ("R", "G", "B")[: coeffs.shape[2]])


def energy(model):
    return (model.dequantized().astype(np.float64) ** 2).sum(axis=(3, 4))            # [H, W, C]


def energy_bound(stack, factor=1.0):
    y = stack.linear().astype(np.float64)
    return factor * FOUR_PI ** 2 * (y ** 2).mean(axis=(0, 1))                       # [H, W, C]


def quiet_fit(*args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", BtforgeWarning)
        return fit_sh(*args, **kwargs)


# ----------------------------------------------------------------------------------------------- basis


def test_real_sh_is_orthonormal_on_the_sphere():
    dirs, weights = sphere_quadrature(24)
    assert abs(weights.sum() - FOUR_PI) < 1e-12
    y = real_sh(10, dirs)
    gram = (y * weights[:, None]).T @ y
    assert y.shape == (len(dirs), 100)
    np.testing.assert_allclose(gram, np.eye(100), atol=1e-10)


def test_real_sh_matches_closed_forms():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(50, 3))
    d = np.vstack([d / np.linalg.norm(d, axis=1, keepdims=True), [[0, 0, 1], [0, 0, -1], [1, 0, 0]]])
    x, y, z = d.T
    got = real_sh(3, d)
    c1 = math.sqrt(3 / FOUR_PI)
    expected = np.column_stack([
        np.full_like(x, 0.5 / math.sqrt(math.pi)),                     # Y_0^0
        c1 * y, c1 * z, c1 * x,                                        # Y_1^-1, Y_1^0, Y_1^1
        0.5 * math.sqrt(15 / math.pi) * x * y,                         # Y_2^-2
        0.5 * math.sqrt(15 / math.pi) * y * z,                         # Y_2^-1
        0.25 * math.sqrt(5 / math.pi) * (3 * z * z - 1),               # Y_2^0
        0.5 * math.sqrt(15 / math.pi) * x * z,                         # Y_2^1
        0.25 * math.sqrt(15 / math.pi) * (x * x - y * y),              # Y_2^2
    ])
    np.testing.assert_allclose(got, expected, atol=1e-12)
    # Addition theorem: sum over a band of Y^2 is (2l + 1) / (4 pi) everywhere.
    np.testing.assert_allclose((real_sh(10, d) ** 2).sum(axis=1), 100 / FOUR_PI, rtol=1e-10)


def test_compression_rate_matches_table_ii():
    assert compression_rate(25, 25, 81, 81) == 625 / 6561
    assert round(100 * compression_rate(25, 25, 81, 81), 2) == 9.53
    assert compression_rate(16, 1, 64, 1) == 0.25


# ----------------------------------------------------------------------------------------------- OpenCL vs NumPy


@pytest.mark.parametrize("light_order,view_order,n_view,n_light", [(2, 1, 1, 30), (4, 1, 1, 30), (6, 1, 1, 30),
                                                                   (3, 2, 3, 12), (2, 3, 5, 9)])
def test_opencl_fit_matches_numpy(light_order, view_order, n_view, n_light):
    rng = np.random.default_rng(light_order * 10 + view_order)
    views = hemisphere(n_view, 0.3) if n_view > 1 else [[0, 0, 1]]
    s = stack_of(rng.uniform(0, 1.5, (n_view, n_light, 9, 11, 3)), hemisphere(n_light, 0.1), views)
    gpu, gs = quiet_fit(s, light_order, view_order)
    ref, rs = quiet_fit(s, light_order, view_order, engine="numpy")
    scale = np.abs(ref.coeffs).max()
    np.testing.assert_allclose(gpu.coeffs, ref.coeffs, atol=2e-4 * scale)
    np.testing.assert_allclose(gs["lambda"], rs["lambda"], rtol=1e-3, atol=1e-7 * gs["sigma_max_sq"])
    assert (gs["lambda"] > 0).sum() == (rs["lambda"] > 0).sum()
    assert gs["clamped"] == rs["clamped"]


def test_projection_and_solve_agree_on_hard_rows():
    """Rows with zero, tiny, huge and infinite bounds through both solvers directly."""
    solver = sh_solver(hemisphere(20, 0.05), np.array([[0.0, 0, 1]]), 5, 1)
    rng = np.random.default_rng(4)
    proj = rng.normal(0, 1, (8, solver.rank)).astype(np.float32)
    proj[0] = 0
    proj[1] *= 1e-20
    proj[2] *= 1e20
    root = np.array([0, 1e-18, 1e21, np.inf, 1.0, 0.5, 30.0, 1e-3], np.float32)
    c_gpu, l_gpu = cls_coeffs_opencl(proj, root, solver)
    c_ref, l_ref = cls_coeffs_numpy(proj, root, solver)
    assert np.isfinite(c_gpu).all() and np.isfinite(l_gpu).all()
    np.testing.assert_allclose(l_gpu, l_ref, rtol=1e-3)
    for row in range(8):
        np.testing.assert_allclose(c_gpu[row], c_ref[row], atol=2e-4 * np.abs(c_ref[row]).max() + 1e-30)
    assert (c_gpu[0] == 0).all() and l_gpu[3] == 0  # nothing measured; no bound = plain least squares
    for row in (4, 5, 6, 7):  # the constrained rows meet their bound
        assert (c_gpu[row].astype(np.float64) ** 2).sum() <= root[row] ** 2 * 1.001


EVALUATION_CASES = given(seed=st.integers(0, 2 ** 16), quantized=st.booleans(),
                         magnitude=st.sampled_from([1e-3, 1.0, 50.0]), light_order=st.integers(1, 6),
                         view_order=st.integers(1, 3))


def random_coefficients(rng, k_v, k_l, magnitude, quantized, n_texel=37):
    """Random SH coefficients ``[n, 3, k_v, k_l]`` (texel 0 black), optionally 8-bit, with scale and bias."""
    coeffs = (rng.normal(0, 1, (n_texel, 3, k_v, k_l)) * magnitude).astype(np.float32)
    coeffs[0] = 0.0
    scale, bias = np.ones((k_v, k_l), np.float32), np.zeros((k_v, k_l), np.float32)
    if quantized:
        coeffs, scale, bias = quantize_coeffs(coeffs)
    return coeffs, scale, bias


@FAST
@EVALUATION_CASES
def test_opencl_evaluation_matches_numpy(seed, quantized, magnitude, light_order, view_order):
    rng = np.random.default_rng(seed)
    k_v, k_l = view_order ** 2, light_order ** 2
    coeffs, scale, bias = random_coefficients(rng, k_v, k_l, magnitude, quantized)
    dirs = rng.normal(size=(7, 3))  # includes directions below the horizon
    dirs = np.vstack([dirs / np.linalg.norm(dirs, axis=1, keepdims=True), [[0, 0, 1], [1, 0, 0]]])
    yl = real_sh(light_order, dirs).astype(np.float32)
    yv = real_sh(view_order, dirs[:3]).astype(np.float32)
    a = evaluate_sh_opencl(coeffs, scale, bias, quantized, yv, yl)
    b = evaluate_sh_numpy(coeffs, scale, bias, quantized, yv, yl)
    assert a.shape == (3, 9, 37, 3) and np.isfinite(a).all() and (a >= 0).all()
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * magnitude * k_v * k_l)


@FAST
@EVALUATION_CASES
def test_opencl_scattered_evaluation_matches_numpy(seed, quantized, magnitude, light_order, view_order):
    rng = np.random.default_rng(seed)
    k_v, k_l = view_order ** 2, light_order ** 2
    coeffs, scale, bias = random_coefficients(rng, k_v, k_l, magnitude, quantized)
    n = 150
    texels = rng.integers(0, 37, n).astype(np.int32)
    dirs = rng.normal(size=(2 * n, 3))                               # each item its own light and view, any side
    dirs[:4] = [[0, 0, 1], [1, 0, 0], [0, 0, -1], [0.999, 0, 0.0447]]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    yl = real_sh(light_order, dirs[:n]).astype(np.float32)
    yv = real_sh(view_order, dirs[n:]).astype(np.float32)
    a = evaluate_sh_scattered_opencl(coeffs, scale, bias, quantized, texels, yv, yl)
    b = evaluate_sh_scattered_numpy(coeffs, scale, bias, quantized, texels, yv, yl)
    assert a.shape == (n, 3) and np.isfinite(a).all() and (a >= 0).all()
    np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * magnitude * k_v * k_l)


# ----------------------------------------------------------------------------------------------- fitting


def test_data_generated_by_sh_is_recovered():
    rng = np.random.default_rng(11)
    lights = hemisphere(60, 0.05)
    coeffs = rng.normal(0, 0.05, (7, 8, 3, 1, 9))
    coeffs[..., 0, 0] += 2.0   # constant
    coeffs[..., 0, 2] += 1.0   # + z: brighter toward the zenith, and energy mostly above the horizon
    truth = model_of(coeffs, 3)
    samples = truth.evaluate(lights, engine="numpy")
    assert samples.min() > 0  # no clipping: the samples are the SH function itself
    for engine in ("opencl", "numpy"):
        model, stats = fit_sh(stack_of(samples, lights), 3, engine=engine)
        assert stats["clamped"] == 0 and stats["lambda_max"] == 0.0  # the bound is not active: lambda -> 0
        relit = model.evaluate(lights, engine=engine)
        assert np.abs(relit - samples).max() / np.abs(samples).max() < 1e-3
        np.testing.assert_allclose(model.coeffs, truth.coeffs, atol=1e-3 * np.abs(truth.coeffs).max())


def test_constrained_fit_bounds_energy_where_plain_least_squares_blows_up():
    rng = np.random.default_rng(2)
    lights = hemisphere(40, 0.1)
    smooth = 0.3 + 0.6 * lights[:, 2]                                   # a Lambertian-like texel ...
    samples = smooth[None, :, None, None, None] + rng.normal(0, 0.05, (1, 40, 4, 5, 3))  # ... with sensor noise
    s = stack_of(samples, lights)
    bound = energy_bound(s)
    cls, stats = fit_sh(s, 6)
    plain, _ = fit_sh(s, 6, energy_factor=np.inf)
    assert (energy(cls) <= bound * (1 + ENERGY_SLACK) * 1.001).all()
    assert (energy(plain) > 10 * bound).all()
    assert stats["clamped"] == 4 * 5 * 3
    # Below the horizon: the constrained function stays within |f| <= sqrt(bound * k) / (4 pi) ...
    below = -hemisphere(30, 0.0)
    limit = np.sqrt(bound * (1 + ENERGY_SLACK) * 36) / FOUR_PI
    assert (np.abs(cls.evaluate(below)[0]) <= limit * 1.001).all()
    assert np.abs(plain.evaluate(below)[0]).max() > 5 * limit.max()
    # ... while fitting the samples about as well as the noise allows.
    residual = np.sqrt(((cls.evaluate(lights) - samples) ** 2).mean())
    assert residual < 0.06


def test_fit_streams_in_bands_with_the_same_result():
    rng = np.random.default_rng(8)
    s = stack_of(rng.uniform(0, 1, (1, 16, 40, 9, 3)), hemisphere(16, 0.1))
    whole, _ = quiet_fit(s, 3)
    banded, _ = quiet_fit(s, 3, budget_bytes=16 * 9 * 3 * 4 * 3)
    # Every texel gets the same solve, but its projection U^T y is a float32 BLAS product, and BLAS may pick its
    # summation order by the width of the product, i.e. by the band (AVX-512 builds do): bands may differ in the
    # last bits of each 16-light sum, and the solve amplifies that by at most its condition number.  A banding
    # mistake (a row fitted from another row's samples) changes coefficients by about their own size, 1000x more.
    solver = sh_solver(s.lights, s.views, 3, 1)
    condition = solver.s.max() / solver.s[solver.s > 0].min()
    tolerance = summation_order_tolerance(whole.coeffs, terms=s.n_light * s.n_view, amplification=condition)
    assert tolerance < 1e-3 * np.abs(whole.coeffs).max()
    np.testing.assert_allclose(banded.coeffs, whole.coeffs, rtol=0, atol=tolerance)


def test_srgb8_stack_is_fitted_in_linear_radiance():
    rng = np.random.default_rng(9)
    raw = rng.integers(0, 256, (1, 30, 3, 4, 3), dtype=np.uint8)
    lights = hemisphere(30, 0.1)
    # (space given: on random bytes neither space predicts held-out lights better, so auto's choice is arbitrary)
    byte_fit, _ = fit_sh(SampleStack(raw, lights, [[0, 0, 1]], encoding="srgb8"), 3, space="linear")
    linear = SampleStack(raw, lights, [[0, 0, 1]], encoding="srgb8").linear()
    float_fit, _ = fit_sh(stack_of(linear, lights), 3)
    np.testing.assert_array_equal(byte_fit.coeffs, float_fit.coeffs)


# ----------------------------------------------------------------------------------------------- quantization


def test_quantization_is_within_half_a_step():
    rng = np.random.default_rng(3)
    lights = hemisphere(30, 0.1)
    s = stack_of(rng.uniform(0, 2, (1, 30, 10, 12, 3)), lights)
    full, _ = fit_sh(s, 4)
    quant, stats = fit_sh(s, 4, quantize=True)
    assert quant.quantized and quant.coeffs.dtype == np.uint8
    assert quant.coeffs.min() == 0 and quant.coeffs.max() == 255  # range-covering
    step = quant.scale.astype(np.float64)
    error = np.abs(quant.dequantized().astype(np.float64) - full.coeffs)
    assert (error <= step / 2 * (1 + 1e-4) + 1e-6 * np.abs(full.coeffs)).all()
    assert (error.reshape(-1, 16).max(axis=0) > step.ravel() / 4).all()  # the bound is not vacuous
    # Relit error <= sum over coefficients of half a step times |Y_b(l)| (plus float rounding).
    relight_at = np.vstack([lights, hemisphere(9, 0.0)])
    bound = (step[0] / 2 * np.abs(real_sh(4, relight_at)) / math.sqrt(FOUR_PI)).sum(axis=1)  # Y_0(view) factor
    diff = np.abs(quant.evaluate(relight_at)[0] - full.evaluate(relight_at)[0])          # [L, H, W, C]
    assert (diff <= bound[:, None, None, None] * 1.001 + 1e-5).all()
    np.testing.assert_allclose(quant.evaluate(lights), quant.evaluate(lights, engine="numpy"), rtol=1e-4, atol=1e-5)


def test_quantization_of_a_constant_coefficient_is_exact():
    coeffs = np.zeros((2, 3, 1, 1, 4), np.float32)
    coeffs[..., 0, 0] = 0.7
    coeffs[..., 0, 1] = np.arange(6).reshape(2, 3, 1)
    q, scale, bias = quantize_coeffs(coeffs)
    assert (q[..., 0, 0] == 0).all() and bias[0, 0] == np.float32(0.7) and scale[0, 0] == 1.0
    np.testing.assert_allclose(q[..., 0, 1] * scale[0, 1] + bias[0, 1], coeffs[..., 0, 1], atol=1e-6)


# ----------------------------------------------------------------------------------------------- hard cases


LIGHT_SETS = {
    "few": lambda rng: hemisphere(int(rng.integers(3, 9)), 0.2),
    "clustered": lambda rng: lights_at(60 + rng.uniform(-1.5, 1.5, 12), 120 + rng.uniform(-1.5, 1.5, 12)),
    "one elevation": lambda rng: lights_at(np.full(12, 40.0), np.linspace(0, 330, 12)),
    "grazing": lambda rng: lights_at(rng.uniform(1, 10, 14), rng.uniform(0, 360, 14)),
    "dome": lambda rng: hemisphere(25, 0.1),
}


@FAST
@given(lights=st.sampled_from(sorted(LIGHT_SETS)), texels=st.sampled_from(["black", "constant", "saturated",
                                                                            "noise", "spiky"]),
       light_order=st.integers(2, 7), seed=st.integers(0, 2 ** 16))
def test_fit_is_finite_and_bounded_on_hard_inputs(lights, texels, light_order, seed):
    rng = np.random.default_rng(seed)
    dirs = LIGHT_SETS[lights](rng)
    shape = (1, len(dirs), 3, 4, 3)
    samples = {"black": np.zeros(shape), "constant": np.full(shape, 0.37), "saturated": np.ones(shape),
               "noise": rng.uniform(0, 1, shape),
               "spiky": rng.uniform(0, 1, shape) ** 8 * 1e3}[texels]
    s = stack_of(samples, dirs)
    model, stats = quiet_fit(s, light_order)
    ref, ref_stats = quiet_fit(s, light_order, engine="numpy")
    assert np.isfinite(model.coeffs).all() and np.isfinite(stats["lambda"]).all()
    scale = max(np.abs(ref.coeffs).max(), 1e-30)
    np.testing.assert_allclose(model.coeffs, ref.coeffs, atol=1e-3 * scale)
    bound = energy_bound(s) * (1 + ENERGY_SLACK)
    assert (energy(model) <= bound * 1.001 + 1e-12).all()
    # |f| <= ||c|| ||Y(l)|| = sqrt(bound) sqrt(k_l / 4 pi) / sqrt(4 pi), anywhere on the sphere.
    anywhere = np.vstack([dirs, -hemisphere(10), [[1, 0, 0]]])
    relit = model.evaluate(anywhere)[0]
    limit = np.sqrt(bound * light_order ** 2) / FOUR_PI
    assert np.isfinite(relit).all() and (relit <= limit * 1.001 + 1e-7).all()
    if texels == "black":
        assert (model.coeffs == 0).all()
    if texels in ("constant", "saturated"):  # exactly representable: recovered at the lights
        np.testing.assert_allclose(model.evaluate(dirs)[0], samples[0], rtol=1e-4)
        if lights == "dome":  # (ill-conditioned sets amplify float rounding enough to engage the bound, harmlessly)
            assert stats["clamped"] == 0


def test_fewer_samples_than_coefficients_warns_and_stays_bounded():
    lights = hemisphere(6, 0.3)
    s = stack_of(np.random.default_rng(0).uniform(0, 1, (1, 6, 2, 3, 3)), lights)
    ctx = StageContext(node="fit")
    with pytest.warns(BtforgeWarning, match="fewer samples"):
        model = btforge.stage("sh.fit")(ctx=ctx, stack=s, light_order=5)["model"]
    assert np.isfinite(model.coeffs).all()
    assert (energy(model) <= energy_bound(s) * 1.001).all()
    assert "fewer samples" in ctx.notes["warnings"][0]


def test_plain_least_squares_on_clustered_lights_and_views_stays_bounded():
    rng = np.random.default_rng(1)
    lights = lights_at(60 + rng.uniform(-1.5, 1.5, 20), 120 + rng.uniform(-1.5, 1.5, 20))
    views = lights_at(70 + rng.uniform(-1.5, 1.5, 10), 30 + rng.uniform(-1.5, 1.5, 10))
    samples = rng.uniform(0, 1, (10, 20, 3, 4, 3))
    s = stack_of(samples, lights, views)
    gpu, stats = quiet_fit(s, 4, 3, energy_factor=np.inf)
    ref, _ = quiet_fit(s, 4, 3, energy_factor=np.inf, engine="numpy")
    solver = sh_solver(lights, views, 4, 3)
    assert stats["rank"] == solver.rank < 16 * 9 and stats["lambda_max"] == 0.0
    # Minimum-norm least squares on the directions kept (s_i >= RCOND s_max): ||c|| <= ||y|| / (RCOND s_max).
    norm_y = np.sqrt((samples.astype(np.float64) ** 2).sum(axis=(0, 1)))           # [H, W, C]
    limit = norm_y / (RCOND * solver.s.max())
    for model in (gpu, ref):
        assert np.isfinite(model.coeffs).all()
        assert (np.sqrt(energy(model)) <= limit * 1.001).all()
        rms = np.sqrt(((model.evaluate(lights, views, engine="numpy") - samples) ** 2).mean())
        assert rms < np.sqrt((samples ** 2).mean())                                 # better than the zero function
    np.testing.assert_allclose(gpu.coeffs, ref.coeffs, atol=2e-4 * np.abs(ref.coeffs).max())


@pytest.mark.parametrize("n_light,n_view,light_order,view_order", [(6, 1, 3, 1), (30, 3, 3, 2)])
def test_plain_least_squares_needs_enough_lights_and_views(n_light, n_view, light_order, view_order):
    views = hemisphere(n_view, 0.3) if n_view > 1 else [[0, 0, 1]]
    s = stack_of(np.ones((n_view, n_light, 2, 2, 3)), hemisphere(n_light, 0.1), views)
    with pytest.raises(BtforgeInputError, match=f"light_order {light_order}.*{n_light} light.*view_order {view_order}"
                                                 f".*{n_view} view") as err:
        fit_sh(s, light_order, view_order, energy_factor=np.inf)
    assert "lower the orders" in err.value.hint and "energy" in err.value.hint
    model, _ = quiet_fit(s, light_order, view_order)                               # the bounded fit still runs
    assert np.isfinite(model.coeffs).all()


# ----------------------------------------------------------------------------------------------- multi-view


def test_multi_view_btf_fits_and_relights_at_new_lights_and_views():
    rng = np.random.default_rng(5)
    views = lights_at([90, 60, 45], [0, 0, 180])          # 3 views in the x-z plane
    lights = hemisphere(12, 0.15)
    albedo = rng.uniform(0.3, 1.0, (4, 5, 3))

    def btf(light_dirs, view_dirs):  # view-dependent, within bands <= 1 in view and light
        v, l = np.asarray(view_dirs), np.asarray(light_dirs)
        view_term = 1.0 + 0.3 * v[:, 0] + 0.2 * v[:, 2]
        light_term = 0.4 + 0.5 * l[:, 2] + 0.1 * l[:, 0]
        return (view_term[:, None, None, None, None] * light_term[None, :, None, None, None] * albedo).astype(np.float32)

    s = stack_of(btf(lights, views), lights, views)
    ctx = StageContext(node="fit")
    with pytest.warns(BtforgeWarning, match="determine only 12 of 16"):  # 3 views for 4 view coefficients
        model = btforge.stage("sh.fit")(ctx=ctx, stack=s, light_order=2, view_order=2)["model"]
    assert model.view_dependent and model.coeffs.shape == (4, 5, 3, 4, 4)
    assert ctx.notes["clamped"] == 0 and ctx.notes["view_order"] == 2
    assert ctx.notes["compression_rate_percent"] == round(100 * 16 / 36, 2)
    # The views never vary in y, and neither does the BTF, so the minimum-norm solution is the BTF itself.
    new_lights = np.vstack([hemisphere(7, 0.2), [[0.3, -0.5, 0.81]]])
    new_views = lights_at([75, 50, 80], [30, 200, 290])
    truth = btf(new_lights, new_views)
    relit = model.evaluate(new_lights, new_views)
    assert relit.shape == (3, 8, 4, 5, 3)
    assert np.abs(relit - truth).max() / truth.max() < 1e-3
    np.testing.assert_allclose(relit, model.evaluate(new_lights, new_views, engine="numpy"), rtol=1e-4, atol=1e-6)
    ref, _ = quiet_fit(s, 2, 2, engine="numpy")
    np.testing.assert_allclose(model.coeffs, ref.coeffs, atol=1e-4 * np.abs(ref.coeffs).max())


# ----------------------------------------------------------------------------------------------- stage and buffer


def test_stage_notes_and_relight(tmp_path):
    lights = hemisphere(20, 0.1)
    rng = np.random.default_rng(1)
    s = stack_of(rng.uniform(0, 1, (1, 20, 5, 6, 3)), lights)
    ctx = StageContext(node="fit")
    model = btforge.stage("sh.fit")(ctx=ctx, stack=s, light_order=3, view_order=4, quantize=True)["model"]
    assert model.quantized and not model.view_dependent and model.view_order == 1
    assert "view_order_ignored" in ctx.notes and "warnings" not in ctx.notes
    assert ctx.notes["compression_rate_percent"] == 45.0
    for key in ("lambda_median", "lambda_max", "clamped", "clamped_fraction", "rank"):
        assert key in ctx.notes
    relit = btforge.stage("relight.images")(model=model, lights=[[0, 0, 1], [0.6, 0, 0.8]])["stack"]
    assert relit.samples.shape == (1, 2, 5, 6, 3) and np.isfinite(relit.samples).all()
    assert relit.samples.min() >= 0


def test_graph_run_caches_and_reloads_the_model(tmp_path):
    graph = {"nodes": {
        "material": {"stage": "demo.material", "params": {"size": [16, 16], "lights": 24, "seed": 3}},
        "fit": {"stage": "sh.fit", "params": {"light_order": 3, "quantize": True}, "inputs": {"stack": "material.stack"}},
        "relit": {"stage": "relight.images", "params": {"lights": [[0, 0, 1]]}, "inputs": {"model": "fit.model"}},
    }}
    first = btforge.run(graph, only=["fit", "relit"], cache_dir=tmp_path)
    second = btforge.run(graph, only=["fit", "relit"], cache_dir=tmp_path)
    assert {r.node: r.status for r in second.report}["fit"] == "cached"
    a, b = first["fit"]["model"], second["fit"]["model"]
    assert isinstance(b, SHModel) and b.content_key == a.content_key
    np.testing.assert_array_equal(first["relit"]["stack"].samples, second["relit"]["stack"].samples)
    notes = {r.node: r.notes for r in first.report}["fit"]
    assert notes["compression_rate_percent"] == round(100 * 9 / 24, 2)


def test_model_validation_names_the_problem():
    with pytest.raises(BtforgeInputError, match="'coeffs' must be"):
        SHModel(np.zeros((2, 2, 3, 1, 4), np.float32), np.ones((1, 4), np.float32), np.zeros((1, 4), np.float32),
                2, 1, True, ("R", "G", "B"))  # quantized models hold uint8
    with pytest.raises(BtforgeInputError, match="'coeffs' must be"):
        model_of(np.zeros((2, 2, 3, 1, 9)), 2)
    with pytest.raises(BtforgeInputError, match="light_order"):
        model_of(np.zeros((2, 2, 3, 1, 121)), 11)
    with pytest.raises(BtforgeInputError, match="finite"):
        model_of(np.full((2, 2, 3, 1, 4), np.nan), 2)


# ----------------------------------------------------------------------------------------------- space


def display_sh_stack(seed, light_order=2, n_light=30):
    """An 8-bit stack whose display values are exactly a low-order SH of the light (up to byte rounding)."""
    rng = np.random.default_rng(seed)
    lights = hemisphere(n_light, 0.1)
    coeffs = np.zeros((3, 4, 3, 1, light_order ** 2))
    coeffs[..., 0, 0] = rng.uniform(1.0, 1.6, (3, 4, 3))                     # Y_0 = 1 / sqrt(4 pi)
    coeffs[..., 0, 1:] = rng.uniform(-0.4, 0.4, (3, 4, 3, light_order ** 2 - 1))
    coeffs[..., 0, 2] = np.abs(coeffs[..., 0, 2])    # brighter above the horizon: within the energy bound
    display = np.einsum("hwcvk,lk->lhwc", coeffs, real_sh(light_order, lights))
    assert 0 < display.min() and display.max() < 1
    raw = np.rint(display * 255).astype(np.uint8)[None]
    return SampleStack(raw, lights, [[0, 0, 1]], encoding="srgb8"), lights


def test_srgb_space_fits_display_values_and_relights_in_linear_radiance():
    stack, lights = display_sh_stack(3)
    model, stats = fit_sh(stack, 2, space="srgb")
    assert model.space == stats["space"] == "srgb" and not model.blendable
    relit = model.evaluate(lights)
    # the fit reproduces the bytes (within rounding), and relighting decodes them to linear radiance
    np.testing.assert_allclose(relit, stack.linear(), atol=2.5 / 255)
    np.testing.assert_allclose(model.evaluate(lights, engine="numpy"), relit, rtol=1e-5, atol=1e-7)
    rows, cols = np.array([0, 2, 1]), np.array([0, 3, 1])
    texels = model.evaluate_texels(rows, cols, lights[[0, 5, 9]])
    np.testing.assert_allclose(texels, relit[0, [0, 5, 9], rows, cols], rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(model.evaluate_texels(rows, cols, lights[[0, 5, 9]], engine="numpy"), texels,
                               rtol=1e-5, atol=1e-7)
    again = SHModel.from_payload(*model.payload())
    assert again.space == "srgb" and again.content_key == model.content_key
    with pytest.raises(BtforgeInputError, match="space"):
        fit_sh(stack, 2, space="gamma")


def test_auto_space_picks_the_space_the_data_is_smooth_in():
    display, _ = display_sh_stack(4)                                          # exact in display values
    assert fit_sh(display, 2)[1]["space"] == "srgb"
    lights = hemisphere(30, 0.1)
    rng = np.random.default_rng(5)
    normals = rng.normal([0, 0, 1], 0.3, (8, 8, 3))
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    radiance = 0.8 * np.maximum(np.einsum("hwi,li->lhw", normals, lights), 0)[..., None] * [1.0, 0.8, 0.6]
    lambert = SampleStack(linear_to_srgb8(radiance)[None], lights, [[0, 0, 1]], encoding="srgb8")
    assert fit_sh(lambert, 3)[1]["space"] == "linear"                          # Lambert is linear in radiance
    assert fit_sh(stack_of(radiance[None], lights), 3)[1]["space"] == "linear"  # a linear capture stays linear


@pytest.mark.parametrize("item", ["item5", "item6"])
def test_srgb_space_beats_linear_sh_on_real_captures(shared_data, item):
    from btforge.plugins.relight import compare_stacks
    from btforge.plugins.stackio.images import load_stack
    stack = load_stack(shared_data / "rti" / "realrti" / item / "dirs.lp")
    r0, c0 = (stack.height - 64) // 2, (stack.width - 64) // 2
    held = np.arange(stack.n_light) % 5 == 0

    def part(mask):
        return SampleStack(stack.samples[:, mask, r0:r0 + 64, c0:c0 + 64], stack.lights[mask], stack.views,
                           stack.channels, stack.encoding)
    fit, test = part(~held), part(held)
    scores = {}
    for space in ("linear", "auto"):
        model, stats = fit_sh(fit, 3, space=space)
        scores[stats["space"]] = compare_stacks(
            SampleStack(model.evaluate(test.lights), test.lights, test.views, model.channels), test)["psnr_db"]
    assert scores["srgb"] >= scores["linear"] + 2.0, scores
