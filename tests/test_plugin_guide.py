"""docs/plugins.md walks a newcomer through a toy representation family: its files are built here exactly as the
page shows them, installed by entry point as `pip install` would, and its graph is run."""
import re
import sys
from pathlib import Path

import btforge
import btforge.registry

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "plugins.md"


def guide_files() -> dict[str, str]:
    """{relative path: text} of every code block the guide marks with ``<!-- file: PATH -->``."""
    blocks = re.findall(r"<!-- file: (\S+) -->\n```\w*\n(.*?)```", GUIDE.read_text(), re.S)
    return {path: text for path, text in blocks}


def _install(project: Path, site: Path) -> None:
    """What `pip install -e .` of the guide's project leaves: its package importable and its entry points."""
    meta = project.joinpath("pyproject.toml").read_text()
    name = re.search(r'^name = "(\w+)"', meta, re.M).group(1)
    entry = re.search(r'\[project\.entry-points\."btforge\.plugins"\]\n(\w+) = "([\w.]+)"', meta)
    info = site / f"{name}-0.1.dist-info"
    info.mkdir(parents=True)
    info.joinpath("METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    info.joinpath("entry_points.txt").write_text(f"[btforge.plugins]\n{entry.group(1)} = {entry.group(2)}\n")


def test_the_guide_shows_a_whole_plugin():
    files = guide_files()
    assert {"matte/__init__.py", "pyproject.toml", "matte.yaml"} <= set(files)


def test_the_toy_family_of_the_guide_installs_and_runs_in_a_graph(tmp_path, monkeypatch):
    project = tmp_path / "project"
    for path, text in guide_files().items():
        target = project / path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text)
    site = tmp_path / "site"
    _install(project, site)
    monkeypatch.syspath_prepend(str(project))
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setattr(btforge.registry, "_default", None)
    monkeypatch.delitem(sys.modules, "matte", raising=False)

    registry = btforge.registry.default_registry()
    assert registry.stages["matte.fit"].role == "fit"
    assert "MatteModel" in registry.types and registry.accepts("ReflectanceModel", "MatteModel")

    result = btforge.run(project / "matte.yaml", cache_dir=tmp_path / "cache", out_dir=tmp_path / "out")
    scores = next(r for r in result.report if r.node == "score").notes
    assert scores["psnr_db"] > 40, scores  # a flat Lambertian material is exactly what the model describes
    model = btforge.run(project / "matte.yaml", only=["fit"], cache_dir=tmp_path / "cache",
                        out_dir=tmp_path / "out")["fit"]["model"]
    assert type(model).__name__ == "MatteModel" and model.albedo.shape == (32, 32, 3)
