"""A PTM written to a .ptm file is fitted in the space the file holds: ``ptm.fit`` left at ``space: auto`` feeding
``ptm.write`` fits display values (the graph check narrows its choice, the report says why), an explicit
``space: linear`` feeding it is refused before anything runs, and ``auto`` chooses freely elsewhere."""
from pathlib import Path

import numpy as np
import pytest

import btforge
from btforge import AUTO, Param, declare_stage
from btforge.cli import main
from btforge.graph import check_graph, load_graph
from btforge.registry import default_registry
from btforge.plugins.ptm.bench import make_synthetic_capture


@pytest.fixture(scope="module")
def rendered_capture(tmp_path_factory) -> Path:
    """A rendered 32 x 32 x 38-light JPEG capture: radiance linear in n . l, on which ``auto`` picks linear."""
    return make_synthetic_capture(tmp_path_factory.mktemp("capture"), 32, 38)


def three_nodes(lp: Path, fit_params: dict | None = None, writer: str = "ptm.write", path: str = "m.ptm") -> dict:
    return {"nodes": {
        "read": {"stage": "stackio.read", "params": {"path": str(lp)}},
        "fit": {"stage": "ptm.fit", "params": dict(fit_params or {}), "inputs": {"stack": "read.stack"}},
        "write": {"stage": writer, "params": {"path": path}, "inputs": {"model": "fit.model"}}}}


def checked(graph: dict):
    return check_graph(load_graph(graph), default_registry())


def test_auto_picks_linear_on_the_rendered_capture_when_nothing_constrains_it(rendered_capture, tmp_path):
    graph = three_nodes(rendered_capture, writer="models.write", path="m.btfm")
    assert checked(graph).params["fit"]["space"] == AUTO  # models.write stores either space: no narrowing
    result = btforge.run(graph, out_dir=tmp_path, cache_dir=tmp_path / "cache", only=["fit", "write"])
    assert result["fit"]["model"].space == "linear"
    fit_report = next(r for r in result.report if r.node == "fit")
    assert not any("(auto)" in key for key in fit_report.notes), fit_report.notes


def test_the_default_graph_writes_a_ptm_fitted_in_display_values(rendered_capture, tmp_path):
    graph = three_nodes(rendered_capture)
    assert checked(graph).params["fit"]["space"] == "srgb"
    result = btforge.run(graph, out_dir=tmp_path, cache_dir=tmp_path / "cache", only=["fit", "write"])
    model = result["fit"]["model"]
    assert model.space == "srgb"
    fit_report = next(r for r in result.report if r.node == "fit")
    why = fit_report.notes["space (auto)"]
    assert "srgb" in why and "'write'" in why and "ptm.write" in why, why
    written = btforge.stage("ptm.read")(path=str(tmp_path / "m.ptm"))["model"]
    lights = np.array([[0.0, 0.0, 1.0], [0.5, 0.3, 0.81]], np.float32)
    relit, relit_written = model.evaluate(lights, engine="numpy"), written.evaluate(lights, engine="numpy")
    # the file quantises each coefficient to 8 bits over its range: one display step, decoded near 1
    assert np.max(np.abs(relit - relit_written)) < 0.03


def test_the_cli_writes_the_ptm_and_says_why_srgb(rendered_capture, tmp_path, capsys):
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  read: {{stage: stackio.read, params: {{path: '{rendered_capture}'}}}}\n"
                     "  fit: {stage: ptm.fit, inputs: {stack: read.stack}}\n"
                     "  write: {stage: ptm.write, params: {path: m.ptm}, inputs: {model: fit.model}}\n")
    assert main(["run", str(graph), "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache")]) == 0
    assert (tmp_path / "out" / "m.ptm").stat().st_size > 0
    assert "space (auto): srgb, as node 'write' (ptm.write) takes space srgb only" in capsys.readouterr().err


@pytest.mark.parametrize("fit", ["ptm.fit", "ptm.fit_capture"])
def test_explicit_linear_into_ptm_write_is_refused_before_anything_runs(rendered_capture, tmp_path, capsys, fit):
    wiring = "inputs: {stack: read.stack}" if fit == "ptm.fit" else f"params: {{path: '{rendered_capture}'}}"
    space = "{space: linear}" if fit == "ptm.fit" else f"{{path: '{rendered_capture}', space: linear}}"
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  read: {{stage: stackio.read, params: {{path: '{rendered_capture}'}}}}\n"
                     f"  fit: {{stage: {fit}, {wiring}, params: {space}}}\n"
                     "  write: {stage: ptm.write, params: {path: m.ptm}, inputs: {model: fit.model}}\n"
                     if fit == "ptm.fit" else
                     f"nodes:\n  fit: {{stage: {fit}, params: {space}}}\n"
                     "  write: {stage: ptm.write, params: {path: m.ptm}, inputs: {model: fit.model}}\n")
    code = main(["run", str(graph), "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache")])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "node 'write', input 'model'" in err and "ptm.write expects space: srgb, found linear in 'fit.model'" in err
    assert "node 'fit', param 'space'" in err and "space: srgb" in err and "models.write" in err, err
    assert "Traceback" not in err and "[1/" not in err  # refused by the check: no node started
    assert not (tmp_path / "out" / "m.ptm").exists()


