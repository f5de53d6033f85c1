"""Streaming by default: stack.read -> per-texel fits runs band by band when no node needs the stack whole.

The decision is the runner's, from the graph (who reads the stack); a streamed fit must equal the fit of the
whole stack, and a graph where any node reads the stack whole must stream nothing and still run.
"""
import numpy as np
import pytest

import btforge
import btforge.streaming
from btforge.graph import check_graph, load_graph
from btforge.registry import default_registry
from btforge.runner import DEFAULT_OUT


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A 24 x 20, 14-light 8-bit PNG capture of the procedural material (written by btforge itself)."""
    folder = tmp_path_factory.mktemp("capture")
    btforge.run({"nodes": {
        "m": {"stage": "demo.material", "params": {"size": [24, 20], "lights": 14, "bumps": 6, "seed": 3}},
        "w": {"stage": "stackio.write", "params": {"dir": "cap", "format": "png"}, "inputs": {"stack": "m.stack"}}}},
        out_dir=folder, use_cache=False)
    return next((folder / "cap").glob("*.lp"))


def _graph(capture, *, whole_reader=False, sh_params=None):
    nodes = {
        "read": {"stage": "stackio.read", "params": {"path": str(capture)}},
        "ptm": {"stage": "ptm.fit", "inputs": {"stack": "read.stack"}},
        "sh": {"stage": "sh.fit", "params": dict(sh_params or {"light_order": 3}), "inputs": {"stack": "read.stack"}},
    }
    if whole_reader:  # a node that needs every light of every texel at once
        nodes["split"] = {"stage": "stackio.split", "inputs": {"stack": "read.stack"}}
    return {"nodes": nodes}


def _by_node(result):
    return {r.node: r for r in result.report}


@pytest.fixture(autouse=True)
def stream_small_captures(monkeypatch):
    """These captures are a few kB: stream them all the same (by default captures under 64 MB are held)."""
    import btforge.plugins.stackio.images as images
    monkeypatch.setattr(images, "STREAM_MIN_BYTES", 0)


@pytest.fixture
def small_bands(monkeypatch):
    # 5 rows a band of the 24-row capture (linear float32 bytes of two bands of 5 rows, one of them read ahead):
    # 5 bands, the last one short
    monkeypatch.setattr(btforge.streaming, "BAND_BYTES", 2 * 5 * 20 * 14 * 3 * 4)


def test_streamed_fits_equal_the_fits_of_the_whole_stack(capture, tmp_path, small_bands):
    streamed = btforge.run(_graph(capture), only=["ptm", "sh"], out_dir=tmp_path, use_cache=False)
    whole = btforge.run(_graph(capture, whole_reader=True), only=["ptm", "sh", "split"], out_dir=tmp_path,
                        use_cache=False)
    s, w = _by_node(streamed), _by_node(whole)
    assert s["read"].notes.get("streamed") is True
    assert s["ptm"].placement == {"where": "local", "bands": 5} and s["sh"].placement["bands"] == 5
    assert "streamed" not in w["read"].notes
    assert w["ptm"].placement == {"where": "local"} and w["sh"].placement == {"where": "local"}
    # auto decided once on the whole stack, before the bands: the same space as the whole-stack fit chose
    assert s["ptm"].notes["space"] == w["ptm"].notes["space"]
    assert s["ptm"].notes["settled"] == {"space": w["ptm"].notes["space"], "ridge": w["ptm"].notes["ridge"]}
    assert s["sh"].notes["space"] == w["sh"].notes["space"]
    # Each texel's fit reads only its own samples with the same float32 operations in both runs; bands change
    # only how texels are grouped into launches, so differences stay within a few float32 roundings of values
    # of order 1 (an 8-bit capture's samples are at most 1).
    a, b = streamed["ptm"]["model"], whole["ptm"]["model"]
    assert a.space == b.space
    np.testing.assert_allclose(a.coeffs, b.coeffs, rtol=0, atol=1e-5)
    a, b = streamed["sh"]["model"], whole["sh"]["model"]
    np.testing.assert_allclose(a.coeffs, b.coeffs, rtol=0, atol=1e-4 * max(1.0, float(np.abs(b.coeffs).max())))


def test_a_graph_that_needs_the_stack_whole_streams_nothing(capture, tmp_path):
    graph = _graph(capture, whole_reader=True)
    checked = check_graph(load_graph(graph), default_registry(), DEFAULT_OUT)
    order = checked.needed_for(None)
    assert btforge.streaming.streamed_outputs(checked, order, {"ptm", "sh", "split"}) == {}
    result = btforge.run(graph, out_dir=tmp_path, use_cache=False)
    assert result["split"]["fit"].n_light + result["split"]["test"].n_light == 14


def test_streaming_is_decided_from_the_readers(capture):
    registry = default_registry()

    def streamed(graph, targets):
        checked = check_graph(load_graph(graph), registry, DEFAULT_OUT)
        return btforge.streaming.streamed_outputs(checked, checked.needed_for(None), set(targets))

    assert streamed(_graph(capture), {"ptm", "sh"}) == {"read": frozenset({"stack"})}
    # the stack itself asked for as a result: it must be whole
    assert streamed(_graph(capture), {"ptm", "sh", "read"}) == {}
    # quantized SH scales over all texels: not per texel, so the stack is read whole
    assert streamed(_graph(capture, sh_params={"light_order": 3, "quantize": True}), {"ptm", "sh"}) == {}


def test_a_quantized_fit_beside_a_streamable_one_still_runs(capture, tmp_path):
    result = btforge.run(_graph(capture, sh_params={"light_order": 2, "quantize": True}), out_dir=tmp_path,
                         use_cache=False)
    nodes = _by_node(result)
    assert "streamed" not in nodes["read"].notes and nodes["sh"].placement == {"where": "local"}
    assert result["sh"]["model"].coeffs.dtype == np.uint8


def test_a_spilled_capture_reads_like_the_capture_in_memory(capture):
    """Bands, the texel grid auto judges on, and the whole stack of a capture decoded into a spill file are the
    samples load_stack gives, read by plain reads (never paging the capture in)."""
    from btforge.plugins.stackio.images import load_stack, load_stack_spilled
    whole = load_stack(capture)
    spilled = load_stack_spilled(capture, threads=2, min_bytes=0)
    assert spilled.chunked and not whole.chunked and spilled.type_name == "SampleStack"
    assert spilled.names == whole.names and np.array_equal(spilled.lights, whole.lights)
    for rows in (slice(0, 5), slice(5, 24), slice(23, 24)):
        np.testing.assert_array_equal(btforge.streaming.band_stack(spilled, rows).samples, whole.samples[:, :, rows])
    for step in (1, 3, 7):
        np.testing.assert_array_equal(spilled.texel_grid(step), whole.texel_grid(step))
    np.testing.assert_array_equal(np.asarray(spilled.in_memory().samples), whole.samples)


def test_spilled_arrays_move_by_plain_reads_and_writes():
    from btforge.spill import finite_range, pages, read_block, spilled_empty, write_items
    rng = np.random.default_rng(5)
    data = rng.standard_normal((2, 3, 7, 5, 2)).astype(np.float32)
    spilled = spilled_empty(data.shape, np.float32)
    write_items(spilled, 0, data.reshape(6, 7, 5, 2)[:4])  # items: images of views x lights
    write_items(spilled, 4, data.reshape(6, 7, 5, 2)[4:])
    np.testing.assert_array_equal(np.asarray(spilled), data)
    for axis, part in ((2, slice(2, 6)), (0, slice(1, 2)), (4, slice(0, 1))):
        index = (slice(None),) * axis + (part,)
        np.testing.assert_array_equal(read_block(spilled, axis, part), data[index])
    flat = np.concatenate([p.copy() for p in pages(spilled, page_bytes=100)])
    np.testing.assert_array_equal(flat, data.reshape(-1))
    assert finite_range(spilled)
    write_items(spilled, 5, np.full((1, 7, 5, 2), np.nan, np.float32))
    assert not finite_range(spilled)


def test_a_run_imports_no_subcommand_bench_or_networkx(capture, tmp_path):
    """Start-up: `btforge run` builds no plugin subcommand (the viewer's HTTP server), collects no bench and
    imports no networkx."""
    import subprocess
    import sys
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  read: {{stage: stackio.read, params: {{path: '{capture}'}}}}\n"
                     "  fit: {stage: ptm.fit, params: {space: srgb}, inputs: {stack: read.stack}}\n"
                     "  save: {stage: ptm.write, params: {path: out.ptm}, inputs: {model: fit.model}}\n")
    code = ("import sys; from btforge.cli import main\n"
            f"assert main(['run', {str(graph)!r}, '--no-cache', '--out', {str(tmp_path)!r}]) == 0\n"
            "loaded = sorted(m for m in sys.modules if m in ('http.server', 'numpy.ma', 'networkx')\n"
            "          or m.startswith('btforge.plugins.') and m.endswith('.bench'))\n"
            "print('loaded:', loaded)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "loaded: []" in proc.stdout, proc.stdout
    assert (tmp_path / "out.ptm").is_file()


def test_a_capture_under_the_streaming_size_is_held_in_memory(capture, tmp_path, monkeypatch):
    import btforge.plugins.stackio.images as images
    monkeypatch.setattr(images, "STREAM_MIN_BYTES", 64 << 20)
    result = btforge.run(_graph(capture), only=["ptm"], out_dir=tmp_path, use_cache=False)
    nodes = _by_node(result)
    assert nodes["read"].notes["streamed"] is False and nodes["ptm"].placement == {"where": "local"}
