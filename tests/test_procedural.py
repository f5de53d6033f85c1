"""The procedural demo material and its OpenCL renderer (checked against the NumPy reference)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from btforge.backend import get_backend
from btforge.errors import BtforgeInputError
from btforge.plugins.demo.procedural import (
    ProceduralMaterial,
    hemisphere_lights,
    make_material,
    normals_from_height,
    render_lights,
    render_lights_numpy,
)

# Shadow-boundary ties may flip a few texels between the kernel and the reference; nothing else may differ.
MAX_TIE_FRACTION = 0.002
TOLERANCE = 1e-5


def lights_at(elevations_deg, azimuths_deg) -> np.ndarray:
    el = np.radians(np.asarray(elevations_deg, dtype=np.float64))
    az = np.radians(np.asarray(azimuths_deg, dtype=np.float64))
    return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1).astype(np.float32)


def random_lights(n: int, seed: int) -> np.ndarray:
    dirs = np.random.default_rng(seed).normal(size=(n, 3))
    dirs[:, 2] = np.abs(dirs[:, 2])
    return (dirs / np.linalg.norm(dirs, axis=1, keepdims=True)).astype(np.float32)


def unshadowed(material: ProceduralMaterial, lights: np.ndarray, ambient: float = 0.0) -> np.ndarray:
    """``albedo * (ambient + max(0, n . l))`` with the renderer's float32 operation order."""
    n = material.normals
    out = []
    for lx, ly, lz in lights.astype(np.float32):
        n_dot_l = n[..., 0] * lx + n[..., 1] * ly + n[..., 2] * lz
        out.append(material.albedo * (np.float32(ambient) + np.maximum(n_dot_l, np.float32(0)))[..., None])
    return np.stack(out)


def assert_agree_up_to_ties(material, lights, ambient=0.0):
    """OpenCL and NumPy agree, except on at most a few texels where one is lit and the other shadowed."""
    on_device = render_lights(material, lights, ambient=ambient)
    reference = render_lights_numpy(material, lights, ambient=ambient)
    assert on_device.shape == reference.shape == (len(lights), *material.shape, 3)
    assert on_device.dtype == reference.dtype == np.float32
    assert np.isfinite(on_device).all() and np.isfinite(reference).all()
    differs = np.abs(on_device - reference).max(axis=-1) > TOLERANCE
    assert differs.mean() <= MAX_TIE_FRACTION, f"{differs.sum()} of {differs.size} texels differ"
    if differs.any():
        lit = unshadowed(material, lights, ambient)[differs]
        dark = (material.albedo[None] * np.float32(ambient) * np.ones((len(lights), 1, 1, 1), np.float32))[differs]
        for a, b in ((on_device[differs], reference[differs]), (reference[differs], on_device[differs])):
            one_lit_other_dark = (np.abs(a - lit).max(-1) <= TOLERANCE) & (np.abs(b - dark).max(-1) <= TOLERANCE)
            if one_lit_other_dark.all():
                break
        else:
            pytest.fail("texels differ by more than being lit vs shadowed")
    return on_device


# ----------------------------------------------------------------------------------------------- agreement


@pytest.mark.parametrize(
    "size, seed",
    [((32, 32), 0), ((37, 53), 1), ((53, 37), 2), ((48, 64), 3), ((33, 33), 4)],
)
def test_opencl_matches_numpy_on_random_materials_and_lights(size, seed):
    material = make_material(*size, bumps=12 + 4 * seed, bump_height=2.0 + 1.5 * seed, seed=seed)
    lights = np.concatenate([hemisphere_lights(8, min_elevation_deg=5.0, seed=seed), random_lights(6, seed)])
    assert_agree_up_to_ties(material, lights, ambient=0.1 * (seed % 2))


# ----------------------------------------------------------------------------------------------- hard inputs


@pytest.mark.parametrize("use_opencl", [True, False])
def test_zenith_light_has_no_shadows(use_opencl):
    material = make_material(40, 36, seed=5, bump_height=8.0)
    out = render_lights(material, np.array([[0.0, 0.0, 1.0]]), use_opencl=use_opencl)
    np.testing.assert_array_equal(out[0], material.albedo * material.normals[..., 2:3])


