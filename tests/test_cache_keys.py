"""Cache keys follow the code: editing a plugin's source or kernel re-runs its nodes; damaged entries are misses."""
import importlib
import shutil
import sys

import numpy as np
import pytest

import btforge
from btforge import BtforgeWarning
from btforge.registry import Registry

from conftest import REPO
from fixtures import toy_plugin

SMALL_DEMO = {"nodes": {"m": {"stage": "demo.material", "params": {"size": [6, 5], "lights": 3, "bumps": 2}}}}


@pytest.fixture
def demo_copy(tmp_path, monkeypatch):
    """A copy of the demo plugin as a package of its own (as a user's fork of a plugin would be)."""
    shutil.copytree(REPO / "plugins" / "demo", tmp_path / "pkgs" / "democopy",
                    ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.syspath_prepend(str(tmp_path / "pkgs"))
    module = importlib.import_module("democopy")
    yield tmp_path / "pkgs" / "democopy", module
    for name in [n for n in sys.modules if n == "democopy" or n.startswith("democopy.")]:
        del sys.modules[name]


def _statuses(result):
    return {r.node: r.status for r in result.report}


def test_editing_a_kernel_of_a_plugin_reruns_its_nodes(demo_copy, tmp_path):
    folder, module = demo_copy
    cache = tmp_path / "cache"
    first = btforge.run(SMALL_DEMO, registry=Registry(load_entry_points=False, extra_plugins=[module]),
                        cache_dir=cache)
    again = btforge.run(SMALL_DEMO, registry=Registry(load_entry_points=False, extra_plugins=[module]),
                        cache_dir=cache)
    assert _statuses(first) == {"m": "ran"} and _statuses(again) == {"m": "cached"}
    kernel = folder / "procedural.cl"
    kernel.write_text(kernel.read_text() + "\n// an edit that changes nothing computed still re-runs\n")
    edited = btforge.run(SMALL_DEMO, registry=Registry(load_entry_points=False, extra_plugins=[module]),
                         cache_dir=cache)
    assert _statuses(edited) == {"m": "ran"}
    np.testing.assert_array_equal(edited["m"]["stack"].samples, first["m"]["stack"].samples)


def test_editing_a_plugin_source_changes_only_its_stages_digest(demo_copy):
    folder, module = demo_copy
    def digests():
        registry = Registry(load_entry_points=False, extra_plugins=[module, toy_plugin])
        return {name: registry.code_digest(name) for name in ("demo.material", "demo.btf", "toy.source")}
    before = digests()
    (folder / "procedural.py").write_text((folder / "procedural.py").read_text() + "\n# edited\n")
    after = digests()
    assert before["demo.material"] != after["demo.material"] and before["demo.btf"] != after["demo.btf"]
    assert before["toy.source"] == after["toy.source"]


GRAPH = {"nodes": {"src": {"stage": "toy.source", "params": {"n": 6}},
                   "twice": {"stage": "toy.scale", "inputs": {"numbers": "src.numbers"}}}}


def test_a_flipped_byte_in_a_cached_output_is_recomputed_with_a_warning(tmp_path):
    registry = Registry(load_entry_points=False, extra_plugins=[toy_plugin])
    btforge.run(GRAPH, registry=registry, cache_dir=tmp_path)
    entry = sorted(tmp_path.rglob("numbers.npz"))[0]
    data = bytearray(entry.read_bytes())
    data[len(data) // 2] ^= 0x01  # same size, different content: only a checksum can tell
    entry.write_bytes(bytes(data))
    toy_plugin.CALLS.clear()
    with pytest.warns(BtforgeWarning, match="cache entry is damaged.*checksum"):
        result = btforge.run(GRAPH, registry=registry, cache_dir=tmp_path)
    assert sum(toy_plugin.CALLS.values()) == 1  # only the damaged node, not the healthy one
    np.testing.assert_array_equal(result["twice"]["numbers"].values, np.arange(6) * 2.0)
    damaged = [r for r in result.report if r.status == "ran"]
    assert len(damaged) == 1 and "damaged" in damaged[0].notes["warnings"][0]
    toy_plugin.CALLS.clear()
    btforge.run(GRAPH, registry=registry, cache_dir=tmp_path)
    assert toy_plugin.CALLS == {}  # the entry was rewritten whole


def test_version_still_overrides(tmp_path):
    import dataclasses
    registry = Registry(load_entry_points=False, extra_plugins=[toy_plugin])
    btforge.run(GRAPH, registry=registry, cache_dir=tmp_path)
    registry.stages["toy.source"] = dataclasses.replace(registry.stages["toy.source"], version="2")
    toy_plugin.CALLS.clear()
    btforge.run(GRAPH, registry=registry, cache_dir=tmp_path)
    assert toy_plugin.CALLS == {"toy.source": 1}  # same numbers again: what depends on them stays cached


def test_outputs_not_worth_storing_run_only_when_a_consumer_misses(tmp_path):
    import dataclasses
    registry = Registry(load_entry_points=False, extra_plugins=[toy_plugin])
    registry.stages["toy.source"] = dataclasses.replace(registry.stages["toy.source"], cache_outputs=False)
    first = btforge.run(GRAPH, registry=registry, cache_dir=tmp_path)
    assert _statuses(first) == {"src": "ran", "twice": "ran"}
    assert len(list(tmp_path.rglob("manifest.json"))) == 1  # only the consumer was stored
    toy_plugin.CALLS.clear()
    again = btforge.run(GRAPH, registry=registry, cache_dir=tmp_path)
    assert _statuses(again) == {"src": "not needed", "twice": "cached"} and toy_plugin.CALLS == {}
    changed = btforge.run(GRAPH, set={"src.n": 3}, registry=registry, cache_dir=tmp_path)
    assert _statuses(changed) == {"src": "ran", "twice": "ran"}
    np.testing.assert_array_equal(changed["twice"]["numbers"].values, [0, 2, 4])
    only_src = btforge.run(GRAPH, only=["src"], registry=registry, cache_dir=tmp_path)
    assert _statuses(only_src)["src"] == "ran"  # a requested output is always produced


def test_a_plugin_without_readable_source_is_keyed_by_its_distribution(monkeypatch):
    import importlib.metadata
    import types

    import btforge.cachekey as cachekey

    plugin = types.ModuleType("zipped_plugin")  # what a zipped install looks like: no files to hash
    plugin.BTFORGE_PLUGIN_API = 1

    @btforge.declare_stage("zipped.make", outputs={"numbers": "Numbers"})
    def make(ctx):
        """Make nothing."""
    make.fn.__module__ = "zipped_plugin"
    plugin.btforge_stages = btforge.hookimpl(lambda: [make])
    releases = {"1.0": "zipped_plugin/__init__.py,sha256=aaa,10\n", "1.1": "zipped_plugin/__init__.py,sha256=bbb,12\n"}

    def digest(version):
        dist = types.SimpleNamespace(version=version, read_text=lambda name: releases[version])
        monkeypatch.setattr(importlib.metadata, "packages_distributions", lambda: {"zipped_plugin": ["zipped"]})
        monkeypatch.setattr(importlib.metadata, "distribution", lambda name: dist)
        return Registry(load_entry_points=False, extra_plugins=[toy_plugin, plugin]).code_digest("zipped.make")
    assert digest("1.0") != digest("1.1")
    assert cachekey._distribution_fingerprint(types.ModuleType("nothing_installed")) == ""


def _package(root, name, files):
    for rel, text in files.items():
        (root / name / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / name / rel).write_text(text)


def test_editing_a_plugin_another_imports_changes_the_importers_digest(tmp_path, monkeypatch):
    """relight reads light files with stackio's reader: an edit to stackio must re-run relight's nodes too."""
    plugin = "from btforge import declare_stage, hookimpl\nBTFORGE_PLUGIN_API = 1\n"
    _package(tmp_path, "readerfam", {"__init__.py": plugin, "parse.py": "def parse():\n    return 1\n",
                                     "kernels/unused.py": "", "other.py": "def unrelated():\n    return 2\n"})
    _package(tmp_path, "userfam", {"__init__.py": plugin + (
        "from .steps import helper\n\n"
        "@declare_stage('user.stage', outputs={})\n"
        "def user_stage(ctx):\n    \"\"\"Use the reader.\"\"\"\n    return {}\n\n"
        "@hookimpl\ndef btforge_stages():\n    return [user_stage]\n"),
        "steps.py": "def helper():\n    from readerfam.parse import parse  # imported where used\n"
                    "    return parse()\n"})
    monkeypatch.syspath_prepend(str(tmp_path))
    modules = [importlib.import_module(name) for name in ("userfam", "readerfam")]

    def digests():
        registry = Registry(load_entry_points=False, extra_plugins=[*modules, toy_plugin])
        return {name: registry.code_digest(name) for name in ("user.stage", "toy.source")}
    try:
        before = digests()
        (tmp_path / "readerfam" / "other.py").write_text("def unrelated():\n    return 3\n")
        assert digests() == before  # userfam never imports it
        (tmp_path / "readerfam" / "parse.py").write_text("def parse():\n    return 2\n")
        after = digests()
        assert after["user.stage"] != before["user.stage"] and after["toy.source"] == before["toy.source"]
    finally:
        for name in [n for n in sys.modules if n.split(".")[0] in ("userfam", "readerfam")]:
            del sys.modules[name]


def test_relight_nodes_follow_the_stackio_reader_they_import():
    files, own = Registry().code_files("relight.images")
    lightfile = REPO / "plugins" / "stackio" / "lightfile.py"
    assert lightfile.resolve() in files and lightfile.resolve() not in own
    assert (REPO / "plugins" / "ptm" / "ptm.cl").resolve() not in files
