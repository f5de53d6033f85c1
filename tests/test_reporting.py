"""All problems at once and nothing lost from the report: every node's prechecks run, read warnings are kept."""
import json

import numpy as np
import pytest
from PIL import Image

import btforge
from btforge import BtforgeInputError, BtforgeWarning


def _capture(folder, rows):
    for name, _ in rows:
        Image.fromarray(np.full((4, 5, 3), 120, np.uint8)).save(folder / name)
    lp = folder / "dirs.lp"
    lp.write_text(f"{len(rows)}\n" + "".join(f"{n} {x} {y} {z}\n" for n, (x, y, z) in rows))
    return lp


def test_the_graph_check_prechecks_every_node_even_when_another_failed(tmp_path):
    lp = _capture(tmp_path, [("a.png", (0, 0, 1)), ("b.png", (0.5, 0, 0.866))])
    (tmp_path / "b.png").unlink()
    graph = tmp_path / "g.yaml"
    graph.write_text("nodes:\n  read: {stage: stack.read, params: {path: dirs.lp}}\n"
                     "  fit: {stage: ptm.fitt, inputs: {stack: read.stack}}\n")
    with pytest.raises(BtforgeInputError) as info:
        btforge.run(graph, cache_dir=tmp_path / "cache")
    text = str(info.value)
    assert "2 problems" in text and "unknown stage 'ptm.fitt'" in text
    assert f"{lp}, line 3: expected the image 'b.png'" in text


def test_warnings_raised_while_a_file_is_read_are_in_the_report(tmp_path):
    _capture(tmp_path, [("a.png", (0, 0, 1)), ("b.png", (0.5, 0, -0.005)), ("c.png", (0, 0.6, 0.8)),
                        ("d.png", (-0.6, 0, 0.8)), ("e.png", (0, -0.6, 0.8)), ("f.png", (0.4, 0.4, 0.82))])
    graph = {"nodes": {"read": {"stage": "stackio.read", "params": {"path": str(tmp_path / "dirs.lp")}},
                       "fit": {"stage": "ptm.fit", "inputs": {"stack": "read.stack"}}}}
    # The second time the fit comes from the cache and the capture is not read again (stack.read does not
    # store its outputs), but the warning of the graph check's reading is still reported.
    for expected in ({"read": "ran", "fit": "ran"}, {"read": "not needed", "fit": "cached"}):
        with pytest.warns(BtforgeWarning, match="below the horizon; clamped"):
            result = btforge.run(graph, cache_dir=tmp_path / "cache", report_path=tmp_path / "report.json")
        nodes = {n["node"]: n for n in json.loads((tmp_path / "report.json").read_text())["nodes"]}
        assert {name: n["status"] for name, n in nodes.items()} == expected
        assert len(nodes["read"]["notes"]["warnings"]) == 1 and "clamped to z = 0" in nodes["read"]["notes"]["warnings"][0]
    assert result.report[0].notes["warnings"] == nodes["read"]["notes"]["warnings"]