def test_grazing_lights_cast_many_shadows_and_stay_in_range():
    material = make_material(48, 40, seed=6)
    lights = lights_at([1, 2, 3, 5, 1, 4], [0, 45, 90, 180, 250, 300])
    out = assert_agree_up_to_ties(material, lights)
    assert out.min() >= 0.0 and out.max() <= material.albedo.max()
    lit_without_shadows = unshadowed(material, lights).max(-1) > 0
    shadowed = lit_without_shadows & (out.max(-1) == 0)
    assert shadowed.sum() / lit_without_shadows.sum() > 0.3


def test_horizon_lights_are_bounded_and_light_slopes_facing_them():
    material = make_material(32, 44, seed=7)
    lights = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [-0.6, 0.8, 0.0], [0.9, 0.3, -0.05]], dtype=np.float32)
    out = assert_agree_up_to_ties(material, lights, ambient=0.05)  # the last one is just below the horizon
    free = render_lights(material, lights, shadows=False, ambient=0.05)
    assert (free.max(-1) > material.albedo.max(-1) * 0.05 + 1e-4).any(), "slopes facing a horizon light are lit"
    assert (out <= free).all()
    assert out.min() >= 0.0


@pytest.mark.parametrize("use_opencl", [True, False])
def test_flat_height_field_casts_no_shadows(use_opencl):
    rng = np.random.default_rng(8)
    h, w = 24, 31
    flat = ProceduralMaterial(
        height=np.full((h, w), 2.5, np.float32),
        albedo=rng.uniform(0.1, 1.0, size=(h, w, 3)).astype(np.float32),
        normals=np.tile(np.array([0, 0, 1], np.float32), (h, w, 1)),
    )
    lights = np.concatenate([lights_at([0.5, 2, 30, 89], [10, 100, 200, 300]), [[1.0, 0.0, 0.0]]]).astype(np.float32)
    out = render_lights(flat, lights, use_opencl=use_opencl)
    expected = flat.albedo[None] * np.maximum(lights[:, 2], 0)[:, None, None, None]
    np.testing.assert_array_equal(out, expected)
    no_bumps = make_material(h, w, bumps=0, seed=8)
    np.testing.assert_array_equal(render_lights(no_bumps, lights, use_opencl=use_opencl),
                                  no_bumps.albedo[None] * np.maximum(lights[:, 2], 0)[:, None, None, None])


@pytest.mark.parametrize("bump_height", [250.0, 1e4, -1e4])
def test_huge_bumps_stay_finite(bump_height):
    material = make_material(32, 28, bumps=6, bump_height=bump_height, seed=9)
    assert np.isfinite(material.normals).all() and (material.normals[..., 2] > 0).all()
    lights = np.concatenate([lights_at([2, 20, 60], [0, 120, 240]), [[0.0, 0.0, 1.0]]]).astype(np.float32)
    out = assert_agree_up_to_ties(material, lights)
    assert out.min() >= 0.0 and out.max() <= material.albedo.max()


@pytest.mark.parametrize("size", [(1, 1), (1, 9), (9, 1), (2, 3)])
def test_tiny_sizes(size):
    material = make_material(*size, bumps=3, seed=10)
    lights = np.concatenate([hemisphere_lights(5, min_elevation_deg=1.0), [[1.0, 0.0, 0.0]]]).astype(np.float32)
    out = assert_agree_up_to_ties(material, lights)
    assert out.shape == (6, *size, 3)
    if size == (1, 1):  # a single texel is its own flat neighbourhood
        np.testing.assert_array_equal(out, material.albedo[None] * np.maximum(lights[:, 2], 0)[:, None, None, None])


def test_no_lights_gives_an_empty_stack():
    material = make_material(8, 8)
    assert render_lights(material, np.zeros((0, 3), np.float32)).shape == (0, 8, 8, 3)
    assert render_lights_numpy(material, np.zeros((0, 3), np.float32)).shape == (0, 8, 8, 3)


