"""A lazy registry: plugins loaded when their names are asked for, with the answers of a registry that loads all."""
import os
import warnings

import pytest

from btforge import BtforgeInputError, plugin_index
from btforge.errors import DeprecatedNameWarning
from btforge.registry import ENTRY_POINT_GROUP, Registry, _api


def _lazy() -> Registry:
    """A lazy registry with the index in place (the first lazy registry of a cache root writes it)."""
    Registry(lazy=True)
    registry = Registry(lazy=True)
    assert registry._lazy is not None, "the index of the installed plugins was not written or not found"
    return registry


def _loaded(registry: Registry) -> set[str]:
    return {name for name, _ in registry.pm.list_name_plugin()}


def test_a_lazy_registry_loads_the_plugins_of_the_names_asked_for_and_all_when_listing():
    registry = _lazy()
    assert _loaded(registry) == set()
    assert registry.stage("ptm.fit").name == "ptm.fit"
    assert _loaded(registry) == {"ptm"}
    assert "PTMModel" in registry.types and registry.accepts("ReflectanceModel", "PTMModel")
    assert registry.types["SampleStack"].type_name == "SampleStack"  # a core type loads nothing
    assert _loaded(registry) == {"ptm"}
    everything = Registry()
    assert sorted(registry.stages) == sorted(everything.stages) and len(_loaded(registry)) > 2
    assert sorted(registry.types) == sorted(everything.types)
    assert registry.info_readers.keys() == everything.info_readers.keys()


def test_a_lazy_registry_answers_old_and_unknown_names_as_a_full_one():
    registry = _lazy()
    with pytest.warns(DeprecatedNameWarning, match="use 'stackio.read'"):
        assert registry.stage("stack.read").name == "stackio.read"
    assert _loaded(registry) == {"stackio"}
    with pytest.raises(BtforgeInputError) as lazy_error:
        _lazy().stage("ptm.fitt")
    with pytest.raises(BtforgeInputError) as full_error:
        Registry().stage("ptm.fitt")
    assert str(lazy_error.value) == str(full_error.value) and "did you mean 'ptm.fit'" in str(lazy_error.value)
    with pytest.raises(KeyError):
        _lazy().types["NoSuchModel"]


@pytest.mark.parametrize("stage", ["ptm.fit", "stackio.read", "sh.fit", "ptm.read", "relight.images"])
def test_code_digests_of_a_lazy_registry_equal_those_of_a_full_one(stage):
    """Cache keys follow a stage's imports into other plugins, loaded or not (stand-ins name their files)."""
    registry = _lazy()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        lazy = registry.code_files(stage), registry.code_digest(stage)
    assert len(_loaded(registry)) < len(Registry().pm.get_plugins())
    full = Registry()
    assert lazy == (full.code_files(stage), full.code_digest(stage))


def test_an_edited_plugin_changes_the_key_and_its_new_stage_is_found(tmp_path, monkeypatch):
    site = tmp_path / "site"
    info = site / "edited-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: edited\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\nedited = edited_plugin\n")
    package = site / "edited_plugin"
    package.mkdir()
    source = '''
from btforge import declare_stage, hookimpl
BTFORGE_PLUGIN_API = 1

@declare_stage("edited.{name}", outputs={{}})
def {name}(ctx):
    """A stage."""
    return {{}}

@hookimpl
def btforge_stages():
    return [{name}]
'''
    (package / "__init__.py").write_text(source.format(name="first"))
    monkeypatch.syspath_prepend(str(site))
    key = plugin_index.describe(ENTRY_POINT_GROUP, _api())[0]
    assert _lazy().stage("edited.first").name == "edited.first"
    (package / "__init__.py").write_text(source.format(name="second"))
    os.utime(package / "__init__.py", ns=(1, 1))  # even an old modification time: the size differs
    assert plugin_index.describe(ENTRY_POINT_GROUP, _api())[0] != key
    monkeypatch.delitem(__import__("sys").modules, "edited_plugin")
    registry = Registry(lazy=True)  # a key not seen before: everything is loaded, and the index rewritten
    assert registry._lazy is None and registry.find_stage("edited.first") is None
    assert _lazy().stage("edited.second").name == "edited.second"


def test_only_the_newest_indexes_are_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("BTFORGE_CACHE_DIR", str(tmp_path))
    for number in range(plugin_index.KEEP + 3):
        plugin_index.save(f"key{number}", {"ptm": {"stages": ["ptm.fit"], "types": []}})
        os.utime(tmp_path / "plugins" / f"key{number}.json", (number, number))
    kept = sorted(p.stem for p in (tmp_path / "plugins").glob("*.json"))
    assert len(kept) == plugin_index.KEEP and "key0" not in kept
    assert plugin_index.load(f"key{plugin_index.KEEP + 2}")["plugins"]["ptm"]["stages"] == ["ptm.fit"]
    assert plugin_index.load("key0") is None


def test_a_name_the_index_places_wrongly_is_found_by_loading_everything():
    registry = _lazy()
    registry._lazy["stackio"]["stages"].remove("stackio.read")
    registry._lazy["ptm"]["stages"].append("stackio.read")  # as if the stage had moved without the key changing
    assert registry.stage("stackio.read").name == "stackio.read"
    assert registry._lazy is None and "stackio" in _loaded(registry)
