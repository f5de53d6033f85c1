"""The paths a streamed capture takes to be fast: decoded on threads into a spill file (with the texel grid taken
on the way), read band by band with the next band read ahead, fitted into memory lent to every band, joined
without a second check of its values, written by two threads.  Each gives what the plain path gives, and bad
input still stops with the clear error."""
import gc
import os
import time

import numpy as np
import pytest

import btforge
import btforge.streaming
from btforge.buffers import values_already_checked
from btforge.cli import main
from btforge.context import StageContext
from btforge.errors import BtforgeInputError
from btforge.fitspace import auto_grid_step


@pytest.fixture(autouse=True)
def stream_small_captures(monkeypatch):
    """These captures are a few kB: stream them all the same (by default captures under 64 MB are held)."""
    import btforge.plugins.stackio.images as images
    monkeypatch.setattr(images, "STREAM_MIN_BYTES", 0)


def jpeg_capture(folder, n_light=9, size=(40, 36), seed=0):
    """An 8-bit JPEG capture of smooth random images (decoded by simplejpeg on the streamed path)."""
    from PIL import Image
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n_light):
        base = rng.uniform(40, 220, (size[1] // 4 + 1, size[0] // 4 + 1, 3))
        pixels = np.repeat(np.repeat(base, 4, axis=0), 4, axis=1)[:size[1], :size[0]].astype(np.uint8)
        Image.fromarray(pixels).save(folder / f"light_{i:03d}.jpg", quality=90)
        azimuth, elevation = 2 * np.pi * i / n_light, np.radians(25 + 50 * (i % 3) / 2)
        x, y, z = np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
        rows.append(f"light_{i:03d}.jpg {x:.6f} {y:.6f} {z:.6f}")
    (folder / "dirs.lp").write_text(f"{n_light}\n" + "\n".join(rows) + "\n")
    return folder / "dirs.lp"


def test_a_capture_decoded_on_threads_into_a_spill_file_is_the_capture_in_memory(tmp_path):
    from btforge.plugins.stackio.images import load_stack, load_stack_spilled
    lp = jpeg_capture(tmp_path / "cap")
    whole = load_stack(lp, threads=1)
    for threads in (1, 2, 3):
        spilled = load_stack_spilled(lp, threads=threads, min_bytes=0)
        assert spilled.chunked
        np.testing.assert_array_equal(np.asarray(spilled.in_memory().samples), whole.samples)


def test_the_texel_grid_taken_while_decoding_is_the_one_read_from_the_file(tmp_path):
    from btforge.plugins.stackio.images import load_stack, load_stack_spilled
    lp = jpeg_capture(tmp_path / "cap", size=(150, 120))
    whole = load_stack(lp)
    spilled = load_stack_spilled(lp, min_bytes=0)
    step = auto_grid_step(whole.height, whole.width)
    assert step > 1 and step in spilled.__dict__["_grids"]   # taken on the way, for the step auto judges on
    kept = spilled.texel_grid(step)
    np.testing.assert_array_equal(kept, whole.texel_grid(step))
    kept[...] = 0  # a copy: the caller may change it
    np.testing.assert_array_equal(spilled.texel_grid(step), whole.texel_grid(step))
    object.__setattr__(spilled, "_grids", {})  # read from the file instead
    np.testing.assert_array_equal(spilled.texel_grid(step), whole.texel_grid(step))


def test_bands_read_ahead_are_the_bands_of_the_capture(tmp_path):
    from btforge.plugins.stackio.images import load_stack, load_stack_spilled
    lp = jpeg_capture(tmp_path / "cap")
    whole = load_stack(lp)
    spilled = load_stack_spilled(lp, min_bytes=0)
    bands = [slice(0, 7), slice(7, 14), slice(14, 21), slice(21, 28), slice(28, 35), slice(35, 36)]  # last short
    with btforge.streaming._BandReader(spilled, bands) as reader:
        for index, rows in enumerate(bands):
            band = reader.band(index)
            np.testing.assert_array_equal(band.samples, whole.samples[:, :, rows])
            assert not band.samples.flags.writeable
            # read into one of the two buffers, the short last band too (a new array costs page faults)
            assert np.shares_memory(band.samples, reader.buffers[index % 2])


def test_a_decode_error_on_a_thread_names_the_earliest_bad_image_and_exits_2(tmp_path, capsys):
    lp = jpeg_capture(tmp_path / "cap")
    (tmp_path / "cap" / "light_006.jpg").write_bytes(b"\xff\xd8 not a JPEG after its first two bytes")
    (tmp_path / "cap" / "light_003.jpg").write_bytes(b"truncated")
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  read: {{stage: stackio.read, params: {{path: '{lp}'}}}}\n"
                     "  fit: {stage: ptm.fit, params: {space: srgb}, inputs: {stack: read.stack}}\n"
                     "  save: {stage: ptm.write, params: {path: out.ptm}, inputs: {model: fit.model}}\n")
    assert main(["run", str(graph), "--no-cache", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "light_003.jpg" in err and "dirs.lp, line 5" in err and "Traceback" not in err
    assert not (tmp_path / "out" / "out.ptm").exists()


def test_streamed_ptm_files_equal_the_whole_stack_files_byte_for_byte(tmp_path, monkeypatch):
    lp = jpeg_capture(tmp_path / "cap", n_light=12, size=(64, 50))
    # a few rows a band: several bands read ahead, and a short last one
    monkeypatch.setattr(btforge.streaming, "BAND_BYTES", 2 * 9 * 64 * 12 * 3 * 4)
    files = {}
    for label, only in (("streamed", None), ("whole", ["read", "save"])):
        nodes = {"read": {"stage": "stackio.read", "params": {"path": str(lp)}},
                 "fit": {"stage": "ptm.fit", "params": {"space": "srgb"}, "inputs": {"stack": "read.stack"}},
                 "save": {"stage": "ptm.write", "params": {"path": f"{label}.ptm"}, "inputs": {"model": "fit.model"}}}
        result = btforge.run({"nodes": nodes}, only=only, out_dir=tmp_path, use_cache=False)
        fit = next(r for r in result.report if r.node == "fit")
        assert ("bands" in fit.placement) == (label == "streamed")
        files[label] = (tmp_path / f"{label}.ptm").read_bytes()
    assert next(r for r in btforge.run({"nodes": nodes}, out_dir=tmp_path, use_cache=False).report
                if r.node == "fit").placement["bands"] == 6
    assert files["streamed"] == files["whole"]


def test_output_arrays_are_new_outside_bands_and_lent_within_them():
    plain = StageContext(node="n")
    a, b = plain.output_array("x", (3, 4), np.float32), plain.output_array("x", (3, 4), np.float32)
    assert a.shape == (3, 4) and a.dtype == np.float32 and not np.shares_memory(a, b)
    banded = StageContext(node="n", band_arrays={})
    first = banded.output_array("x", (6, 4), np.float32)
    first.flags.writeable = False  # a buffer built on it freezes it
    second = banded.output_array("x", (6, 4), np.float32)
    assert np.shares_memory(first, second) and second.flags.writeable
    shorter = banded.output_array("x", (2, 4), np.float32)  # a short last band: part of the same memory
    assert shorter.shape == (2, 4) and np.shares_memory(shorter, first)
    other = banded.output_array("y", (6, 4), np.float64)
    assert other.dtype == np.float64 and not np.shares_memory(other, first)
    # the next band's outputs are computed while this band's are written out: other memory, every other band
    next_band = StageContext(node="n", band_arrays=banded.band_arrays, band_index=1).output_array("x", (6, 4),
                                                                                                np.float32)
    after = StageContext(node="n", band_arrays=banded.band_arrays, band_index=2).output_array("x", (6, 4), np.float32)
    assert not np.shares_memory(next_band, first) and np.shares_memory(after, first)


def test_band_outputs_written_on_the_reading_thread_are_all_written_in_order():
    calls = []
    reader = btforge.streaming._BandReader.__new__(btforge.streaming._BandReader)
    import concurrent.futures
    reader.pool, reader.writes = concurrent.futures.ThreadPoolExecutor(1), []
    try:
        for index in range(5):
            reader.defer(calls.append, index)
        reader.defer(lambda: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            reader.finish()
        assert calls == list(range(5))
    finally:
        reader.pool.shutdown()


def test_values_already_checked_skips_only_the_value_check():
    from btforge.plugins.ptm.model import PTMModel
    bad = np.full((2, 2, 3, 6), np.nan, np.float32)
    with pytest.raises(BtforgeInputError, match="finite"):
        PTMModel(bad, np.zeros((2, 2, 0), np.float32), "rgb", "srgb")
    with values_already_checked():
        PTMModel(bad.copy(), np.zeros((2, 2, 0), np.float32), "rgb", "srgb")
        with pytest.raises(BtforgeInputError, match="must be"):  # shapes are still checked
            PTMModel(np.zeros((2, 2, 3, 5), np.float32), np.zeros((2, 2, 0), np.float32), "rgb", "srgb")
    with pytest.raises(BtforgeInputError, match="finite"):
        PTMModel(bad, np.zeros((2, 2, 0), np.float32), "rgb", "srgb")


def test_the_ptm_solver_of_a_light_set_is_shared_and_read_only():
    from btforge.plugins.ptm.model import ptm_solver
    rng = np.random.default_rng(3)
    lights = rng.normal(size=(12, 3))
    lights[:, 2] = np.abs(lights[:, 2]) + 0.5
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    a, b = ptm_solver(lights, ridge=1e-3), ptm_solver(lights.copy(), ridge=1e-3)
    assert a is b and not a.solve.flags.writeable and not a.design.flags.writeable
    assert ptm_solver(lights, ridge=0.0) is not a
    assert ptm_solver(lights[:-1], ridge=1e-3).solve.shape == (6, 11)


def test_a_dead_spill_file_is_emptied_off_the_callers_path():
    from btforge.spill import spilled_empty
    array = spilled_empty((4, 1 << 16), np.float32)
    array[...] = 1.0
    handle = btforge.spill._files[id(array.base)]
    descriptor = os.dup(handle.fileno())
    try:
        assert os.fstat(descriptor).st_size == array.nbytes
        del array
        gc.collect()
        deadline = time.monotonic() + 10
        while os.fstat(descriptor).st_size and time.monotonic() < deadline:
            time.sleep(0.01)
        assert os.fstat(descriptor).st_size == 0
    finally:
        os.close(descriptor)


def test_a_ptm_file_of_non_finite_coefficients_is_refused_naming_the_texel(tmp_path):
    from btforge.plugins.ptm.ptmfile import write_ptm
    coeffs = np.zeros((5, 4, 3, 6), np.float32)
    coeffs[3, 2, 1, 4] = np.inf
    with pytest.raises(BtforgeInputError, match="row 3, column 2"):
        write_ptm(tmp_path / "bad.ptm", "rgb", coeffs, None)
    assert not (tmp_path / "bad.ptm").exists()


def test_ptm_bands_encoded_on_threads_give_the_bytes_of_one_thread(tmp_path, monkeypatch):
    import btforge.plugins.ptm.ptmfile as ptmfile
    rng = np.random.default_rng(7)
    coeffs = rng.normal(0, 0.4, (37, 23, 3, 6)).astype(np.float32)
    monkeypatch.setattr(ptmfile, "WRITE_BAND_BYTES", 23 * 3 * 6 * 8 * 3)  # 3 rows a band: 13 bands
    ptmfile.write_ptm(tmp_path / "threads.ptm", "rgb", coeffs, None)
    monkeypatch.setattr(ptmfile, "WRITE_THREADS", 1)
    ptmfile.write_ptm(tmp_path / "one.ptm", "rgb", coeffs, None)
    assert (tmp_path / "threads.ptm").read_bytes() == (tmp_path / "one.ptm").read_bytes()


def test_an_in_process_main_leaves_collection_on(tmp_path):
    """Only the command line's own process stops collecting as it ends; a caller's process is left as it was."""
    assert gc.isenabled()
    assert main(["validate", str(tmp_path / "missing.yaml")]) != 0
    assert gc.isenabled() and not gc.get_freeze_count()


def test_a_fresh_run_reports_its_own_peak_not_its_parents(tmp_path):
    """The kernel's peak of a child starts from its parent's peak; the run's report gives the child's own."""
    import json

    from btforge.bench import fresh_run
    lp = jpeg_capture(tmp_path / "cap")
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  read: {{stage: stackio.read, params: {{path: '{lp}'}}}}\n"
                     "  fit: {stage: ptm.fit, params: {space: srgb}, inputs: {stack: read.stack}}\n")
    ballast = np.ones(400 << 20, np.uint8)  # this process peaks above 400 MB
    report = tmp_path / "report.json"
    figures = fresh_run(graph, tmp_path / "out", "--report", str(report))
    del ballast
    own = json.loads(report.read_text())["startup"]["peak_rss_mb"]
    assert figures["peak_rss_mb"] == round(own, 1) and 0 < own < 400
