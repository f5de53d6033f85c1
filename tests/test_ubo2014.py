"""Bonn UBO2014 .btf files (DFMF): the tests write small files in the public layout and read them back."""
import json

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

import btforge
from btforge import BtforgeInputError
from btforge.cli import main
from btforge.graph import check_graph, load_graph
from btforge.registry import default_registry
from btforge.plugins.stackio.importer import import_capture, load_store_stack
from btforge.plugins.stackio.ubo2014 import read_dfmf

from ubo2014_files import random_factors, write_dfmf

LIGHTS = np.radians([[15.0, 0.0], [45.0, 120.0], [60.0, 240.0], [75.0, 300.0], [0.0, 0.0]])
VIEWS = np.radians([[0.0, 0.0], [30.0, 90.0], [60.0, 180.0]])
H, W = 5, 7


def _unit(angles):
    theta, phi = np.asarray(angles, np.float32).astype(np.float64).T
    return np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)


def _reconstruct(stored, transposed):
    """Channels [pairs, texels, C] in float64 from the stored factors (the reference the reader must match)."""
    channels = []
    for _, left, right in stored:
        angular, spatial = (right, left) if transposed else (left, right)
        channels.append(angular.astype(np.float64) @ spatial.astype(np.float64).T)
    return np.stack(channels, axis=-1)


def _as_stack(values):
    return values.reshape(len(VIEWS), len(LIGHTS), H, W, values.shape[-1])


