"""What `auto` chooses from held-out lights: the fitting space (PTM, SH) and the SH light order, on constructed
captures whose right answer is known, and staying finite and bounded on hard light sets."""
import math
import warnings

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from btforge.buffers import SampleStack, linear_to_srgb8
from btforge.errors import BtforgeInputError
from btforge.fitspace import AUTO_HOLD_EVERY, best_held_out
from btforge.numerics import real_sh
from btforge.plugins.sh.model import AUTO_ORDERS, AUTO_SMOOTHNESS, auto_orders, few_lights_order, fit_sh, highest_near_best

from lightsets import dome, lights_at

FAST = settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def sh_capture(order: int, lights: np.ndarray, noise: float, seed: int, size: int = 12) -> np.ndarray:
    """Values ``[1, L, size, size, 3]`` of a random positive function of SH order ``order`` per texel and channel
    (every band present), plus Gaussian noise of standard deviation ``noise``."""
    rng = np.random.default_rng(seed)
    k = order * order
    coeffs = rng.normal(0.0, 0.12, (size, size, 3, k))
    coeffs[..., 0] = 1.4                                   # a positive mean: Y_0 = 0.282
    y = real_sh(order, lights)                             # [L, k]
    values = np.einsum("lk,hwck->lhwc", y, coeffs)
    values = values + rng.normal(0.0, noise, values.shape)
    return values[None].astype(np.float32)


def quiet(fn, *args, **kwargs):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fn(*args, **kwargs)


# ----------------------------------------------------------------------------------------------- the criterion


def test_every_light_is_held_out_exactly_once_and_the_truth_wins():
    lights = dome(23, seed=3)
    samples = np.random.default_rng(0).integers(0, 256, (1, 23, 4, 5, 3), dtype=np.uint8)
    stack = SampleStack(samples, lights, np.array([[0.0, 0.0, 1.0]]), encoding="srgb8")
    asked = []

    def predict(fit, candidate, held_lights, views):
        asked.append((candidate, held_lights))
        if candidate == "truth":  # the held-out samples themselves, as linear radiance
            rows = [int(np.argmin(np.abs(stack.lights - light).sum(axis=1))) for light in held_lights]
            return stack.linear()[:, rows]
        return np.full((1, len(held_lights), 4, 5, 3), 0.5, np.float32)

    best, errors = best_held_out(samples, stack, ("flat", "truth"), predict)
    assert best == "truth" and errors["truth"] < 1e-10 < errors["flat"]
    held = np.concatenate([h for c, h in asked if c == "flat"])
    assert len(asked) == 2 * AUTO_HOLD_EVERY and len(held) == 23
    assert sorted(map(tuple, held)) == sorted(map(tuple, stack.lights))


def test_ties_go_to_the_first_candidate():
    stack = SampleStack(np.zeros((1, 12, 2, 2, 1), np.float32), dome(12), np.array([[0.0, 0.0, 1.0]]), ("Y",))
    flat = lambda fit, candidate, lights, views: np.zeros((1, len(lights), 2, 2, 1), np.float32)  # noqa: E731
    assert best_held_out(stack.samples, stack, (4, 2, 3), flat)[0] == 4


# ----------------------------------------------------------------------------------------------- SH light order


@pytest.mark.parametrize("true_order,noise", [(2, 0.03), (3, 0.01), (4, 0.002)])
def test_auto_light_order_recovers_the_order_a_capture_was_rendered_from(true_order, noise):
    lights = dome(45, seed=true_order)
    stack = SampleStack(sh_capture(true_order, lights, noise, seed=true_order), lights, np.array([[0.0, 0.0, 1.0]]))
    model, stats = quiet(fit_sh, stack, "auto")
    assert model.light_order == true_order, stats["held_out_errors"]
    assert stats["light_order"] == true_order and model.space == "linear"   # a linear capture stays linear


