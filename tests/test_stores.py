"""Chunked stores: stack.import from every public layout the tests write, stack.read of a store, cache keys."""
import json
import math
import zipfile

import numpy as np
import pytest
from hypothesis import given, strategies as st
from PIL import Image

import btforge
from btforge import BtforgeInputError
from btforge.cli import main
from btforge.plugins.stackio.images import load_stack, write_stack
from btforge.plugins.stackio.importer import import_capture, load_store_stack
from btforge.buffers import unit_directions
from btforge.store import open_store

from lightsets import dome


def _ubo_images(rng, views=((0, 0), (30, 90)), lights=((15, 0), (45, 120), (60, 240), (75, 300))):
    return {f"tl{tl}_pl{pl}_tv{tv}_pv{pv}.png": rng.integers(0, 256, (9, 11, 3), dtype=np.uint8)
            for tv, pv in views for tl, pl in lights}


def _same(a, b):
    np.testing.assert_array_equal(a.samples, b.samples)
    np.testing.assert_allclose(a.lights, b.lights, atol=1e-7)
    np.testing.assert_allclose(a.views, b.views, atol=1e-7)
    assert (a.channels, a.encoding, a.names) == (b.channels, b.encoding, b.names)


@pytest.mark.parametrize("layout", ["lp-jpeg", "lp-exr", "lvp-png", "ubo-folder", "ubo-zip"])
def test_import_matches_the_capture_it_was_written_from(tmp_path, layout):
    rng = np.random.default_rng(1)
    if layout.startswith("lp"):
        stack = btforge.stage("demo.material")(size=[13, 10], lights=7)["stack"]
        write_stack(stack, tmp_path / "cap", fmt="exr")
        source = tmp_path / "cap" / "lights.lp"
        if layout == "lp-jpeg":
            for i in range(7):
                Image.fromarray(rng.integers(0, 256, (13, 10, 3), dtype=np.uint8)).save(tmp_path / "cap" / f"j{i}.jpg")
            from btforge.plugins.stackio.lightfile import write_light_file
            write_light_file(tmp_path / "cap" / "j.lp", [f"j{i}.jpg" for i in range(7)], dome(7))
            source = tmp_path / "cap" / "j.lp"
    elif layout == "lvp-png":
        write_stack(btforge.stage("demo.btf")(size=[12, 9], lights=5, views=3)["stack"], tmp_path / "cap", fmt="png")
        source = tmp_path / "cap" / "lights.lvp"
    else:
        images = _ubo_images(rng)
        folder = tmp_path / "ubo"
        folder.mkdir()
        for name, pixels in images.items():
            Image.fromarray(pixels).save(folder / name)
        source = folder
        if layout == "ubo-zip":
            source = tmp_path / "ubo.zip"
            with zipfile.ZipFile(source, "w") as archive:
                for name in images:
                    archive.write(folder / name, f"sample/{name}")  # the download nests the images in a folder
    expected = load_stack(source if layout != "ubo-zip" else tmp_path / "ubo")
    array = import_capture(source, tmp_path / "s.zarr", block=(4, 5))
    assert array.chunks == (expected.n_view, expected.n_light, 4, 5, expected.n_channel)
    back = load_store_stack(tmp_path / "s.zarr")
    if layout == "ubo-zip":
        expected = type(expected)(expected.samples, expected.lights, expected.views, expected.channels,
                                  expected.encoding, tuple(f"sample/{n}" for n in expected.names))
    _same(back, expected)
    if layout.startswith("ubo"):
        theta, phi = math.radians(45), math.radians(120)
        np.testing.assert_allclose(back.lights[1], [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi),
                                                    math.cos(theta)], atol=1e-6)


