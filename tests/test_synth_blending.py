"""Blending through a coordinate map: 8-bit sRGB stacks mix in linear radiance, non-linear PTMs take the heavier
texel, and ``coords.write`` keeps the blend record."""
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


@pytest.mark.parametrize("variant,space,blends", [("rgb", "linear", "records"), ("rgb", "srgb", "no"),
                                                  ("lrgb", "linear", "rgb form"), ("lrgb", "srgb", "no")])
def test_ptm_blends_where_linear_in_its_functions(variant, space, blends):
    rng = np.random.default_rng(2)
    k = 3 if variant == "rgb" else 1
    albedo = rng.uniform(0.2, 1, (H, W, 3 if variant == "lrgb" else 0)).astype(np.float32)
    model = PTMModel(rng.normal(0.5, 0.2, (H, W, k, 6)).astype(np.float32), albedo, variant, space)
    assert model.blendable is (blends == "records")
    assert (model.blendable_form() is None) is (blends == "no")
    coords = blended_map()
    out = materialize(coords=coords, source=model)["output"]
    rows, cols = coords.coords[..., 0], coords.coords[..., 1]
    brows, bcols = coords.blend_coords[..., 0], coords.blend_coords[..., 1]
    w = coords.blend_weight[..., None, None]
    if blends == "no":
        heavier = coords.blend_weight > 0.5
        expected = model.coeffs[np.where(heavier, brows, rows), np.where(heavier, bcols, cols)]
    else:
        # lrgb: each channel's polynomial is its colour times the luminance polynomial
        per_channel = model.coeffs if variant == "rgb" else albedo[..., None] * model.coeffs
        expected = (1 - w) * per_channel[rows, cols] + w * per_channel[brows, bcols]
        assert out.variant == "rgb" and out.space == space and out.albedo.shape == (*rows.shape, 0)
    np.testing.assert_allclose(out.coeffs, expected, rtol=1e-6, atol=1e-7)


def test_an_lrgb_ptm_and_its_rgb_form_relight_alike():
    rng = np.random.default_rng(5)
    coeffs = rng.normal(0.0, 0.3, (H, W, 1, 6)).astype(np.float32)
    coeffs[..., 5] += rng.choice([0.0, 0.6], (H, W, 1)).astype(np.float32)  # some texels negative at many lights
    model = PTMModel(coeffs, rng.uniform(0, 1, (H, W, 3)).astype(np.float32), "lrgb", "linear")
    form = model.blendable_form()
    lights = np.array([[0, 0, 1], [0.6, 0.0, 0.8], [0.0, -0.8, 0.6], [-0.7, 0.7, 0.14]])
    for engine in ("numpy", "opencl"):
        # float32 sums in another order: relative error of a few ulps of the largest term
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
