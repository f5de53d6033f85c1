"""Blending through a coordinate map: 8-bit sRGB stacks mix in linear radiance, PTMs mix the coefficients of their
rgb form, records that do not mix take the heavier texel, and ``coords.write`` keeps the blend record."""
from __future__ import annotations

import numpy as np
import pytest

from btforge.buffers import SRGB8_TO_LINEAR, CoordMap, SampleStack, linear_to_srgb8
from btforge.context import StageContext
from btforge.plugins.ptm.model import PTMModel
from btforge.plugins.synth import coords_write, materialize
from btforge.stages import RunPaths

H, W = 6, 7
LIGHTS = [[0, 0, 1], [0.6, 0, 0.8]]


def blended_map(seed: int = 0) -> CoordMap:
    rng = np.random.default_rng(seed)
    coords = rng.integers(0, [H, W], (5, 4, 2)).astype(np.int32)
    other = rng.integers(0, [H, W], (5, 4, 2)).astype(np.int32)
    weight = rng.uniform(0, 1, (5, 4)).astype(np.float32)
    weight[0] = 0  # a row that is not blended must come out unchanged
    return CoordMap(coords, (H, W), other, weight)


def test_srgb8_stack_blends_in_linear_radiance():
    codes = np.random.default_rng(1).integers(0, 256, (1, 2, H, W, 3)).astype(np.uint8)
    stack = SampleStack(codes, LIGHTS, [[0, 0, 1]], encoding="srgb8")
    coords = blended_map()
    out = materialize(coords=coords, source=stack)["output"]
    assert out.encoding == "srgb8" and out.samples.dtype == np.uint8
    a = codes[:, :, coords.coords[..., 0], coords.coords[..., 1]]
    b = codes[:, :, coords.blend_coords[..., 0], coords.blend_coords[..., 1]]
    w = coords.blend_weight[..., None]
    expected = linear_to_srgb8((1 - w) * SRGB8_TO_LINEAR[a] + w * SRGB8_TO_LINEAR[b])
    np.testing.assert_array_equal(out.samples, expected)
    np.testing.assert_array_equal(out.samples[:, :, 0], a[:, :, 0])
    # Mixing the codes themselves is darker (the sRGB curve is concave): most blended texels differ from it.
    code_mean = np.rint((1 - w) * a + w * b).astype(np.uint8)
    differs = np.abs(out.samples.astype(int) - code_mean).max(axis=(0, 1, 4))[1:]
    assert (differs > 1).mean() > 0.3
    linear = materialize(coords=coords, source=SampleStack(SRGB8_TO_LINEAR[codes], LIGHTS, [[0, 0, 1]]))["output"]
    assert np.abs(out.linear() - linear.samples).max() < 0.01  # the same radiance as a linear stack, to 8 bits


@pytest.mark.parametrize("variant,space", [("rgb", "linear"), ("rgb", "srgb"), ("lrgb", "linear"), ("lrgb", "srgb")])
def test_ptm_mixes_the_coefficients_of_its_rgb_form(variant, space):
    """Only a linear rgb PTM blends as radiance; every PTM mixes the coefficients of its rgb form (an srgb one's
    mix is the mix of its display values)."""
    rng = np.random.default_rng(2)
    k = 3 if variant == "rgb" else 1
    albedo = rng.uniform(0.2, 1, (H, W, 3 if variant == "lrgb" else 0)).astype(np.float32)
    model = PTMModel(rng.normal(0.5, 0.2, (H, W, k, 6)).astype(np.float32), albedo, variant, space)
    assert model.blendable is (variant == "rgb" and space == "linear")
    assert model.mixes_records is (variant == "rgb")
    coords = blended_map()
    out = materialize(coords=coords, source=model)["output"]
    rows, cols = coords.coords[..., 0], coords.coords[..., 1]
    brows, bcols = coords.blend_coords[..., 0], coords.blend_coords[..., 1]
    w = coords.blend_weight[..., None, None]
    # lrgb: each channel's polynomial is its colour times the luminance polynomial
    per_channel = model.coeffs if variant == "rgb" else albedo[..., None] * model.coeffs
    expected = (1 - w) * per_channel[rows, cols] + w * per_channel[brows, bcols]
    assert out.variant == "rgb" and out.space == space and out.albedo.shape == (*rows.shape, 0)
    np.testing.assert_allclose(out.coeffs, expected, rtol=1e-6, atol=1e-7)


def test_records_that_do_not_mix_keep_the_heavier_texel():
    stack = SampleStack(np.random.default_rng(3).uniform(0, 1, (1, 2, H, W, 3)).astype(np.float32), LIGHTS,
                        [[0, 0, 1]])
    coords = blended_map()

    class Unmixed(SampleStack):   # a stack type whose records claim not to mix
        blendable = False
    unmixed = Unmixed(stack.samples, stack.lights, stack.views)
    assert not unmixed.mixes_records and unmixed.mixing_form() is None
    out = materialize(coords=coords, source=unmixed)["output"]
    heavier = coords.blend_weight > 0.5
    rows = np.where(heavier, coords.blend_coords[..., 0], coords.coords[..., 0])
    cols = np.where(heavier, coords.blend_coords[..., 1], coords.coords[..., 1])
    np.testing.assert_array_equal(out.samples, stack.samples[:, :, rows, cols])