def test_bad_inputs_raise_input_errors():
    material = make_material(8, 8)
    with pytest.raises(BtforgeInputError):
        render_lights(material, np.ones((3, 2), np.float32))
    with pytest.raises(BtforgeInputError):
        render_lights(material, np.zeros((1, 3), np.float32))
    with pytest.raises(BtforgeInputError):
        render_lights(material, [[0, 0, 1]], ambient=-1.0)
    with pytest.raises(BtforgeInputError):
        render_lights(material.height, [[0, 0, 1]])
    with pytest.raises(BtforgeInputError):
        make_material(0, 5)
    with pytest.raises(BtforgeInputError):
        hemisphere_lights(4, min_elevation_deg=90.0)
    with pytest.raises(BtforgeInputError):
        ProceduralMaterial(material.height, material.albedo * 0, material.normals)


# ----------------------------------------------------------------------------------------------- physics


@pytest.mark.parametrize("use_opencl", [True, False])
def test_without_shadows_is_plain_lambert(use_opencl):
    material = make_material(36, 30, seed=11)
    lights = np.concatenate([hemisphere_lights(10, min_elevation_deg=3.0), random_lights(4, 11)])
    out = render_lights(material, lights, shadows=False, use_opencl=use_opencl)
    np.testing.assert_array_equal(out, unshadowed(material, lights))
    # Independent of the operation order, too.
    expected = material.albedo[None] * np.maximum(np.einsum("hwc,lc->lhw", material.normals, lights), 0)[..., None]
    np.testing.assert_allclose(out, expected, atol=1e-6)


def test_shadows_never_brighten():
    material = make_material(40, 40, seed=12, bump_height=6.0)
    lights = hemisphere_lights(12, min_elevation_deg=5.0, seed=12)
    shadowed = render_lights(material, lights, ambient=0.2)
    free = render_lights(material, lights, ambient=0.2, shadows=False)
    assert (shadowed <= free).all()
    assert (shadowed < free).any()
    assert (shadowed >= material.albedo[None] * np.float32(0.2)).all()