def test_auto_light_order_and_space_on_8_bit_captures():
    """Lambertian shading under lights above every normal's horizon is linear in the light (SH order 2) as
    radiance, not as display values; a display value linear in the light is the reverse."""
    lights = lights_at(np.random.default_rng(1).uniform(35, 88, 40), np.random.default_rng(2).uniform(0, 360, 40))
    rng = np.random.default_rng(3)
    tilt = np.radians(rng.uniform(0, 25, (16, 16)))
    azimuth = rng.uniform(0, 2 * np.pi, (16, 16))
    normals = np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)], -1)
    albedo = rng.uniform(0.2, 0.9, (16, 16, 3))
    shading = np.einsum("lk,hwk->lhw", lights, normals)
    radiance = albedo[None] * shading[..., None]
    lambert = SampleStack(linear_to_srgb8(radiance[None]), lights, np.array([[0.0, 0.0, 1.0]]), encoding="srgb8")
    display = 0.25 + 0.5 * albedo[None] * (0.3 + 0.7 * shading[..., None])
    glaze = SampleStack(np.rint(display[None] * 255).astype(np.uint8), lights, np.array([[0.0, 0.0, 1.0]]),
                        encoding="srgb8")
    model, stats = quiet(fit_sh, lambert, "auto")
    assert (model.light_order, model.space) == (2, "linear"), stats["held_out_errors"]
    model, stats = quiet(fit_sh, glaze, "auto")
    assert (model.light_order, model.space) == (2, "srgb"), stats["held_out_errors"]


def test_auto_orders_fit_the_lights_each_fold_keeps():
    assert auto_orders(38) == (2, 3, 4, 5)          # 30 lights per fold: 25 coefficients fit, 36 do not
    assert auto_orders(60) == AUTO_ORDERS
    assert auto_orders(10) == (2,)
    assert [few_lights_order(n) for n in (1, 2, 7, 8, 9, 18, 32)] == [1, 1, 1, 2, 2, 3, 4]


def test_near_ties_go_to_the_higher_order_in_its_better_space():
    errors = {(2, "srgb"): 1.0, (3, "srgb"): 1.04, (3, "linear"): 1.03, (4, "srgb"): 1.2, (4, "linear"): 1.06}
    assert highest_near_best(errors) == (3, "linear")
    assert highest_near_best({(2, "linear"): 0.0, (3, "linear"): 1e-9}) == (2, "linear")


def test_a_given_order_is_fitted_as_given():
    lights = dome(30)
    stack = SampleStack(sh_capture(2, lights, 0.01, seed=5), lights, np.array([[0.0, 0.0, 1.0]]))
    model, stats = quiet(fit_sh, stack, 5)
    assert model.light_order == 5 and stats["held_out_errors"] == {}


# ----------------------------------------------------------------------------------------------- hard light sets


HARD_LIGHTS = {
    "few": lambda rng: dome(int(rng.integers(3, 10)), seed=int(rng.integers(1 << 16)), min_el=20),
    "clustered": lambda rng: lights_at(60 + rng.uniform(-1.5, 1.5, 12), 120 + rng.uniform(-1.5, 1.5, 12)),
    "grazing": lambda rng: lights_at(rng.uniform(1, 10, 14), rng.uniform(0, 360, 14)),
    "one elevation": lambda rng: lights_at(np.full(15, 40.0), np.linspace(0, 336, 15)),
}


@FAST
@given(lights=st.sampled_from(sorted(HARD_LIGHTS)), texels=st.sampled_from(["noise", "spiky", "black"]),
       encoding=st.sampled_from(["srgb8", "linear"]), seed=st.integers(0, 2 ** 16))