def test_the_choice_is_narrowed_through_stages_that_keep_the_space(rendered_capture):
    graph = three_nodes(rendered_capture)
    graph["nodes"]["basis"] = {"stage": "ptm.basis", "inputs": {"model": "fit.model"}}
    graph["nodes"]["write"]["inputs"] = {"model": "basis.model"}
    assert checked(graph).params["fit"]["space"] == "srgb"
    graph["nodes"]["fit"]["params"] = {"space": "linear"}
    with pytest.raises(btforge.BtforgeInputError) as refused:
        checked(graph)
    assert "found linear in 'basis.model'" in str(refused.value) and "node 'fit', param 'space'" in str(refused.value)


def test_one_fit_feeding_the_ptm_writer_and_another_writer_fits_srgb_for_both(rendered_capture):
    graph = three_nodes(rendered_capture)
    graph["nodes"]["keep"] = {"stage": "models.write", "params": {"path": "m.btfm"}, "inputs": {"model": "fit.model"}}
    graph["nodes"]["relit"] = {"stage": "relight.images", "params": {"lights": [[0, 0, 1]]},
                               "inputs": {"model": "fit.model"}}
    assert checked(graph).params["fit"]["space"] == "srgb"


def test_facts_from_params_must_name_an_output_and_a_param():
    def fit(ctx, *, space):
        return {}
    with pytest.raises(TypeError, match="facts_from_params"):
        declare_stage("toy.fit", outputs={"model": "PTMModel"}, facts_from_params={"model": {"space": "colour"}},
                      params=[Param("space", "choice", AUTO, "the space", choices=(AUTO, "srgb"))])(fit)
    with pytest.raises(TypeError, match="facts_from_params"):
        declare_stage("toy.fit", outputs={"model": "PTMModel"}, facts_from_params={"coeffs": {"space": "space"}},
                      params=[Param("space", "choice", AUTO, "the space", choices=(AUTO, "srgb"))])(fit)


# the mechanism itself, on toy stages the framework knows nothing of

def toy_registry():
    from btforge.registry import Registry
    from fixtures import toy_facts_plugin, toy_plugin
    return Registry(load_entry_points=False, extra_plugins=[toy_plugin, toy_facts_plugin])


def toy_graph(unit=None, consumers=("toyfacts.in_metres",), through_keep=False):
    nodes = {"measure": {"stage": "toyfacts.measure", "params": {"unit": unit} if unit else {}}}
    source = "measure.numbers"
    if through_keep:
        nodes["keep"] = {"stage": "toyfacts.keep", "inputs": {"numbers": source}}
        source = "keep.numbers"
    for index, stage in enumerate(consumers):
        nodes[f"use{index}"] = {"stage": stage, "inputs": {"numbers": source}}
    return {"nodes": nodes}


@pytest.mark.parametrize("through_keep", [False, True])
def test_auto_is_narrowed_to_what_the_consumer_takes_and_the_run_notes_why(tmp_path, through_keep):
    registry = toy_registry()
    graph = toy_graph(through_keep=through_keep)
    assert check_graph(load_graph(graph), registry).params["measure"]["unit"] == "m"
    result = btforge.run(graph, registry=registry, out_dir=tmp_path, cache_dir=tmp_path / "cache")
    np.testing.assert_array_equal(result["use0"]["numbers"].values, [1.0, 2.0])
    notes = next(r.notes for r in result.report if r.node == "measure")
    assert notes["unit"] == "m" and notes["unit (auto)"] == "m, as node 'use0' (toyfacts.in_metres) takes unit m only"
    free = {"nodes": {"measure": graph["nodes"]["measure"]}}  # no consumer: auto decides for itself
    assert check_graph(load_graph(free), registry).params["measure"]["unit"] == AUTO
    assert btforge.run(free, registry=registry, out_dir=tmp_path, use_cache=False)["measure"]["numbers"].values[0] == 100


def test_an_explicit_value_the_consumer_does_not_take_is_refused_naming_both_nodes():
    with pytest.raises(btforge.BtforgeInputError) as refused:
        check_graph(load_graph(toy_graph("cm", through_keep=True)), toy_registry())
    text = refused.value.render()
    assert "node 'use0', input 'numbers': toyfacts.in_metres expects unit: m, found cm in 'keep.numbers'" in text
    assert "node 'measure', param 'unit'" in text and "measure with `unit: m`" in text


def test_consumers_that_disagree_are_refused_with_the_narrowing_named():
    with pytest.raises(btforge.BtforgeInputError) as refused:
        check_graph(load_graph(toy_graph(consumers=("toyfacts.in_metres", "toyfacts.in_cm"))), toy_registry())
    text = refused.value.render()
    assert "toyfacts.in_cm expects unit: cm, found m in 'measure.numbers'" in text
    assert "auto narrowed to m, as node 'use0' (toyfacts.in_metres)" in text


def test_the_documented_capture_maker_creates_its_folder(tmp_path):
    """docs/benchmarks.md makes the 1024^2 capture with ``make_synthetic_capture(Path('/tmp/cap'), ...)`` on a
    machine where that folder does not exist yet."""
    lp = make_synthetic_capture(tmp_path / "new" / "cap", 8, 3)
    assert lp.is_file() and len(list(lp.parent.glob("light_*.jpg"))) == 3