def test_graph_imports_then_reads_the_store_and_the_cache_follows_its_contents(tmp_path, capsys):
    stack = btforge.stage("demo.material")(size=[8, 8], lights=8)["stack"]
    write_stack(stack, tmp_path / "cap", fmt="exr")
    importing = {"nodes": {"imp": {"stage": "stackio.import", "params": {"path": str(tmp_path / "cap" / "lights.lp"),
                                                                      "store": str(tmp_path / "s.zarr"), "block": [4, 4]}}}}
    btforge.run(importing, out_dir=tmp_path)
    reading = {"nodes": {"read": {"stage": "stackio.read", "params": {"path": str(tmp_path / "s.zarr")}},
                         "fit": {"stage": "ptm.fit", "inputs": {"stack": "read.stack"}}}}
    first = btforge.run(reading, out_dir=tmp_path)
    np.testing.assert_array_equal(first["fit"]["model"].coeffs, btforge.stage("ptm.fit")(stack=stack)["model"].coeffs)
    again = btforge.run(reading, out_dir=tmp_path)
    assert [r.status for r in again.report] == ["not needed", "cached"]  # stack.read is keyed, never stored
    array, _ = open_store(tmp_path / "s.zarr")
    import zarr
    writable = zarr.open_array(str(tmp_path / "s.zarr" / "samples"), mode="r+")
    writable[0, 0, 0, 0, 0] = 0.5  # one chunk changes: the store's key changes
    changed = btforge.run(reading, out_dir=tmp_path)
    assert [r.status for r in changed.report] == ["ran", "ran"]
    assert main(["info", str(tmp_path / "s.zarr"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["lights"] == 8 and info["texels"] == [8, 8] and info["chunk"] == [1, 8, 4, 4, 3]


def test_bad_stores_and_archives_are_refused(tmp_path):
    (tmp_path / "not.zarr").mkdir()
    (tmp_path / "not.zarr" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group"}')
    with pytest.raises(BtforgeInputError, match="no readable 'samples' array"):
        load_store_stack(tmp_path / "not.zarr")
    (tmp_path / "bad.zip").write_bytes(b"PK nothing")
    with pytest.raises(BtforgeInputError, match="cannot read the zip archive"):
        import_capture(tmp_path / "bad.zip", tmp_path / "s.zarr")
    with zipfile.ZipFile(tmp_path / "empty.zip", "w") as archive:
        archive.writestr("readme.txt", "no images")
    with pytest.raises(BtforgeInputError, match="tl15_pl0_tv30_pv120"):
        import_capture(tmp_path / "empty.zip", tmp_path / "s.zarr")
    (tmp_path / "folder").mkdir()
    with pytest.raises(BtforgeInputError, match="not a zarr store"):
        from btforge.store import create_store
        create_store(tmp_path / "folder", (1, 1, 1, 1, 1), np.uint8, lights=[[0, 0, 1]], views=[[0, 0, 1]],
                     channels=("Y",), encoding="srgb8")


def _stored(tmp_path, stack, block=(5, 4)):
    write_stack(stack, tmp_path / "cap", fmt="exr")
    import_capture(tmp_path / "cap" / ("lights.lvp" if stack.n_view > 1 else "lights.lp"), tmp_path / "s.zarr",
                   block=block)
    return btforge.stage("stackio.read")(path=str(tmp_path / "s.zarr"))["stack"]


def test_a_store_is_read_lazily_and_fits_equal_the_in_memory_stack(tmp_path):
    stack = btforge.stage("demo.btf")(size=[11, 9], lights=10, views=3, seed=4)["stack"]
    stored = _stored(tmp_path, stack)
    assert stored.chunked and not stack.chunked and type(stored).__name__ == "StoredSampleStack"
    assert not isinstance(stored.samples, np.ndarray)  # nothing was read yet
    np.testing.assert_array_equal(stored.linear(slice(5, 10)), stack.linear(slice(5, 10)))
    sh_memory = btforge.stage("sh.fit")(stack=stack, light_order=2, view_order=2)["model"]
    sh_stored = btforge.stage("sh.fit")(stack=stored, light_order=2, view_order=2)["model"]
    np.testing.assert_allclose(sh_stored.coeffs, sh_memory.coeffs, rtol=1e-5, atol=1e-6)
    from btforge.spill import is_spilled
    assert is_spilled(sh_stored.coeffs) and not is_spilled(sh_memory.coeffs)  # a store's fit stays out of memory
    picked = btforge.stage("stackio.select")(stack=stored, views=[2], lights=[9, 0])["stack"]
    np.testing.assert_array_equal(picked.samples, stack.samples[[2]][:, [9, 0]])
    top = _stored(tmp_path / "top", btforge.stage("stackio.select")(stack=stack, views=[0])["stack"])
    for variant in ("rgb", "lrgb"):
        memory = btforge.stage("ptm.fit")(stack=top.in_memory(), variant=variant)["model"]
        streamed = btforge.stage("ptm.fit")(stack=top, variant=variant)["model"]
        np.testing.assert_array_equal(streamed.coeffs, memory.coeffs)
        np.testing.assert_array_equal(streamed.albedo, memory.albedo)


@given(st.integers(0, 2**32 - 1))
def test_normalising_directions_twice_changes_no_bit(seed):
    raw = np.random.default_rng(seed).normal(size=(256, 3)) * 10.0
    raw[:, 2] = np.abs(raw[:, 2]) + 1e-3
    once = unit_directions("lights", raw)
    np.testing.assert_array_equal(unit_directions("lights", once), once)


def test_a_stored_stack_read_into_memory_keeps_its_lights_bit_for_bit(tmp_path):
    rng = np.random.default_rng(3)
    lights = rng.normal(size=(300, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 0.05
    stack = btforge.SampleStack(rng.random((1, 300, 2, 2, 1), dtype=np.float32), lights, [[0.0, 0.0, 1.0]], ("Y",))
    stored = _stored(tmp_path, stack)
    np.testing.assert_array_equal(stored.in_memory().lights, stored.lights)


def test_a_cached_stored_stack_refers_to_the_store_and_refuses_a_changed_one(tmp_path):
    stack = btforge.stage("demo.material")(size=[6, 6], lights=6)["stack"]
    stored = _stored(tmp_path, stack, block=(3, 3))
    assert len(stored.to_bytes()) < 4000  # the cache entry holds the store's path and digest, not its samples
    from btforge.registry import default_registry
    from btforge.buffers import Buffer
    (tmp_path / "entry.npz").write_bytes(stored.to_bytes())
    back = Buffer.from_file(tmp_path / "entry.npz", default_registry().types)
    assert back.content_key == stored.content_key
    import zarr
    zarr.open_array(str(tmp_path / "s.zarr" / "samples"), mode="r+")[0, 0, 0, 0, 0] = 0.25
    with pytest.raises(BtforgeInputError, match="changed since"):
        Buffer.from_file(tmp_path / "entry.npz", default_registry().types)


def test_demo_btf_renders_chunk_by_chunk_into_a_store(tmp_path):
    from btforge.buffers import linear_to_srgb8
    memory = btforge.stage("demo.btf")(size=[10, 7], lights=5, views=3, seed=1)["stack"]
    stored = btforge.stage("demo.btf")(size=[10, 7], lights=5, views=3, seed=1, store=str(tmp_path / "b.zarr"),
                                      block=[4, 3])["stack"]
    assert stored.chunked and stored.encoding == "srgb8" and stored.samples.chunks == (3, 5, 4, 3, 3)
    np.testing.assert_array_equal(stored.in_memory().samples, linear_to_srgb8(memory.samples))
    np.testing.assert_allclose(stored.lights, memory.lights, atol=1e-7)
    bands = list(stored.row_bands(budget_bytes=3 * 5 * 7 * 3 * 4 * 2))  # two rows fit: half a chunk row
    assert [(b.start, b.stop) for b in bands] == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 10)]


def test_btf_store_bench_runs_on_a_small_btf(tmp_path, capsys):
    from btforge.plugins.stackio.bench import bench_btf_store
    figures = tmp_path / "f.json"
    assert bench_btf_store(["--size", "8", "--lights", "9", "--views", "4", "--order", "2", "--json", str(figures)]) == 0
    written = json.loads(figures.read_text())
    assert written["render into store"]["peak_rss_mb"] > 0 and written["sh fit, local"]["fit_node_seconds"] > 0
    assert "sh fit, local" in capsys.readouterr().out
