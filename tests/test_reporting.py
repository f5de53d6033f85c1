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
    graph.write_text("nodes:\n  read: {stage: stackio.read, params: {path: dirs.lp}}\n"
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


def test_cached_nodes_report_the_notes_they_ran_with(tmp_path, capsys):
    """A re-run serves every node from the cache; each reports the same notes (scores, counts) as when it ran,
    in the report file, in the table and in the Python result."""
    from btforge.cli import main
    graph = tmp_path / "g.yaml"
    graph.write_text("""nodes:
  material: {stage: demo.material, params: {size: [24, 24], lights: 12, bumps: 4}}
  split:    {stage: stackio.split, params: {every: 3}, inputs: {stack: material.stack}}
  fit:      {stage: ptm.fit, inputs: {stack: split.fit}}
  test:     {stage: relight.images, inputs: {model: fit.model, at: split.test}}
  compare:  {stage: relight.compare, inputs: {stack: test.stack, reference: split.test}}
  quilt:    {stage: synth.quilt, params: {size: [24, 24], block: 8, overlap: 2}, inputs: {exemplar: fit.model}}
  texture:  {stage: synth.materialize, inputs: {coords: quilt.coords, source: fit.model}}
  score:    {stage: synth.score, params: {samples: 64, projections: 8},
             inputs: {output: texture.output, coords: quilt.coords, exemplar: fit.model}}
""")
    reports, tables = [], []
    for run in range(2):
        report = tmp_path / f"report{run}.json"
        assert main(["run", str(graph), "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache"),
                     "--report", str(report)]) == 0
        reports.append({n["node"]: n for n in json.loads(report.read_text())["nodes"]})
        tables.append([line.split(None, 6) for line in capsys.readouterr().err.splitlines()
                       if line.split()[:1] in (["compare"], ["score"])])
    assert {n["status"] for n in reports[1].values()} == {"cached"}
    for node in ("compare", "score"):
        assert reports[0][node]["notes"] == reports[1][node]["notes"], node
    assert "psnr_db" in reports[1]["compare"]["notes"] and "swd" in reports[1]["score"]["notes"]
    assert [row[6] for row in tables[0]] == [row[6] for row in tables[1]]   # the notes column (after "where")
    again = btforge.run(graph, out_dir=tmp_path / "out", cache_dir=tmp_path / "cache")
    assert {r.node: r.notes for r in again.report} == {name: n["notes"] for name, n in reports[0].items()}


def test_run_ends_with_the_files_it_wrote(tmp_path, monkeypatch, capsys):
    """The last lines of `btforge run` name what it wrote, relative to the current folder; an output folder of
    many files is one line with its count."""
    from btforge.cli import main
    monkeypatch.chdir(tmp_path)
    (tmp_path / "g.yaml").write_text("""nodes:
  material: {stage: demo.material, params: {size: [8, 8], lights: 6, bumps: 2}}
  images:   {stage: stackio.write, params: {dir: relit, format: exr}, inputs: {stack: material.stack}}
  sheet:    {stage: stackio.contact_sheet, params: {path: sheet.png}, inputs: {stack: material.stack}}
""")
    assert main(["run", "g.yaml", "--out", "results", "--cache", str(tmp_path / "cache")]) == 0
    tail = capsys.readouterr().err.splitlines()
    start = tail.index("wrote:")
    assert sorted(tail[start + 1:]) == ["  results/relit/ (7 files)", "  results/sheet.png"]
