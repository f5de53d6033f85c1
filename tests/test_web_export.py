"""relight's web layout (model.export_web, ptm.read / web.read of info.json) and HSH .rti files."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import btforge
from btforge import SampleStack
from btforge.buffers import linear_to_srgb
from btforge.errors import BtforgeInputError
from btforge.plugins.web.hsh import HSHModel, hsh_basis, write_rti
from btforge.plugins.web.layout import quantize_planes, read_web, sh_weights, write_web

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
PROBE = np.array([[0, 0, 1.0], [0.6, 0.2, 0.77], [-0.5, -0.5, 0.71], [0.1, 0.9, 0.42], [-0.95, 0.1, 0.3]])
PROBE = PROBE / np.linalg.norm(PROBE, axis=1, keepdims=True)


def capture(n=30, size=(24, 20), seed=0, encoding="srgb8") -> SampleStack:
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.25, 1, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    lights = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    normal = rng.normal(0, 0.3, size + (3,)) + [0, 0, 1]
    normal /= np.linalg.norm(normal, axis=2, keepdims=True)
    albedo = rng.uniform(0.2, 0.9, size + (3,))
    shade = np.clip(np.einsum("hwk,lk->lhw", normal, lights), 0, None)[..., None] * albedo
    if encoding == "srgb8":
        from btforge.buffers import linear_to_srgb8
        return SampleStack(linear_to_srgb8(shade)[None], lights, [[0, 0, 1]], encoding="srgb8")
    return SampleStack(shade.astype(np.float32)[None], lights, [[0, 0, 1]])


def display_psnr(a: SampleStack, b: SampleStack) -> float:
    x, y = linear_to_srgb(a.samples), linear_to_srgb(b.samples)
    return float(10 * np.log10(1.0 / max(np.mean((x - y) ** 2), 1e-20)))


def round_trip(model, tmp_path, reader="web.read"):
    btforge.stage("web.export")(model=model, dir=str(tmp_path / "web"))
    again = btforge.stage(reader)(path=str(tmp_path / "web" / "info.json"))["model"]
    relight = btforge.stage("relight.images")
    return relight(model=model, lights=PROBE.tolist())["stack"], relight(model=again, lights=PROBE.tolist())["stack"], again


@pytest.mark.parametrize("variant", ["rgb", "lrgb"])
def test_ptm_round_trip_45db(tmp_path, variant):
    model = btforge.stage("ptm.fit")(stack=capture(), variant=variant)["model"]
    before, after, again = round_trip(model, tmp_path, "ptm.read")
    assert again.variant == variant and again.space == model.space
    assert display_psnr(before, after) >= 45


def test_linear_ptm_and_sh_round_trip_45db(tmp_path):
    stack = capture(encoding="linear")
    ptm = btforge.stage("ptm.fit")(stack=stack, space="linear")["model"]
    before, after, again = round_trip(ptm, tmp_path)
    assert again.space == "linear" and display_psnr(before, after) >= 45
    for order in (2, 3):
        sh = btforge.stage("sh.fit")(stack=stack, light_order=order)["model"]
        before, after, again = round_trip(sh, tmp_path / f"sh{order}")
        assert again.type_name == "SHModel" and display_psnr(before, after) >= 45
    info = json.loads((tmp_path / "sh3" / "web" / "info.json").read_text())
    assert info["type"] == "sh" and info["nplanes"] == 27 and info["btforge"] == {"transfer": "linear"}


def test_sh_of_display_values_round_trips_marked_as_display_values(tmp_path):
    sh = btforge.stage("sh.fit")(stack=capture(), light_order=3, space="srgb")["model"]
    before, after, again = round_trip(sh, tmp_path)
    assert again.type_name == "SHModel" and again.space == "srgb" and display_psnr(before, after) >= 45
    info = json.loads((tmp_path / "web" / "info.json").read_text())
    assert info["type"] == "sh" and "btforge" not in info  # no linear transfer: viewers show the values as they are


def test_sh_basis_matches_openlime_and_high_orders_are_refused(tmp_path):
    from btforge.plugins.sh.model import real_sh
    rng = np.random.default_rng(1)
    d = rng.normal(size=(20, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # the same functions up to order and sign: every web function is one of ours
    corr = np.abs(np.corrcoef(real_sh(3, d).T, sh_weights(d).T)[:9, 9:])
    assert np.allclose(np.sort(corr.max(axis=0)), 1.0, atol=1e-9)
    sh = btforge.stage("sh.fit")(stack=capture(encoding="linear"), light_order=4)["model"]
    with pytest.raises(BtforgeInputError, match="light_order: 3"):
        btforge.stage("web.export")(model=sh, dir=str(tmp_path / "x"))


def test_quantization_keeps_the_whole_range():
    planes = np.random.default_rng(2).normal(0, 1, (4, 8, 8))
    planes[0, 0, 0] = 50.0  # one outlier: relight's quantile clipping would lose it
    levels, scale, bias = quantize_planes(planes)
    decoded = (levels / 255.0 - np.array(bias)[:, None, None]) * np.array(scale)[:, None, None]
    assert np.abs(decoded - planes).max() <= max(scale) / 510 + 1e-12
    assert abs(decoded[0, 0, 0] - 50.0) <= scale[0] / 510 + 1e-12


def test_hsh_rti_and_web_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    coeffs = rng.normal(0, 0.2, (10, 12, 3, 9)).astype(np.float32)
    coeffs[..., 0] += 1.0
    model = HSHModel(coeffs)
    write_rti(tmp_path / "m.rti", model)
    back = btforge.stage("web.read")(path=str(tmp_path / "m.rti"))["model"]
    step = (coeffs.max(axis=(0, 1, 2)) - coeffs.min(axis=(0, 1, 2))) / 510
    assert np.all(np.abs(back.coeffs - coeffs) <= step + 1e-6)
    before, after, again = round_trip(model, tmp_path)
    assert again.type_name == "HSHModel" and display_psnr(before, after) >= 45
    top = hsh_basis(np.array([[0.0, 0.0, 1.0]]), 9)[0]
    assert abs(top[0] - 1 / np.sqrt(2 * np.pi)) < 1e-12 and abs(top[1]) < 1e-9


def test_bad_layouts_are_named(tmp_path):
    (tmp_path / "info.json").write_text('{"width": 4, "height": 4, "type": "rbf", "colorspace": "rgb", "nplanes": 3, '
                                        '"materials": [{"scale": [1], "bias": [0, 0, 0]}]}')
    with pytest.raises(BtforgeInputError) as err:
        read_web(tmp_path)
    assert "rbf" in str(err.value) and "scale" in str(err.value)
    model = btforge.stage("ptm.fit")(stack=capture())["model"]
    write_web(model, tmp_path / "w")
    (tmp_path / "w" / "plane_2.png").unlink()
    with pytest.raises(BtforgeInputError, match="plane_2.png"):
        read_web(tmp_path / "w")
    sh_dir = tmp_path / "sh"
    write_web(HSHModel(np.ones((2, 2, 3, 4), np.float32)), sh_dir)
    with pytest.raises(BtforgeInputError, match="web.read"):
        btforge.stage("ptm.read").precheck({"path": str(sh_dir / "info.json")},
                                           btforge.stages.RunPaths(tmp_path, tmp_path))


@pytest.mark.shared_data
def test_openlime_sample_reads_as_its_planes_say():
    folder = SHARED / "ptm" / "openlime_relight_ptm"
    if not folder.is_dir():
        pytest.skip("../shared/data is not present")
    model = btforge.stage("ptm.read")(path=str(folder / "info.json"))["model"]
    info = json.loads((folder / "info.json").read_text())
    assert (model.height, model.width) == (info["height"], info["width"]) and model.variant == "rgb"
    # straight above, the relit value is the constant term: plane_0 decoded with its scale and bias
    pixel = np.asarray(Image.open(folder / "plane_0.jpg").convert("RGB"))[300, 400] / 255.0
    expected = (pixel - np.array(info["materials"][0]["bias"][:3])) * np.array(info["materials"][0]["scale"][:3])
    got = model.with_basis("raw").coeffs[300, 400, :, 5]
    np.testing.assert_allclose(got, expected, atol=1e-5)