@pytest.mark.parametrize("dtype", ["<f2", "<f4", "<f8"])
@pytest.mark.parametrize("transposed", [False, True])
def test_reader_returns_the_arrays_the_file_was_written_from(tmp_path, dtype, transposed):
    rng = np.random.default_rng(3)
    path = tmp_path / "m.btf"
    stored = write_dfmf(path, LIGHTS, VIEWS, W, H, random_factors(rng, len(LIGHTS) * len(VIEWS), H * W,
                                                                  transposed=transposed), dtype=dtype)
    btf = read_dfmf(path)
    assert (btf.n_view, btf.n_light, btf.height, btf.width, btf.channels) == (3, 5, H, W, ("R", "G", "B"))
    assert btf.rotations == 2 and btf.factors[0].dtype == np.dtype(dtype)
    np.testing.assert_array_equal(btf.lights, _unit(LIGHTS))
    np.testing.assert_array_equal(btf.views, _unit(VIEWS))
    for channel, arrays in enumerate(stored):
        for read, written in zip(btf.matrices(channel), arrays):
            np.testing.assert_array_equal(read, written)  # bit for bit, half floats included
    expected = _as_stack(_reconstruct(stored, transposed))
    np.testing.assert_allclose(btf.decode(), expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(btf.decode(slice(1, 4), slice(2, 7)), expected[:, :, 1:4, 2:7], rtol=1e-5, atol=1e-6)


def _colour_reference(values, model, mean, transform):
    eps = 1e-5
    yuv = np.array([[1, 0, 1.13983], [1, -0.39465, -0.5806], [1, 2.03211, 0]])
    v = values.copy()
    if model == 3:
        return v @ transform + mean
    if model == 4:
        return v @ np.array([[1, 1, -1], [1, 0, 1], [1, -1, -1]]).T
    if model == 12:
        return np.exp(v) - eps
    if model in (9, 10, 11):
        y = np.exp(v[..., 0]) - eps
        if model == 10:
            v[..., 1:] = np.sign(v[..., 1:]) * eps * np.exp(np.abs(v[..., 1:]))
        if model == 11:
            v[..., 1:] = v[..., 1:] * (y[..., None] + eps)
        v[..., 0] = y
    return v @ yuv.T


@pytest.mark.parametrize("model", [1, 3, 4, 9, 10, 11, 12])
def test_colour_models_are_undone(tmp_path, model):
    rng = np.random.default_rng(model)
    mean, transform = rng.uniform(0, 0.2, 3), rng.normal(0, 1, (3, 3))
    path = tmp_path / "m.btf"
    stored = write_dfmf(path, LIGHTS, VIEWS, W, H, random_factors(rng, 15, H * W), colour_model=model,
                        colour_mean=mean, colour_transform=transform)
    expected = _colour_reference(_reconstruct(stored, False), model, mean.astype(np.float32),
                                 transform.astype(np.float32))
    np.testing.assert_allclose(read_dfmf(path).decode(), _as_stack(expected), rtol=2e-5, atol=2e-5)


def test_cosine_flag_is_divided_out(tmp_path):
    rng = np.random.default_rng(5)
    stored = write_dfmf(tmp_path / "m.btf", LIGHTS, VIEWS, W, H, random_factors(rng, 15, H * W), cosine=True)
    cosine = np.cos(LIGHTS[:, 0].astype(np.float32))
    expected = _as_stack(_reconstruct(stored, False)) / cosine[None, :, None, None, None]
    np.testing.assert_allclose(read_dfmf(tmp_path / "m.btf").decode(), expected, rtol=1e-5)


def test_import_read_and_info_of_a_btf_file(tmp_path, capsys):
    rng = np.random.default_rng(7)
    path = tmp_path / "m.btf"
    write_dfmf(path, LIGHTS, VIEWS, W, H, random_factors(rng, 15, H * W), dtype="<f2", colour_model=11)
    decoded = read_dfmf(path).decode()
    array = import_capture(path, tmp_path / "s.zarr", block=(2, 3))
    assert array.chunks == (3, 5, 2, 3, 3)
    stored = load_store_stack(tmp_path / "s.zarr")
    # chunk by chunk: BLAS may round a product 1 ulp differently for a block than for the whole
    np.testing.assert_allclose(stored.samples, decoded, rtol=1e-6)
    assert stored.encoding == "linear"
    np.testing.assert_allclose(stored.lights, _unit(LIGHTS), atol=1e-7)
    graph = {"nodes": {"imp": {"stage": "stackio.import", "params": {"path": str(path), "store": "g.zarr"}},
                       "read": {"stage": "stackio.read", "params": {"path": str(path)}}}}
    result = btforge.run(graph, out_dir=tmp_path)
    np.testing.assert_allclose(result["imp"]["stack"].in_memory().samples, decoded, rtol=1e-6)
    np.testing.assert_array_equal(result["read"]["stack"].samples, decoded)
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "Bonn UBO2014 BTF (DFMF)" and info["views"] == 3 and info["scalar"] == "float16"


def _refusal(tmp_path, case):
    rng = np.random.default_rng(0)
    path = tmp_path / "bad.btf"
    factors = random_factors(rng, 15, H * W)
    if case == "fmf":
        path.write_bytes(b"!FMF12FCER" + bytes(200))
    elif case == "bdi":
        path.write_bytes(b"!BDIF06R2!" + bytes(200))
    elif case == "pvf":
        path.write_bytes(b"!PVF06FCR" + bytes(200))
    elif case == "garbage":
        path.write_bytes(b"P6 7 5 255\n" + bytes(105))
    elif case == "truncated":
        write_dfmf(path, LIGHTS, VIEWS, W, H, factors)
        path.write_bytes(path.read_bytes()[:-17])
    elif case == "trailing":
        write_dfmf(path, LIGHTS, VIEWS, W, H, factors)
        path.write_bytes(path.read_bytes() + b"\0\0")
    elif case == "lab":
        write_dfmf(path, LIGHTS, VIEWS, W, H, factors, colour_model=2)
    elif case == "sizes":
        write_dfmf(path, LIGHTS, VIEWS, W + 1, H, factors)
    return path


@pytest.mark.parametrize("case, words", [
    ("fmf", ["FMF", "'!FMF12FCE'", "DFMF"]), ("bdi", ["BDI", "DFMF"]), ("pvf", ["PVF", "DFMF"]),
    ("garbage", ["expected a Bonn UBO2014 BTF"]), ("truncated", ["byte", "truncated"]),
    ("trailing", ["expected the file to end at byte"]), ("lab", ["LAB colour model"]),
    ("sizes", ["light-view pairs", "texels"])])
def test_other_formats_and_damaged_files_are_refused_at_validation(tmp_path, case, words):
    path = _refusal(tmp_path, case)
    with pytest.raises(BtforgeInputError) as caught:
        read_dfmf(path)
    for word in words:
        assert word in str(caught.value)
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  imp: {{stage: stackio.import, params: {{path: {path}, store: s.zarr}}}}\n")
    with pytest.raises(BtforgeInputError, match=words[0]):
        check_graph(load_graph(graph), default_registry(), tmp_path)
    assert not (tmp_path / "s.zarr").exists()


@settings(max_examples=12, deadline=None)
@given(n_light=st.integers(1, 6), n_view=st.integers(1, 4), height=st.integers(1, 5), width=st.integers(1, 5),
       components=st.lists(st.integers(1, 4), min_size=3, max_size=3), dtype=st.sampled_from(["<f2", "<f4", "<f8"]),
       transposed=st.booleans(), seed=st.integers(0, 2**16))
def test_any_small_file_reads_back_as_the_product_of_its_factors(tmp_path_factory, n_light, n_view, height, width,
                                                                 components, dtype, transposed, seed):
    # with as many light-view pairs as texels the two ways round cannot be told apart: read as U = pairs
    assume(not transposed or n_light * n_view != height * width)
    rng = np.random.default_rng(seed)
    lights = np.column_stack([rng.uniform(0, 1.4, n_light), rng.uniform(0, 6.28, n_light)])
    views = np.column_stack([rng.uniform(0, 1.2, n_view), rng.uniform(0, 6.28, n_view)])
    path = tmp_path_factory.mktemp("btf") / "m.btf"
    factors = random_factors(rng, n_light * n_view, height * width, components, transposed)
    stored = write_dfmf(path, lights, views, width, height, factors, dtype=dtype)
    btf = read_dfmf(path)
    assert [f.components for f in btf.factors] == components
    expected = _reconstruct(stored, transposed).reshape(n_view, n_light, height, width, 3)
    decoded = btf.decode()
    assert decoded.dtype == np.float32 and np.isfinite(decoded).all()
    np.testing.assert_allclose(decoded, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(btf.lights, _unit(lights), atol=1e-12)
