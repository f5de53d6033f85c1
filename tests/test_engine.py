"""The engine: plugin registration, demand-driven runs, content-addressed caching, reports, atomic writes."""
import json
import os

import numpy as np
import pytest

import btforge
from btforge import BtforgeError, BtforgeInputError
from btforge.atomic import atomic_write
from btforge.buffers import SampleStack
from btforge.registry import Registry

from fixtures import toy_plugin


@pytest.fixture
def registry():
    toy_plugin.CALLS.clear()
    return Registry(load_entry_points=True, extra_plugins=[toy_plugin])


GRAPH = {
    "nodes": {
        "src": {"stage": "toy.source", "params": {"n": 5}},
        "twice": {"stage": "toy.scale", "inputs": {"numbers": "src.numbers"}},
        "thrice": {"stage": "toy.scale", "params": {"factor": 3.0}, "inputs": {"numbers": "src.numbers"}},
        "sum": {"stage": "toy.add", "inputs": {"a": "twice.numbers", "b": "thrice.numbers"}},
        "text": {"stage": "toy.describe", "params": {"label": "total"}, "inputs": {"numbers": "sum.numbers"}},
        "side": {"stage": "toy.scale", "params": {"factor": -1.0}, "inputs": {"numbers": "src.numbers"}},
    }
}


def test_builtin_families_come_from_entry_points():
    reg = Registry()
    assert {"stackio.read", "stackio.write", "ptm.fit", "ptm.read", "ptm.write", "relight.images"} <= set(reg.stages)
    assert {"SampleStack", "PTMModel", "ReflectanceModel"} <= set(reg.types)


def test_run_returns_typed_buffers_of_requested_nodes(registry, tmp_path):
    result = btforge.run(GRAPH, only=["text"], registry=registry, cache_dir=tmp_path)
    assert set(result) == {"text"}
    assert result["text"]["text"].text == "total: 50.0"
    status = {r.node: r.status for r in result.report}
    assert status["side"] == "not needed"  # demand-driven: nothing else is computed
    assert toy_plugin.CALLS == {"toy.source": 1, "toy.scale": 2, "toy.add": 1, "toy.describe": 1}


def test_default_targets_are_the_sinks(registry, tmp_path):
    result = btforge.run(GRAPH, registry=registry, cache_dir=tmp_path)
    assert set(result) == {"text", "side"}


def test_changed_param_reruns_only_what_depends_on_it(registry, tmp_path):
    btforge.run(GRAPH, only=["text"], registry=registry, cache_dir=tmp_path)
    toy_plugin.CALLS.clear()
    result = btforge.run(GRAPH, only=["text"], set={"thrice.factor": 4.0}, registry=registry, cache_dir=tmp_path)
    status = {r.node: r.status for r in result.report}
    assert status == {"src": "cached", "twice": "cached", "thrice": "ran", "sum": "ran", "text": "ran",
                      "side": "not needed"}
    assert result["text"]["text"].text == "total: 60.0"
    # a cached upstream node is never loaded when only its content key is needed... but its output is when used
    assert toy_plugin.CALLS == {"toy.scale": 1, "toy.add": 1, "toy.describe": 1}


def test_second_identical_run_is_all_cache_hits(registry, tmp_path):
    first = btforge.run(GRAPH, only=["text"], registry=registry, cache_dir=tmp_path)
    toy_plugin.CALLS.clear()
    second = btforge.run(GRAPH, only=["text"], registry=registry, cache_dir=tmp_path)
    assert toy_plugin.CALLS == {}
    assert second["text"]["text"].text == first["text"]["text"].text
    assert {r.status for r in second.report} == {"cached", "not needed"}
    assert second.report[-2].notes["total"] == 50.0  # notes survive the cache


def test_half_written_cache_entry_is_a_miss(registry, tmp_path):
    btforge.run(GRAPH, only=["src"], registry=registry, cache_dir=tmp_path)
    for manifest in tmp_path.rglob("manifest.json"):
        manifest.unlink()  # what a crash between the data and the manifest leaves behind
    toy_plugin.CALLS.clear()
    btforge.run(GRAPH, only=["src"], registry=registry, cache_dir=tmp_path)
    assert toy_plugin.CALLS == {"toy.source": 1}


