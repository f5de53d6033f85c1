"""Height fields: the buffer, its files, and height from shading (kernel vs twin, accuracy on known geometry)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from btforge import SampleStack, stage
from btforge.errors import BtforgeInputError
from btforge.plugins.height import sfs
from btforge.plugins.height.field import HeightField, normals_of
from btforge.plugins.height.testing import angular_error_degrees, known_capture


def _random_problem(rng, h, w, k, *, steep=1.0, grazing=False, black=False, zero_weights=False):
    lights = rng.normal(size=(k, 3))
    lights[:, 2] = 0.0 if grazing else np.abs(lights[:, 2])
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    image = np.zeros((k, h, w), np.float32) if black else rng.random((k, h, w)).astype(np.float32) * 4
    eta = np.zeros_like(image) if zero_weights else rng.random((k, h, w)).astype(np.float32)
    problem = sfs.Problem(image, lights, eta, rng.random((h, w)), 1.0, 0.3, 0.2)
    z = (rng.normal(size=(h, w)) * steep).astype(np.float32)
    rho = rng.random((h, w)).astype(np.float32) * 2
    return problem, z, rho


@settings(max_examples=6, deadline=None)
@given(st.integers(0, 2**16), st.integers(3, 19), st.integers(3, 23), st.integers(1, 9),
       st.sampled_from(["plain", "steep", "grazing", "black", "zero_weights"]))
def test_energy_kernel_matches_twin(seed, h, w, k, case):
    rng = np.random.default_rng(seed)
    problem, z, rho = _random_problem(rng, h, w, k, steep=1e3 if case == "steep" else 1.0, grazing=case == "grazing",
                                      black=case == "black", zero_weights=case == "zero_weights")
    e_cl, gz_cl, ga_cl = sfs.OpenCLEnergy(problem)(z, rho)
    e_np, gz_np, ga_np = sfs.NumpyEnergy(problem)(z, rho)
    for a in (gz_cl, ga_cl):
        assert np.isfinite(a).all()
    assert e_cl == pytest.approx(e_np, rel=1e-5, abs=1e-6)
    np.testing.assert_allclose(gz_cl, gz_np, rtol=1e-4, atol=1e-4 * (np.abs(gz_np).max() + 1e-6))
    np.testing.assert_allclose(ga_cl, ga_np, rtol=1e-4, atol=1e-4 * (np.abs(ga_np).max() + 1e-6))


def test_gradient_is_the_derivative_of_the_energy():
    rng = np.random.default_rng(1)
    problem, z, rho = _random_problem(rng, 9, 11, 5)
    energy = sfs.NumpyEnergy(problem)
    _, gz, ga = energy(z, rho)
    dz, da = rng.normal(size=z.shape).astype(np.float32), rng.normal(size=z.shape).astype(np.float32)
    t = 1e-2
    numeric = (energy(z + t * dz, rho + t * da)[0] - energy(z - t * dz, rho - t * da)[0]) / (2 * t)
    assert numeric == pytest.approx(float((gz * dz).sum() + (ga * da).sum()), rel=2e-2)


def test_integrating_exact_normals_gives_back_the_heights():
    y, x = np.mgrid[0:40, 0:48]
    heights = (3 * np.sin(x / 6.0) * np.cos(y / 5.0)).astype(np.float32)
    recovered = sfs.integrate_normals(normals_of(heights))
    assert np.abs(recovered - (heights - heights.mean())).max() < 0.15


def _run(capture, **params):
    stack = SampleStack(capture.images[None], capture.lights, [[0.0, 0.0, 1.0]])
    return stage("height.from_shading")(stack=stack, **params)


def test_matte_demo_material_normals():
    capture = known_capture(size=64, lights=24, specular=0.0, bump_height=4.0, min_elevation=20.0)
    field = _run(capture)["height"]
    error = angular_error_degrees(field.normals, capture.normals)
    print(f"matte: mean {error.mean():.3f} deg, median {np.median(error):.3f} deg")
    assert error.mean() < 1.5 and np.median(error) < 1.0


def test_glossy_shadowed_capture_beats_least_squares_and_finds_shadows():
    capture = known_capture(size=80, lights=24, specular=0.6, bump_height=6.0, min_elevation=12.0)
    out = _run(capture)
    field, weights = out["height"], out["weights"]
    grey = capture.images.mean(3)
    ls_normals, _ = sfs.photometric_stereo_ls(grey, capture.lights)
    ours = angular_error_degrees(field.normals, capture.normals)
    ls = angular_error_degrees(ls_normals, capture.normals)
    w = weights.samples[0, :, :, :, 0]
    recall = float((w[capture.shadowed] < 0.5).mean())
    print(f"glossy: ours mean {ours.mean():.3f} median {np.median(ours):.3f}; least squares mean {ls.mean():.3f} "
          f"median {np.median(ls):.3f}; shadow recall {recall:.3f}")
    assert ours.mean() < 0.5 * ls.mean() and np.median(ours) < np.median(ls)
    assert recall > 0.85
    # Re-rendered at the input lights, the recovered field reproduces the shading the weights keep.
    shade = np.maximum(np.einsum("hwc,kc->khw", field.normals, capture.lights), 0)
    rendered = shade[..., None] * field.albedo[None]
    kept = w > 0.5
    relative = np.sqrt(((rendered - capture.images)[kept] ** 2).mean()) / capture.images[kept].mean()
    print(f"re-rendered relative RMSE on kept samples: {relative:.4f}")
    assert relative < 0.05


def test_non_robust_solve_is_worse_on_shadows():
    capture = known_capture(size=48, lights=16, specular=0.6, bump_height=6.0, min_elevation=12.0)
    robust = angular_error_degrees(_run(capture, rounds=2)["height"].normals, capture.normals).mean()
    plain = angular_error_degrees(_run(capture, robust=False, rounds=2)["height"].normals, capture.normals).mean()
    assert robust < plain


def test_flat_start_still_descends():
    capture = known_capture(size=32, lights=12, bump_height=2.0, bumps=6, min_elevation=30.0)
    field = _run(capture, init="flat", iterations=300)["height"]
    assert angular_error_degrees(field.normals, capture.normals).mean() < 10.0


def test_too_small_stack_is_refused():
    stack = SampleStack(np.ones((1, 2, 8, 8, 1), np.float32), [[0, 0, 1], [1, 0, 1]], [[0, 0, 1]], channels=("Y",))
    with pytest.raises(BtforgeInputError, match="at least 3 images"):
        stage("height.from_shading")(stack=stack)


# ----------------------------------------------------------------------------------------------- the buffer


def _field(h=12, w=10, k=0):
    y, x = np.mgrid[0:h, 0:w]
    heights = (np.sin(x / 2.0) + np.cos(y / 3.0)).astype(np.float32)
    albedo = np.random.default_rng(0).random((h, w, 3)).astype(np.float32)
    return HeightField.from_height(heights, albedo, weights=np.full((h, w, k), 0.5, np.float32))


def test_buffer_validation_names_every_problem():
    good = _field()
    with pytest.raises(BtforgeInputError) as err:
        HeightField(good.heights, -good.albedo, good.normals * 2)
    assert "albedo" in str(err.value) and "normals" in str(err.value)
    with pytest.raises(BtforgeInputError, match="'heights' must be"):
        HeightField(good.heights[None], good.albedo, good.normals)


def test_crop_materialize_and_synthesis_accept_a_height_field():
    field = _field(24, 24, k=4)
    cropped = stage("synth.crop")(input=field, origin=[2, 3], size=[10, 12])["output"]
    assert isinstance(cropped, HeightField) and cropped.heights.shape == (10, 12)
    np.testing.assert_array_equal(cropped.heights, field.heights[2:12, 3:15])
    assert cropped.weights.shape == (10, 12, 4)
    features = field.appearance_features()
    assert features.shape == (24, 24, 3) and features.dtype == np.float32
    coords = stage("synth.quilt")(exemplar=field, size=[32, 32], block=8, seam="blend")["coords"]
    grown = stage("synth.materialize")(coords=coords, source=field)["output"]
    assert isinstance(grown, HeightField) and grown.heights.shape == (32, 32)
    np.testing.assert_allclose(np.linalg.norm(grown.normals, axis=-1), 1, atol=1e-5)


def test_writers_round_trip(tmp_path):
    from PIL import Image

    from btforge.context import StageContext
    from btforge.plugins.height.io import describe_ply
    from btforge.plugins.render.geometry import read_mesh_file
    from btforge.plugins.stackio.images import read_exr
    from btforge.stages import RunPaths
    field = _field()
    ctx = StageContext(node="t", paths=RunPaths(tmp_path, tmp_path))
    for name in ("n.png", "n.exr"):
        stage("height.write_normals")(ctx=ctx, height=field, path=name)
    for name in ("h.exr", "h.ply"):
        stage("height.write")(ctx=ctx, height=field, path=name)
    png = np.asarray(Image.open(tmp_path / "n.png"), np.float64) / 255 * 2 - 1
    assert np.abs(png - field.normals).max() < 1.01 / 255 * 2
    np.testing.assert_array_equal(read_exr(tmp_path / "n.exr"), field.normals)
    np.testing.assert_array_equal(read_exr(tmp_path / "h.exr")[..., 0], field.heights)
    mesh = read_mesh_file(str(tmp_path / "h.ply"))
    assert mesh["positions"].shape == (12 * 10, 3) and mesh["corner_uv"].shape == (2 * 11 * 9, 3, 2)
    np.testing.assert_allclose(mesh["positions"][:, 2], field.heights.ravel())
    first = mesh["triangles"][0]
    p = mesh["positions"][first]
    assert np.cross(p[1] - p[0], p[2] - p[0])[2] > 0  # faces point up
    info = describe_ply(tmp_path / "h.ply")
    assert info["uv"] and info["vertices"] == 120
    with pytest.raises(BtforgeInputError, match="ending in .png or .exr"):
        stage("height.write_normals")(ctx=ctx, height=field, path="n.jpg")


def test_kcoherence_grows_a_height_field():
    field = _field(24, 24)
    coords = stage("synth.kcoherence")(exemplar=field, size=[32, 32], levels=1, neighborhood=3, k=2, textons=16)["coords"]
    grown = stage("synth.materialize")(coords=coords, source=field)["output"]
    assert isinstance(grown, HeightField) and grown.heights.shape == (32, 32)


@settings(max_examples=6, deadline=None)
@given(st.sampled_from(["black", "constant", "saturated", "three_lights", "clustered", "grazing"]))
def test_height_from_shading_stays_finite_on_hard_stacks(case):
    rng = np.random.default_rng(0)
    k = 3 if case == "three_lights" else 8
    lights = np.column_stack([rng.normal(size=k), rng.normal(size=k), np.abs(rng.normal(size=k)) + 0.3])
    if case == "clustered":
        lights = np.tile([0.3, 0.1, 0.95], (k, 1)) + rng.normal(size=(k, 3)) * 1e-3
    if case == "grazing":
        lights[:, 2] = 0.01
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    images = {"black": np.zeros((k, 12, 12, 1)), "constant": np.full((k, 12, 12, 1), 0.4),
              "saturated": np.ones((k, 12, 12, 1))}.get(case, rng.random((k, 12, 12, 1)))
    stack = SampleStack(images[None].astype(np.float32), lights, [[0.0, 0.0, 1.0]], channels=("Y",))
    out = stage("height.from_shading")(stack=stack, iterations=30)
    field = out["height"]
    for a in (field.heights, field.albedo, field.normals, out["weights"].samples):
        assert np.isfinite(a).all()
    assert np.abs(field.heights).max() < 1e3 and (out["weights"].samples >= 0).all() and (out["weights"].samples <= 1).all()