def test_auto_order_stays_finite_and_bounded_on_hard_light_sets(lights, texels, encoding, seed):
    rng = np.random.default_rng(seed)
    dirs = HARD_LIGHTS[lights](rng)
    shape = (1, len(dirs), 3, 4, 3)
    linear = {"noise": rng.uniform(0, 1, shape), "spiky": rng.uniform(0, 1, shape) ** 8,
              "black": np.zeros(shape)}[texels].astype(np.float32)
    samples = linear_to_srgb8(linear) if encoding == "srgb8" else linear
    stack = SampleStack(samples, dirs, np.array([[0.0, 0.0, 1.0]]), encoding=encoding)
    model, stats = quiet(fit_sh, stack, "auto")
    allowed = auto_orders(len(dirs)) if len(dirs) >= 10 else (few_lights_order(len(dirs)),)
    assert model.light_order in allowed
    assert all(math.isfinite(e) for e in stats["held_out_errors"].values())
    anywhere = np.vstack([dirs, lights_at([30, 60, 89, -40], [0, 90, 180, 270])])
    relit = model.evaluate(anywhere)
    peak = float(stack.linear().max())
    # the energy bound caps |f| at sqrt(k_l mean(y^2)) <= order x the brightest sample (display or radiance)
    assert np.isfinite(relit).all() and (relit <= model.light_order * max(peak, 1.0) * 1.001 + 1e-6).all()
    if texels == "black":
        assert (relit == 0).all()


# ----------------------------------------------------------------------------------------------- smoothness


def test_smoothness_solves_the_penalised_least_squares():
    """With enough lights and no energy bound the fit is the solution of the normal equations
    ``(A^T A + s (L / 4 pi) diag(l (l + 1))) c = A^T y``."""
    lights = dome(40, seed=7)
    stack = SampleStack(sh_capture(3, lights, 0.05, seed=7, size=3), lights, np.array([[0.0, 0.0, 1.0]]))
    order, smoothness = 4, 0.02
    model, _ = quiet(fit_sh, stack, order, energy_factor=np.inf, space="linear", smoothness=smoothness)
    a = real_sh(order, lights)
    bands = np.repeat(np.arange(order), 2 * np.arange(order) + 1)
    normal = a.T @ a + np.diag(smoothness * len(lights) / (4 * np.pi) * bands * (bands + 1.0))
    y = stack.samples[0].reshape(len(lights), -1).astype(np.float64)
    # a single view's coefficients carry the factor sqrt(4 pi) of the constant view harmonic
    expected = np.sqrt(4 * np.pi) * np.linalg.solve(normal, a.T @ y).T.reshape(3, 3, 3, 1, order * order)
    scale = np.abs(expected).max()
    np.testing.assert_allclose(model.coeffs, expected, atol=2e-4 * scale)


def test_more_smoothness_means_less_gradient_energy():
    lights = dome(30, seed=8)
    stack = SampleStack(sh_capture(4, lights, 0.05, seed=8, size=4), lights, np.array([[0.0, 0.0, 1.0]]))
    bands = np.repeat(np.arange(5), 2 * np.arange(5) + 1)
    gradient = [float((quiet(fit_sh, stack, 5, space="linear", smoothness=s)[0].coeffs ** 2 * bands * (bands + 1)).sum())
                for s in (0.0, 0.01, 0.1, 1.0)]
    assert all(a > b for a, b in zip(gradient, gradient[1:])), gradient


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf"), "smooth", True])
def test_bad_smoothness_is_named(bad):
    lights = dome(12)
    stack = SampleStack(sh_capture(2, lights, 0.0, seed=1, size=2), lights, np.array([[0.0, 0.0, 1.0]]))
    with pytest.raises(BtforgeInputError, match="smoothness"):
        fit_sh(stack, 2, smoothness=bad)


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(lights=st.sampled_from(sorted(HARD_LIGHTS)), seed=st.integers(0, 2 ** 16))
def test_auto_smoothness_stays_finite_and_bounded_on_hard_light_sets(lights, seed):
    rng = np.random.default_rng(seed)
    dirs = HARD_LIGHTS[lights](rng)
    samples = linear_to_srgb8(rng.uniform(0, 1, (1, len(dirs), 3, 4, 3)) ** 4)
    stack = SampleStack(samples, dirs, np.array([[0.0, 0.0, 1.0]]), encoding="srgb8")
    model, stats = quiet(fit_sh, stack, "auto", smoothness="auto")
    assert stats["smoothness"] in (0.0,) + AUTO_SMOOTHNESS
    relit = model.evaluate(np.vstack([dirs, lights_at([30, 89, -40], [0, 180, 270])]))
    assert np.isfinite(relit).all() and (relit <= model.light_order * 1.001).all()
