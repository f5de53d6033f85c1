"""PTM fit while reading: kernel ptm_project and ptm_finish_lrgb against their NumPy twins, batches against one
launch, and ptm.fit_capture against stack.read + ptm.fit."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

import btforge
from btforge import BtforgeInputError
from btforge.buffers import SRGB8_TO_LINEAR
from btforge.plugins.ptm.model import (PTMProjection, finish_lrgb, fit_ptm, fit_ptm_capture, project_numpy,
                                      ptm_solver)
from btforge.plugins.stackio.images import load_stack, read_image
from btforge.plugins.stackio.lightfile import write_light_file

from lightsets import dome

FEW = settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _samples(kind, rng, shape, dtype):
    if dtype == np.uint8:
        return {"random": rng.integers(0, 256, shape, dtype=np.uint8), "black": np.zeros(shape, np.uint8),
                "saturated": np.full(shape, 255, np.uint8)}[kind]
    return {"random": rng.uniform(0, 2, shape), "black": np.zeros(shape),
            "saturated": np.full(shape, 1e6)}[kind].astype(np.float32)


@FEW
@given(n_light=st.integers(6, 40), n_texel=st.integers(1, 70), n_channel=st.integers(1, 4),
       kind=st.sampled_from(["random", "black", "saturated"]), table=st.booleans(), as_bytes=st.booleans(),
       seed=st.integers(0, 1000))
def test_project_kernel_matches_numpy_and_batches_match_one_launch(n_light, n_texel, n_channel, kind, table,
                                                                   as_bytes, seed):
    rng = np.random.default_rng(seed)
    solver = ptm_solver(dome(n_light, seed=seed))
    samples = _samples(kind, rng, (n_light, n_texel, n_channel), np.uint8 if as_bytes else np.float32)
    lut = SRGB8_TO_LINEAR if (table and as_bytes) else None
    reference = project_numpy(samples, lut, solver)
    whole = PTMProjection(n_texel, n_channel, "rgb", solver, lut)
    whole.add(samples)
    got, _ = whole.finish()
    scale = max(float(np.abs(reference).max()), 1e-30)
    assert np.isfinite(got).all() and float(np.abs(got - reference).max()) <= 1e-5 * scale
    batched = PTMProjection(n_texel, n_channel, "rgb", solver, lut)
    for start in range(0, n_light, 7):
        batched.add(np.ascontiguousarray(samples[start:start + 7]))
    np.testing.assert_array_equal(batched.finish()[0], got)  # the same operations in the same order


def test_bytes_read_as_numbers_equal_the_display_table():
    rng = np.random.default_rng(4)
    solver = ptm_solver(dome(20))
    samples = rng.integers(0, 256, (20, 37, 3), dtype=np.uint8)
    scaled = PTMProjection(37, 3, "rgb", solver, None, byte_scale=1 / 255)
    scaled.add(samples)
    reference = project_numpy(samples, np.arange(256, dtype=np.float32) / 255, solver)
    np.testing.assert_allclose(scaled.finish()[0], reference, rtol=1e-5, atol=1e-6)


def test_part_of_a_capture_read_in_place():
    rng = np.random.default_rng(5)
    solver = ptm_solver(dome(12))
    samples = rng.uniform(0, 1, (12, 50, 3)).astype(np.float32)
    part = PTMProjection(21, 3, "rgb", solver, None)
    part.add(samples, texel_offset=13)
    np.testing.assert_allclose(part.finish()[0], project_numpy(samples[:, 13:34], None, solver), rtol=1e-5, atol=1e-6)


@FEW
@given(n_texel=st.integers(1, 50), n_channel=st.integers(1, 4), kind=st.sampled_from(["random", "black", "huge", "anti"]),
       seed=st.integers(0, 1000))
def test_finish_lrgb_kernel_matches_numpy(n_texel, n_channel, kind, seed):
    rng = np.random.default_rng(seed)
    lights = dome(16, seed=seed)
    solver = ptm_solver(lights)
    samples = rng.uniform(0, 1, (16, n_texel, n_channel)).astype(np.float32)
    if kind == "black":
        samples[:] = 0
    elif kind == "huge":
        samples *= 1e5
    elif kind == "anti" and n_channel > 1:
        samples[..., 0] = 1.0 - samples[..., 1]   # one channel against the luminance
    projection = PTMProjection(n_texel, n_channel, "lrgb", solver, None)
    projection.add(samples)
    sums = project_numpy(samples, None, solver)
    coeffs, albedo = projection.finish()
    want_coeffs, want_albedo = finish_lrgb(sums, solver)
    scale = max(float(np.abs(want_coeffs).max()), 1e-30)
    assert float(np.abs(coeffs - want_coeffs).max()) <= 1e-4 * scale
    np.testing.assert_allclose(albedo, want_albedo, atol=1e-4)
    assert albedo.min() >= 0 and albedo.max() <= 1


def _capture(folder, fmt, n_light=14, size=(9, 13), grey=False, seed=0):
    rng = np.random.default_rng(seed)
    names = []
    for i in range(n_light):
        shape = size if grey else size + (3,)
        if fmt == "png16":
            Image.fromarray(rng.integers(0, 65536, size, dtype=np.uint16)).save(folder / f"l{i}.png")
            names.append(f"l{i}.png")
            continue
        pixels = rng.integers(0, 256, shape, dtype=np.uint8)
        name = f"l{i}.{fmt}"
        Image.fromarray(pixels).save(folder / name, **({"quality": 90} if fmt == "jpg" else {}))
        names.append(name)
    write_light_file(folder / "dirs.lp", names, dome(n_light, seed=seed))
    return folder / "dirs.lp"


@pytest.mark.parametrize("fmt,grey", [("jpg", False), ("jpg", True), ("png", False), ("png16", True)])
@pytest.mark.parametrize("variant", ["rgb", "lrgb"])
@pytest.mark.parametrize("space", ["auto", "linear", "srgb"])
def test_fit_while_reading_equals_read_then_fit(tmp_path, fmt, grey, variant, space):
    lp = _capture(tmp_path, fmt, grey=grey)
    whole, _ = fit_ptm(load_stack(lp), variant, space)
    streamed, _ = fit_ptm_capture(lp, variant, space, batch_bytes=3 * 9 * 13 * 4)  # a few images per batch
    np.testing.assert_array_equal(streamed.coeffs, whole.coeffs)
    np.testing.assert_array_equal(streamed.albedo, whole.albedo)
    assert (streamed.space, streamed.channel_names) == (whole.space, whole.channel_names)


def test_fit_capture_stage_in_a_graph_and_refusals(tmp_path):
    lp = _capture(tmp_path, "jpg")
    graph = {"nodes": {"fit": {"stage": "ptm.fit_capture", "params": {"path": str(lp), "variant": "lrgb"}},
                       "save": {"stage": "ptm.write", "params": {"path": "m.ptm"}, "inputs": {"model": "fit.model"}}}}
    result = btforge.run(graph, out_dir=tmp_path, only=["fit", "save"])
    assert result["fit"]["model"].variant == "lrgb" and (tmp_path / "m.ptm").stat().st_size > 0
    btf = btforge.stage("demo.btf")(size=[4, 4], lights=6, views=2)["stack"]
    from btforge.plugins.stackio.images import write_stack
    write_stack(btf, tmp_path / "btf", fmt="png")
    with pytest.raises(BtforgeInputError, match="stackio.select"):
        fit_ptm_capture(tmp_path / "btf" / "lights.lvp")
    (tmp_path / "l3.jpg").write_bytes(b"broken")
    with pytest.raises(BtforgeInputError, match="line 5"):
        fit_ptm_capture(lp)


@pytest.mark.parametrize("grey", [False, True])
def test_jpeg_decoder_gives_pillows_pixels(tmp_path, grey):
    pytest.importorskip("simplejpeg")
    rng = np.random.default_rng(2)
    pixels = rng.integers(0, 256, (33, 47) if grey else (33, 47, 3), dtype=np.uint8)
    for subsampling in (0, 2):
        Image.fromarray(pixels).save(tmp_path / "a.jpg", quality=85, subsampling=subsampling)
        with Image.open(tmp_path / "a.jpg") as image:
            expected = np.asarray(image)
        got, transfer = read_image(tmp_path / "a.jpg")
        np.testing.assert_array_equal(got, expected.reshape(got.shape))
        assert transfer == "srgb"
    Image.fromarray(rng.integers(0, 256, (8, 8, 4), dtype=np.uint8), mode="CMYK").save(tmp_path / "c.jpg")
    with Image.open(tmp_path / "c.jpg") as image:
        np.testing.assert_array_equal(read_image(tmp_path / "c.jpg")[0], np.asarray(image.convert("RGB")))


def test_stream_bench_measures_every_way_and_compares_the_files(tmp_path, capsys):
    from btforge.plugins.ptm.bench_stream import bench_ptm_stream
    lp = _capture(tmp_path, "jpg", n_light=8, size=(12, 10))
    assert bench_ptm_stream(["--stack", str(lp), "--repeat", "1", "--json", str(tmp_path / "f.json")]) == 0
    import json
    figures = json.loads((tmp_path / "f.json").read_text())
    assert figures["same_ptm_file"] is True
    for label in ("streamed (default)", "stack read whole", "fit while reading"):
        assert figures[label]["seconds"] > 0 and figures[label]["peak_rss_mb"] > 10
    # a capture this small is held in memory even where it could stream (STREAM_MIN_BYTES)
    assert figures["streamed (default)"]["fit_placement"] == {"where": "local"}
    assert figures["stack read whole"]["fit_placement"] == {"where": "local"}
    # at the fit's default space: fed to ptm.write, auto fits the display values a .ptm file holds
    assert figures["space"] == "auto" and all(figures[label]["fit_space"] == "srgb" for label in
                                               ("streamed (default)", "stack read whole", "fit while reading"))