def test_damaged_cache_output_is_a_miss(registry, tmp_path):
    btforge.run(GRAPH, only=["src"], registry=registry, cache_dir=tmp_path)
    for data in tmp_path.rglob("numbers.npz"):
        data.write_bytes(data.read_bytes()[:20])  # e.g. a disk that filled up under another tool
    toy_plugin.CALLS.clear()
    result = btforge.run(GRAPH, only=["src"], registry=registry, cache_dir=tmp_path)
    assert toy_plugin.CALLS == {"toy.source": 1}
    np.testing.assert_array_equal(result["src"]["numbers"].values, np.arange(5))


def test_a_node_feeding_two_ports_and_another_node(registry, tmp_path):
    graph = {"nodes": {
        "src": {"stage": "toy.source", "params": {"n": 3}},
        "sum": {"stage": "toy.add", "inputs": {"a": "src.numbers", "b": "src.numbers"}},
        "twice": {"stage": "toy.scale", "inputs": {"numbers": "src.numbers"}},
    }}
    result = btforge.run(graph, registry=registry, cache_dir=tmp_path)
    np.testing.assert_array_equal(result["sum"]["numbers"].values, [0, 2, 4])
    np.testing.assert_array_equal(result["twice"]["numbers"].values, [0, 2, 4])


