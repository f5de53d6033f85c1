"""Renamed stages: the new name is listed, the old one still runs (graphs and btforge.stage), with a warning."""
import warnings

import pytest

import btforge
from btforge import BtforgeInputError, declare_stage
from btforge.errors import DeprecatedNameWarning
from btforge.registry import Registry

from fixtures import toy_plugin

BUILT_IN_RENAMES = {  # old name -> new name, as CHANGELOG.md lists them
    "coords.write": "synth.write_coords", "crop": "synth.crop", "materialize": "synth.materialize",
    "quilt": "synth.quilt", "kcoherence": "synth.kcoherence", "jumpmap": "synth.jumpmap", "score": "synth.score",
    "image.write": "render.write_image", "scene.read": "render.read_scene", "render": "render.image",
    "relight": "relight.images", "stack.compare": "relight.compare", "lights.calibrate": "calibrate.lights",
    "stack.normalize": "normalize.stack", "stack.read": "stackio.read", "stack.write": "stackio.write",
    "stack.contact_sheet": "stackio.contact_sheet", "stack.split": "stackio.split", "stack.import": "stackio.import",
    "stack.select": "stackio.select", "model.read": "models.read", "model.write": "models.write",
    "model.export_web": "web.export", "normals.write": "height.write_normals", "tiles.read": "wang.read_tiles",
    "tiles.write": "wang.write_tiles", "tiles.sheet": "wang.sheet",
}


def test_every_built_in_stage_is_named_after_its_family():
    reg = Registry()
    for name, st in reg.stages.items():
        family = st.fn.__module__.split(".")[2]  # btforge.plugins.<family>[.module]
        assert name.split(".")[0] == family, f"stage '{name}' lives in plugins/{family}/"


def test_old_names_resolve_to_the_renamed_stages_with_a_warning():
    reg = Registry()
    assert reg.aliases == BUILT_IN_RENAMES
    for old, new in BUILT_IN_RENAMES.items():
        assert old not in reg.stages
        with pytest.warns(DeprecatedNameWarning, match=f"stage '{old}' is deprecated, use '{new}'"):
            assert reg.stage(old) is reg.stages[new]


def test_a_graph_using_an_old_name_runs_and_reports_the_warning(tmp_path):
    graph = {"nodes": {
        "material": {"stage": "demo.material", "params": {"size": [16, 16], "lights": 8}},
        "split": {"stage": "stack.split", "params": {"every": 4}, "inputs": {"stack": "material.stack"}},
        "fit": {"stage": "ptm.fit", "inputs": {"stack": "split.fit"}},
        "heldout": {"stage": "relight", "inputs": {"model": "fit.model", "at": "split.test"}},
    }}
    with pytest.warns(DeprecatedNameWarning) as caught:
        result = btforge.run(graph, cache_dir=tmp_path / "cache", out_dir=tmp_path)
    texts = [str(w.message) for w in caught]
    assert any("node 'split'" in t and "stage 'stack.split' is deprecated, use 'stackio.split'" in t for t in texts)
    assert any("stage 'relight' is deprecated, use 'relight.images'" in t for t in texts)
    assert result["heldout"]["stack"].samples.shape[1] == 2
    report = {r.node: r for r in result.report}
    assert any("deprecated" in w for w in report["heldout"].notes["warnings"])
    assert report["heldout"].stage == "relight.images"


def test_old_and_new_names_give_the_same_cache_keys(tmp_path):
    def graph(split, relight):
        return {"nodes": {
            "material": {"stage": "demo.material", "params": {"size": [8, 8], "lights": 8}},
            "split": {"stage": split, "params": {"every": 4}, "inputs": {"stack": "material.stack"}},
            "fit": {"stage": "ptm.fit", "inputs": {"stack": "split.fit"}},
            "heldout": {"stage": relight, "inputs": {"model": "fit.model", "at": "split.test"}}}}
    btforge.run(graph("stackio.split", "relight.images"), cache_dir=tmp_path, out_dir=tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecatedNameWarning)
        again = btforge.run(graph("stack.split", "relight"), cache_dir=tmp_path, out_dir=tmp_path)
    assert {r.status for r in again.report} == {"cached"}


def test_an_old_name_that_another_stage_uses_is_refused():
    @declare_stage("other.numbers", outputs={"numbers": "Numbers"}, deprecated_names=("toy.source",))
    def numbers(ctx):
        """Nothing."""

    plugin = type("Plugin", (), {"BTFORGE_PLUGIN_API": 1,
                                 "btforge_stages": staticmethod(btforge.hookimpl(lambda: [numbers]))})
    with pytest.raises(BtforgeInputError, match="stage name 'toy.source'.*deprecated name of 'other.numbers'"):
        Registry(load_entry_points=False, extra_plugins=[toy_plugin, plugin])


def test_stages_lists_the_new_name_and_mentions_the_old(capsys):
    from btforge.cli import main
    assert main(["stages", "--markdown"]) == 0
    text = capsys.readouterr().out
    assert "#### `synth.score`" in text and "#### `score`" not in text
    assert "*Deprecated name: `score`" in text
    assert main(["stages", "score"]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("synth.score") and "deprecated name: score" in out
    assert "warning: stage 'score' is deprecated, use 'synth.score'" in err
