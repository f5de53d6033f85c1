"""model.write / model.read: exact round trips of every representation, versions, damage, btforge info."""
import json
import zipfile

import numpy as np
import pytest

import btforge
from btforge import BtforgeInputError
from btforge.cli import main
from btforge.plugins.models.modelfile import FORMAT_VERSION, read_model, write_model
from btforge.registry import default_registry


@pytest.fixture(scope="module")
def btf():
    return btforge.stage("demo.btf")(size=[6, 5], lights=12, views=4, seed=2)["stack"]


def _models(btf):
    top = btforge.stage("stackio.select")(stack=btf, views=[0])["stack"]
    yield "ptm rgb", btforge.stage("ptm.fit")(stack=top)["model"]
    yield "ptm lrgb orthonormal", btforge.stage("ptm.fit")(stack=top, variant="lrgb", basis="orthonormal")["model"]
    yield "sh", btforge.stage("sh.fit")(stack=btf, light_order=3, view_order=2)["model"]
    yield "sh quantized", btforge.stage("sh.fit")(stack=btf, light_order=3, view_order=2, quantize=True)["model"]
    yield "lafortune", btforge.stage("lafortune.fit")(stack=top, iterations=5)["model"]


def test_every_representation_round_trips_exactly(btf, tmp_path):
    types = default_registry().types
    for label, model in _models(btf):
        path = tmp_path / f"{label.replace(' ', '_')}.btfm"
        btforge.stage("models.write")(model=model, path=str(path))
        back = read_model(path, types)
        assert type(back) is type(model), label
        assert back.content_key == model.content_key, label  # same type, parameters and array bytes
        for name, array in model.payload()[1].items():
            got = getattr(back, name)
            assert got.dtype == array.dtype and np.array_equal(got, array), (label, name)
        if label == "sh quantized":
            assert back.coeffs.dtype == np.uint8 and back.quantized
            with zipfile.ZipFile(path) as archive:
                assert {"arrays/coeffs.npy", "arrays/scale.npy", "arrays/bias.npy"} <= set(archive.namelist())


def test_graph_writes_then_reads_and_relights(btf, tmp_path):
    graph = {"nodes": {
        "btf": {"stage": "demo.btf", "params": {"size": [4, 4], "lights": 9, "views": 2}},
        "fit": {"stage": "sh.fit", "params": {"light_order": 2, "view_order": 2}, "inputs": {"stack": "btf.stack"}},
        "save": {"stage": "models.write", "params": {"path": "m.btfm"}, "inputs": {"model": "fit.model"}}}}
    result = btforge.run(graph, out_dir=tmp_path, only=["fit", "save"])
    read = {"nodes": {"load": {"stage": "models.read", "params": {"path": str(tmp_path / "m.btfm")}},
                      "lit": {"stage": "relight.images", "params": {"lights": [[0, 0, 1]]}, "inputs": {"model": "load.model"}}}}
    lit = btforge.run(read, out_dir=tmp_path)["lit"]["stack"]
    np.testing.assert_array_equal(lit.samples[0], result["fit"]["model"].evaluate([[0, 0, 1]])[0])


def _rewrite_manifest(path, change):
    with zipfile.ZipFile(path) as archive:
        members = {n: archive.read(n) for n in archive.namelist()}
    manifest = json.loads(members["manifest.json"])
    change(manifest)
    members["manifest.json"] = json.dumps(manifest).encode()
    with zipfile.ZipFile(path, "w") as archive:
        for name, data in members.items():
            archive.writestr(name, data)


def test_other_format_versions_and_damage_are_refused_with_the_reason(btf, tmp_path):
    model = next(m for label, m in _models(btf) if label == "ptm rgb")
    types = default_registry().types
    path = tmp_path / "m.btfm"

    write_model(path, model)
    _rewrite_manifest(path, lambda m: m.update(format_version=FORMAT_VERSION + 1, written_by="btforge 9.0"))
    with pytest.raises(BtforgeInputError, match=r"format version 2 \(written by btforge 9.0\).*reads format versions 1") as info:
        read_model(path, types)
    assert "upgrade btforge" in info.value.hint

    write_model(path, model)
    _rewrite_manifest(path, lambda m: m["parameters"].update(texture_space="tangent"))
    with pytest.raises(BtforgeInputError, match="fields this btforge's PTMModel does not know: texture_space"):
        read_model(path, types)

    write_model(path, model)
    _rewrite_manifest(path, lambda m: m["parameters"].pop("basis"))   # an older file: the field takes its default
    assert read_model(path, types).basis == "raw"

    write_model(path, model)
    _rewrite_manifest(path, lambda m: m["arrays"]["coeffs"].update(blake2b="0" * 40))
    with pytest.raises(BtforgeInputError, match="does not match its manifest"):
        read_model(path, types)

    write_model(path, model)
    _rewrite_manifest(path, lambda m: m.update(representation="NoSuchModel"))
    with pytest.raises(BtforgeInputError, match="no installed plugin defines"):
        read_model(path, types)

    (tmp_path / "junk.btfm").write_bytes(b"not a zip")
    with pytest.raises(BtforgeInputError, match="not a btforge model file"):
        read_model(tmp_path / "junk.btfm", types)


def test_bad_model_file_is_refused_before_a_run(tmp_path, capsys):
    (tmp_path / "junk.btfm").write_bytes(b"PK\x03\x04 truncated")
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  load: {{stage: models.read, params: {{path: {tmp_path / 'junk.btfm'}}}}}\n")
    assert main(["validate", str(graph)]) == 2
    assert "not a btforge model file" in capsys.readouterr().err


def test_info_shows_a_saved_model(btf, tmp_path, capsys):
    model = next(m for label, m in _models(btf) if label == "sh quantized")
    write_model(tmp_path / "sh.btfm", model)
    assert main(["info", str(tmp_path / "sh.btfm"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["representation"] == "SHModel" and info["parameters"]["quantized"] is True
    assert info["arrays"]["coeffs"] == "(6, 5, 3, 4, 9) uint8" and info["texels"] == [6, 5]
