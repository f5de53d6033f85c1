"""The orthonormal PTM basis is an isometry: coefficient distance equals function distance over [-1, 1]^2."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import btforge
from btforge.plugins.ptm.legendre import BASIS_IN_RAW_TERMS, to_orthonormal, to_raw
from btforge.plugins.ptm.model import PTMModel

# A dense midpoint grid: a numerical integral that knows nothing about Legendre polynomials.
_N = 400
_GRID = (np.arange(_N) + 0.5) / _N * 2 - 1
_U, _V = np.meshgrid(_GRID, _GRID, indexing="ij")
_TERMS = np.stack([_U * _U, _V * _V, _U * _V, _U, _V, np.ones_like(_U)])  # raw PTM terms on the grid
_CELL = (2.0 / _N) ** 2


def l2_distance_squared(raw_a, raw_b):
    diff = np.tensordot(np.asarray(raw_a, np.float64) - raw_b, _TERMS, axes=(0, 0))
    return float((diff ** 2).sum() * _CELL)


coefficients = arrays(np.float64, 6, elements=st.floats(-50, 50, allow_nan=False, width=32))


@settings(max_examples=60, deadline=None)
@given(a=coefficients, b=coefficients)
def test_orthonormal_distance_equals_function_distance(a, b):
    numeric = l2_distance_squared(a, b)
    coeff = float(((to_orthonormal(a).astype(np.float64) - to_orthonormal(b)) ** 2).sum())
    assert abs(numeric - coeff) <= 1e-4 * max(numeric, 1.0)


@settings(max_examples=60, deadline=None)
@given(a=coefficients)
def test_round_trip_is_identity(a):
    np.testing.assert_allclose(to_raw(to_orthonormal(a)), a.astype(np.float32), rtol=1e-5, atol=1e-4)


def test_basis_functions_are_orthonormal_numerically():
    functions = np.tensordot(BASIS_IN_RAW_TERMS, _TERMS, axes=(1, 0))
    gram = np.einsum("iuv,juv->ij", functions, functions) * _CELL
    np.testing.assert_allclose(gram, np.eye(6), atol=1e-4)


def test_the_printed_matrix_is_not_the_coefficient_map():
    # The paper prints b = M a with M = BASIS_IN_RAW_TERMS; integrating shows it is not an isometry.
    a, b = np.array([1.0, 0, 0, 0, 0, 0]), np.zeros(6)
    printed = float(((BASIS_IN_RAW_TERMS @ a - BASIS_IN_RAW_TERMS @ b) ** 2).sum())
    assert abs(printed - l2_distance_squared(a, b)) > 0.1


def test_stage_and_relighting_are_basis_independent():
    rng = np.random.default_rng(2)
    model = PTMModel(rng.normal(0, 0.3, (5, 6, 1, 6)).astype(np.float32),
                     rng.uniform(0, 1, (5, 6, 3)).astype(np.float32), "lrgb", "linear")
    ortho = btforge.stage("ptm.basis")(model=model, basis="orthonormal")["model"]
    assert ortho.basis == "orthonormal"
    np.testing.assert_array_equal(ortho.albedo, model.albedo)  # the colour part stays as it is
    lights = np.array([[0.3, 0.2, 0.93], [0.0, 0.0, 1.0], [-0.7, 0.1, 0.7]])
    np.testing.assert_allclose(ortho.evaluate(lights), model.evaluate(lights), rtol=1e-5, atol=1e-6)
    back = btforge.stage("ptm.basis")(model=ortho, basis="raw")["model"]
    np.testing.assert_allclose(back.coeffs, model.coeffs, rtol=1e-5, atol=1e-6)