@pytest.mark.parametrize("space", ["linear", "srgb"])
def test_an_lrgb_ptm_and_its_rgb_form_relight_alike(space):
    rng = np.random.default_rng(5)
    coeffs = rng.normal(0.0, 0.3, (H, W, 1, 6)).astype(np.float32)
    coeffs[..., 5] += rng.choice([0.0, 0.6], (H, W, 1)).astype(np.float32)  # some texels negative at many lights
    model = PTMModel(coeffs, rng.uniform(0, 1, (H, W, 3)).astype(np.float32), "lrgb", space)
    form = model.mixing_form()
    lights = np.array([[0, 0, 1], [0.6, 0.0, 0.8], [0.0, -0.8, 0.6], [-0.7, 0.7, 0.14]])
    for engine in ("numpy", "opencl"):
        # float32 sums in another order: relative error of a few ulps of the largest term (before the decode,
        # whose slope is at most 1 / 12.92 near 0 and below 2.5 over [0, 1])
        np.testing.assert_allclose(form.evaluate(lights, engine=engine), model.evaluate(lights, engine=engine),
                                   rtol=1e-5, atol=1e-6)


def test_coords_write_keeps_the_blend_record(tmp_path):
    import OpenEXR
    from btforge.plugins.stackio.images import read_exr
    coords = CoordMap(blended_map().coords, (H, W), blended_map().blend_coords, blended_map().blend_weight,
                      wrap=True)
    ctx = StageContext(node="map", paths=RunPaths(tmp_path, tmp_path))
    coords_write(ctx, coords=coords, path="map.exr")
    with OpenEXR.File(str(tmp_path / "map.exr"), separate_channels=True) as exr:
        channels = {name: np.asarray(c.pixels) for name, c in exr.channels().items()}
        header = dict(exr.header())  # closing the file empties the dict it handed out
    assert set(channels) == {"R", "G", "B", "blend.R", "blend.G"}
    back = CoordMap(np.stack([channels["R"], channels["G"]], axis=-1).astype(np.int32),
                    tuple(int(v) for v in header["btforgeSourceSize"]),
                    np.stack([channels["blend.R"], channels["blend.G"]], axis=-1).astype(np.int32),
                    channels["B"], wrap=bool(header["btforgeWrap"]))
    for name in ("coords", "blend_coords", "blend_weight"):
        np.testing.assert_array_equal(getattr(back, name), getattr(coords, name))
    assert back.source_size == (H, W) and back.wrap is True
    assert read_exr(tmp_path / "map.exr").shape == (5, 4, 3)  # RGB readers still see row, column, weight
    # An unblended map writes the texel itself as its partner and weight 0.
    plain = CoordMap(coords.coords, (H, W))
    coords_write(ctx, coords=plain, path="plain.exr")
    with OpenEXR.File(str(tmp_path / "plain.exr"), separate_channels=True) as exr:
        channels = {name: np.asarray(c.pixels) for name, c in exr.channels().items()}
        assert exr.header()["btforgeWrap"] == 0
    np.testing.assert_array_equal(channels["blend.R"], channels["R"])
    assert not channels["B"].any()


def test_an_srgb_hsh_blend_cross_fades_the_display_values():
    """RTI files' HSH coefficients are of display values: a blended map replays as the mix of the two texels'
    display values (before the clip to [0, 1] and the decode), not of their radiance."""
    from btforge.buffers import srgb_to_linear
    from btforge.plugins.web.hsh import HSHModel, hsh_basis
    rng = np.random.default_rng(7)
    coeffs = (rng.normal(0, 0.3, (H, W, 3, 9)) + np.array([0.6] + [0.0] * 8)).astype(np.float32)
    model = HSHModel(coeffs)
    assert model.mixes_records and not model.blendable and model.mixing_form() is model
    coords = blended_map()
    out = materialize(coords=coords, source=model)["output"]
    lights = np.array([[0, 0, 1], [0.6, 0.0, 0.8], [-0.5, 0.5, np.sqrt(0.5)]])
    display = np.einsum("hwck,lk->lhwc", coeffs.astype(np.float64), hsh_basis(lights, 9))
    a = display[:, coords.coords[..., 0], coords.coords[..., 1]]
    b = display[:, coords.blend_coords[..., 0], coords.blend_coords[..., 1]]
    w = coords.blend_weight[None, ..., None]
    expected = srgb_to_linear(np.clip((1 - w) * a + w * b, 0, 1))
    # float32 sums of 9 terms of about 1, through the decode (slope below 2.5): a few 1e-6
    np.testing.assert_allclose(out.evaluate(lights)[0], expected, atol=2e-5)