def test_edited_input_file_reruns_even_with_its_old_mtime(registry, tmp_path):
    data = tmp_path / "numbers.txt"
    data.write_text("1\n2\n")
    graph_file = tmp_path / "g.yaml"
    graph_file.write_text("nodes:\n  read: {stage: toy.read, params: {path: numbers.txt}}\n")
    first = btforge.run(graph_file, registry=registry, cache_dir=tmp_path / "cache")
    np.testing.assert_array_equal(first["read"]["numbers"].values, [1, 2])
    stamp = data.stat()
    data.write_text("5\n6\n")  # same size; then the old times put back, as `cp -p` or `rsync -t` would
    os.utime(data, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
    toy_plugin.CALLS.clear()
    second = btforge.run(graph_file, registry=registry, cache_dir=tmp_path / "cache")
    assert toy_plugin.CALLS == {"toy.read": 1}
    np.testing.assert_array_equal(second["read"]["numbers"].values, [5, 6])
    toy_plugin.CALLS.clear()
    btforge.run(graph_file, registry=registry, cache_dir=tmp_path / "cache")
    assert toy_plugin.CALLS == {}  # unchanged: a hit, with the digest remembered


def test_a_crashing_stage_is_reported_by_node(registry, tmp_path):
    graph = {"nodes": {"src": {"stage": "toy.source"}, "bad": {"stage": "toy.crash", "inputs": {"numbers": "src.numbers"}}}}
    with pytest.raises(BtforgeError, match=r"node 'bad' \(toy.crash, plugin .*\) failed: IndexError") as info:
        btforge.run(graph, registry=registry, cache_dir=tmp_path)
    assert isinstance(info.value.__cause__, IndexError)


def test_report_file(registry, tmp_path):
    report = tmp_path / "report.json"
    btforge.run(GRAPH, only=["sum"], registry=registry, cache_dir=tmp_path / "c", report_path=report)
    data = json.loads(report.read_text())
    rows = {r["node"]: r for r in data["nodes"]}
    assert rows["sum"]["status"] == "ran" and rows["sum"]["seconds"] >= 0 and rows["sum"]["peak_rss_mb"] > 0
    assert rows["text"]["status"] == "not needed"


def test_plugin_returning_the_wrong_type_is_caught(registry, tmp_path):
    with pytest.raises(BtforgeError, match="returned Text on port 'numbers', declared Numbers"):
        btforge.run({"nodes": {"b": {"stage": "toy.broken"}}}, registry=registry, cache_dir=tmp_path)


def test_stage_callable_directly():
    ptm_fit = btforge.stage("ptm.fit")
    rng = np.random.default_rng(1)
    lights = np.column_stack([rng.uniform(-0.6, 0.6, (12, 2)), np.ones(12)])
    stack = SampleStack(rng.uniform(0, 1, (1, 12, 4, 5, 3)).astype(np.float32), lights, [[0, 0, 1]])
    model = ptm_fit(stack=stack, variant="lrgb")["model"]
    assert model.coeffs.shape == (4, 5, 1, 6)
    with pytest.raises(BtforgeInputError, match="expected rgb\\|lrgb"):
        ptm_fit(stack=stack, variant="xyz")


def test_unknown_stage_has_did_you_mean():
    with pytest.raises(BtforgeInputError, match="did you mean 'ptm.fit'"):
        btforge.stage("ptm.fitt")


def test_duplicate_stage_names_are_refused():
    class Clash:
        BTFORGE_PLUGIN_API = 1

        @staticmethod
        @btforge.hookimpl
        def btforge_stages():
            return [toy_plugin.source]
    with pytest.raises(BtforgeInputError, match="is defined by both"):
        Registry(load_entry_points=False, extra_plugins=[toy_plugin, Clash])


def test_buffer_type_name_clashes_are_refused():
    import dataclasses
    from typing import ClassVar

    @dataclasses.dataclass(frozen=True, eq=False)
    class OtherNumbers(btforge.buffers.Buffer):
        type_name: ClassVar[str] = "Numbers"

    class Clash:
        BTFORGE_PLUGIN_API = 1

        @staticmethod
        @btforge.hookimpl
        def btforge_buffer_types():
            return [OtherNumbers]
    with pytest.raises(BtforgeInputError, match="buffer type 'Numbers'.*defined by both"):
        Registry(load_entry_points=False, extra_plugins=[toy_plugin, Clash])


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_float_params_are_refused(registry, tmp_path, value):
    graph = {"nodes": {"m": {"stage": "demo.material", "params": {"min_elevation": value}}}}
    with pytest.raises(BtforgeInputError, match="param 'min_elevation'.*expected float in"):
        btforge.run(graph, registry=registry, cache_dir=tmp_path)


def test_cli_stages_refuses_an_unknown_name():
    import subprocess
    import sys
    proc = subprocess.run([sys.executable, "-m", "btforge.cli", "stages", "relite"], capture_output=True, text=True)
    assert proc.returncode == 2 and "did you mean 'relight.images'" in proc.stderr


def test_buffers_are_immutable_and_validated():
    samples = np.zeros((1, 3, 2, 2, 3), np.float32)
    stack = SampleStack(samples, np.eye(3), [[0, 0, 1]])
    key = stack.content_key
    with pytest.raises(ValueError):
        stack.samples[0, 0, 0, 0, 0] = 1.0
    with pytest.raises(ValueError):  # nor through the array it was made from
        samples[0, 0, 0, 0, 0] = 1.0
    base = np.zeros((2, 3, 2, 2, 3), np.float32)
    from_view = SampleStack(base[1:], np.eye(3), [[0, 0, 1]])
    base[1] = 7.0  # a view's base stays the caller's: the buffer holds a copy
    assert not from_view.samples.any() and from_view.content_key == key
    whole = np.zeros((3, 2, 2, 3), np.float32)
    reshaped = SampleStack(whole[None], np.eye(3), [[0, 0, 1]])  # a view of all of it: frozen, not copied
    assert np.shares_memory(reshaped.samples, whole) and not whole.flags.writeable
    with pytest.raises(BtforgeInputError, match=r"'samples' must be \(V, L, H, W, C\) float32, got \(2, 2, 9\) float64"):
        SampleStack(np.zeros((2, 2, 9)), np.eye(3), [[0, 0, 1]])
    bad = np.zeros((1, 3, 2, 2, 3), np.float32)
    bad[0, 1, 1, 0, 2] = np.nan
    with pytest.raises(BtforgeInputError, match=r"light 1.*row 1, column 0"):
        SampleStack(bad, np.eye(3), [[0, 0, 1]])


def test_stack_refuses_directions_below_the_horizon():
    with pytest.raises(BtforgeInputError, match=r"'lights' must lie on the upper hemisphere.*row 1"):
        SampleStack(np.zeros((1, 2, 2, 2, 3), np.float32), [[0, 0, 1], [0.5, 0, -0.5]], [[0, 0, 1]])


def test_content_key_follows_content():
    a = SampleStack(np.zeros((1, 3, 2, 2, 3), np.float32), np.eye(3), [[0, 0, 1]])
    b = SampleStack(np.zeros((1, 3, 2, 2, 3), np.float32), np.eye(3), [[0, 0, 1]])
    c = SampleStack(np.ones((1, 3, 2, 2, 3), np.float32), np.eye(3), [[0, 0, 1]])
    assert a.content_key == b.content_key != c.content_key


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_write(target) as handle:
            handle.write(b"half")
            raise RuntimeError("crash mid-write")
    assert target.read_bytes() == b"old"
    assert os.listdir(tmp_path) == ["out.bin"]


def test_ports_that_depend_on_params(registry, tmp_path):
    graph = {"nodes": {
        "src": {"stage": "toy.source", "params": {"n": 3}},
        "sum": {"stage": "toy.total", "params": {"names": ["a", "b"]},
                "inputs": {"a": "src.numbers", "b": "src.numbers"}},
    }}
    result = btforge.run(graph, registry=registry, cache_dir=tmp_path)
    np.testing.assert_array_equal(result["sum"]["numbers"].values, [0, 2, 4])
    graph["nodes"]["sum"]["inputs"] = {"a": "src.numbers"}
    with pytest.raises(BtforgeInputError, match="input port 'b' \\(Numbers\\) is not wired"):
        btforge.run(graph, registry=registry, cache_dir=tmp_path)
    graph["nodes"]["sum"]["inputs"] = {"a": "src.numbers", "b": "src.numbers", "c": "src.numbers"}
    with pytest.raises(BtforgeInputError, match="has no input port 'c'"):
        btforge.run(graph, registry=registry, cache_dir=tmp_path)


def test_outputs_typed_like_an_input_keep_the_wired_type(tmp_path):
    graph = {"nodes": {
        "material": {"stage": "demo.material", "params": {"size": [12, 12], "lights": 8}},
        "fit": {"stage": "ptm.fit", "inputs": {"stack": "material.stack"}},
        "patch": {"stage": "synth.crop", "params": {"origin": [2, 3], "size": [5, 6]}, "inputs": {"input": "fit.model"}},
        "relit": {"stage": "relight.images", "params": {"lights": [[0, 0, 1]]}, "inputs": {"model": "patch.output"}},
    }}
    result = btforge.run(graph, cache_dir=tmp_path)
    assert result["relit"]["stack"].samples.shape == (1, 1, 5, 6, 3)
    graph["nodes"]["patch"]["inputs"] = {"input": "material.stack"}  # a cropped stack is no model
    with pytest.raises(BtforgeInputError, match="expects ReflectanceModel, but 'patch.output' gives SampleStack"):
        btforge.run(graph, cache_dir=tmp_path)


def test_blending_integer_records_rounds():
    from btforge.buffers import CoordMap
    stack = SampleStack(np.array([10, 13], np.uint8).reshape(1, 1, 2, 1, 1), [[0, 0, 1]], [[0, 0, 1]], ("Y",),
                        encoding="srgb8")
    blend = CoordMap(np.zeros((1, 1, 2), np.int32), (2, 1), np.array([[[1, 0]]], np.int32),
                     np.array([[0.5]], np.float32))
    assert blend.apply(stack).samples[0, 0, 0, 0, 0] == 12  # 11.5 rounds to the even code; truncation gives 11


def test_non_linear_models_take_the_heavier_texel():
    from btforge.buffers import CoordMap
    from btforge.plugins.lafortune.model import LafortuneModel
    normals = np.array([[[0, 0, 1]], [[0.6, 0, 0.8]]], np.float32)                    # [2, 1, 3]
    model = LafortuneModel(normals, np.array([[[0.2]], [[0.4]]], np.float32),
                           np.array([[[[-1, -1, 1]]], [[[-0.5, -0.5, 0.9]]]], np.float32),
                           np.array([[[10.0]], [[200.0]]], np.float32), np.full((2, 1, 3), 0.8, np.float32), "lum")
    blend = CoordMap(np.zeros((1, 1, 2), np.int32), (2, 1), np.array([[[1, 0]]], np.int32),
                     np.array([[0.7]], np.float32))
    out = blend.apply(model)
    for name in LafortuneModel.texel_fields:
        np.testing.assert_array_equal(getattr(out, name)[0, 0], getattr(model, name)[1, 0])