def single_bump(size=64, radius=6.0, peak=6.0) -> ProceduralMaterial:
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float64)
    distance = np.hypot(rows - size // 2, cols - size // 2)
    height = np.where(distance < radius, 0.5 * peak * (1 + np.cos(np.pi * np.minimum(distance / radius, 1))), 0.0)
    return ProceduralMaterial(height=height.astype(np.float32), albedo=np.full((size, size, 3), 0.5, np.float32),
                              normals=normals_from_height(height))


@pytest.mark.parametrize("azimuth_deg, away", [(0, "left"), (180, "right"), (90, "below"), (270, "above")])
def test_shadow_falls_away_from_the_light(azimuth_deg, away):
    """x is to the right and y up the image: a light from +x shadows the left, one from +y shadows below."""
    material = single_bump()
    centre = material.shape[0] // 2
    lights = lights_at([25], [azimuth_deg])
    out = render_lights(material, lights)[0]
    cast = (unshadowed(material, lights)[0].max(-1) > 0) & (out.max(-1) == 0)
    rows, cols = np.nonzero(cast)
    assert rows.size > 20, "a 6-texel bump under a 25 degree light casts a visible shadow"
    side = {"left": cols < centre, "right": cols > centre, "below": rows > centre, "above": rows < centre}[away]
    assert side.all()
    # The tip of the shadow lies about peak / tan(elevation) from the bump's top (13.2 texels for this cap).
    reach = np.abs(cols - centre).max() if away in ("left", "right") else np.abs(rows - centre).max()
    assert abs(reach - 6 / math.tan(math.radians(25))) <= 1.5


# ----------------------------------------------------------------------------------------------- material


def test_same_seed_same_material_and_other_seed_differs():
    a, b, c = make_material(30, 40, seed=13), make_material(30, 40, seed=13), make_material(30, 40, seed=14)
    for field in ("height", "albedo", "normals"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    assert not np.array_equal(a.height, c.height)
    assert not np.array_equal(a.albedo, c.albedo)


def test_material_fields_are_valid_and_read_only():
    material = make_material(37, 53, seed=15)
    assert material.height.dtype == material.albedo.dtype == material.normals.dtype == np.float32
    assert material.albedo.min() > 0 and material.albedo.max() <= 1
    np.testing.assert_allclose(np.linalg.norm(material.normals, axis=-1), 1.0, atol=1e-6)
    assert (material.normals[..., 2] > 0).all()
    np.testing.assert_allclose(material.normals, normals_from_height(material.height), atol=1e-6)
    assert material.height.max() > 1.0
    # Colour varies across the ground, not just brightness.
    chroma = material.albedo / material.albedo.sum(-1, keepdims=True)
    assert chroma.std(axis=(0, 1)).max() > 0.03
    # Bumps are darker than the ground around them.
    on_bumps = material.height > 0.5 * material.height.max()
    assert material.albedo[on_bumps].mean() < material.albedo[material.height == 0].mean()
    with pytest.raises(ValueError):
        material.height[0, 0] = 1.0


def seam_and_interior_steps(field: np.ndarray, axis: int, order: int) -> tuple[np.ndarray, np.ndarray]:
    """|order-th differences| along ``axis`` of two copies of ``field`` side by side: those spanning the seam
    between the copies, and the per-line (across the other axes) interior ones, ``(n_lines, rest)``."""
    tiled = np.concatenate([field, field], axis=axis)
    steps = np.moveaxis(np.abs(np.diff(tiled, n=order, axis=axis)), axis, 0)
    steps = steps.reshape(steps.shape[0], -1)
    n = field.shape[axis]
    spanning = [i for i in range(steps.shape[0]) if i < n <= i + order]  # differences that use both copies
    interior = [i for i in range(n - order)]  # differences inside the first copy
    return steps[spanning], steps[interior]


@pytest.mark.parametrize("seed", [0, 16, 17])
def test_material_tiles(seed):
    """Across each edge the fields continue like between interior neighbours: the differences spanning the
    seam of two tiled copies are no outliers among the interior ones (a cut through bumps would be)."""
    material = make_material(40, 56, seed=seed)
    for field in (material.height, material.albedo):
        for axis in (0, 1):
            for order in (1, 2):
                seam, interior = seam_and_interior_steps(field, axis, order)
                assert seam.max() <= 1.5 * interior.max() + 1e-6
                assert seam.mean(axis=1).max() <= 1.5 * interior.mean(axis=1).max() + 1e-6


def test_tile_check_catches_a_cut():
    """The tiling check above fails on a field that does not wrap (a crop of the material)."""
    material = make_material(40, 56, seed=0)
    cropped = material.height[:, 9:40]
    seam, interior = seam_and_interior_steps(cropped, 1, 1)
    assert seam.max() > 1.5 * interior.max() or seam.mean(axis=1).max() > 1.5 * interior.mean(axis=1).max()


# ----------------------------------------------------------------------------------------------- lights


@pytest.mark.parametrize("n, min_elevation", [(1, 15.0), (8, 15.0), (20, 5.0), (36, 30.0), (50, 0.0)])
def test_hemisphere_lights_are_unit_above_min_elevation_and_spread(n, min_elevation):
    lights = hemisphere_lights(n, min_elevation_deg=min_elevation)
    assert lights.shape == (n, 3) and lights.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(lights, axis=1), 1.0, atol=1e-6)
    assert (lights[:, 2] >= math.sin(math.radians(min_elevation)) - 1e-6).all()
    if n > 1:
        cosines = lights.astype(np.float64) @ lights.T.astype(np.float64)
        np.fill_diagonal(cosines, -1.0)
        min_angle = math.acos(min(1.0, cosines.max()))
        cap_area = 2 * math.pi * (1 - math.sin(math.radians(min_elevation)))
        assert min_angle >= 0.7 * math.sqrt(cap_area / n)


def test_hemisphere_lights_determinism():
    np.testing.assert_array_equal(hemisphere_lights(12), hemisphere_lights(12))
    np.testing.assert_array_equal(hemisphere_lights(12, seed=3), hemisphere_lights(12, seed=3))
    assert not np.array_equal(hemisphere_lights(12, seed=3), hemisphere_lights(12, seed=4))
    assert hemisphere_lights(0).shape == (0, 3)


# ----------------------------------------------------------------------------------------------- backend


def test_program_is_built_once():
    material = make_material(16, 16, seed=18)
    lights = hemisphere_lights(4)
    first = render_lights(material, lights)
    builds = get_backend().builds
    second = render_lights(material, lights)
    assert get_backend().builds == builds
    np.testing.assert_array_equal(first, second)
