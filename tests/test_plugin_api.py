"""Plugins: a third-party family installed by entry point, API versions, misspelt hooks, bench commands."""
import subprocess
import sys
import types

import pytest

import btforge
from btforge import BtforgeInputError
from btforge.registry import Registry

from conftest import FIXTURES
from fixtures import toy_plugin


def _distribution(site, name: str, module: str):
    """A minimal installed distribution whose entry point names ``module`` (what `pip install` leaves)."""
    info = site / f"{name}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[btforge.plugins]\n{name} = {module}\n")


def test_a_third_party_plugin_adds_a_representation_and_a_synthesizer(tmp_path, monkeypatch, capsys):
    """tests/fixtures/third_party_plugin, installed by entry point, is listed and benched like a built-in family."""
    import csv

    import btforge.registry
    from btforge.cli import main
    from btforge.plugins.stackio.images import write_stack
    site = tmp_path / "site"
    _distribution(site, "thirdparty", "third_party_plugin")
    write_stack(btforge.stage("demo.material")(size=[12, 12], lights=10, bumps=4)["stack"], tmp_path / "cap", fmt="exr")
    monkeypatch.syspath_prepend(str(FIXTURES))
    monkeypatch.syspath_prepend(str(site))  # where entry points are found, as after `pip install`
    monkeypatch.setattr(btforge.registry, "_default", None)
    assert main(["stages", "lambert.fit"]) == 0
    assert "Fit a Lambertian albedo" in capsys.readouterr().out
    assert main(["bench", "representations", "--stack", str(tmp_path / "cap" / "lights.lp"), "--out",
                 str(tmp_path / "reps"), "--only", "lambert", "--only", "ptm"]) == 0
    table = (tmp_path / "reps" / "representations.csv").read_text()
    assert "\nlambert," in table and "\nptm," in table
    assert "all 12 x 12 texels" in capsys.readouterr().err  # the bench says what size it measured
    assert main(["bench", "synthesis", "--exemplar", "procedural", "--out", str(tmp_path / "synth"), "--sizes", "24",
                 "--size", "32", "--only", "thirdparty.offsets", "--lights", "3"]) == 0
    rows = list(csv.DictReader((tmp_path / "synth" / "synthesis.csv").open()))
    assert [r["synthesizer"] for r in rows] == ["shuffled blocks", "thirdparty.offsets"]
    assert float(rows[1]["texture_statistics"]) >= 0 and float(rows[1]["swd"]) >= 0
    assert float(next(csv.DictReader((tmp_path / "synth" / "search.csv").open()))["recall"]) >= 0.9
    found = [st.name for st in btforge.registry.default_registry().stages_with_role("synthesizer")]
    assert {"synth.quilt", "synth.kcoherence", "synth.jumpmap", "thirdparty.offsets"} <= set(found)


def _plugin(**attributes):
    module = types.ModuleType("made_up_plugin")
    module.__dict__.update(attributes)
    return module


def test_a_plugin_for_another_api_version_is_refused_by_name():
    with pytest.raises(BtforgeInputError, match="plugin 'old'.*written for plugin API 0.*has API 1"):
        Registry(load_entry_points=False, extra_plugins=[]).register(_plugin(BTFORGE_PLUGIN_API=0), name="old")


def test_a_plugin_without_an_api_version_is_refused_with_the_fix():
    with pytest.raises(BtforgeInputError, match="plugin 'bare'.*states no plugin API version.*BTFORGE_PLUGIN_API = 1"):
        Registry(load_entry_points=False).register(_plugin(), name="bare")


def test_a_misspelt_hook_is_an_error_naming_plugin_and_hook():
    @btforge.hookimpl
    def btforge_stage():
        return []
    with pytest.raises(BtforgeInputError, match="plugin 'typo'.*unknown hook 'btforge_stage'.*did you mean 'btforge_stages'"):
        Registry(load_entry_points=False).register(_plugin(BTFORGE_PLUGIN_API=1, btforge_stage=btforge_stage),
                                                   name="typo")


def test_bench_commands_come_from_plugins_and_clash_by_name():
    def bench_numbers(args):
        """Count to three."""
        return 0

    @btforge.hookimpl
    def btforge_bench_commands():
        return {"ptm": bench_numbers}
    registry = Registry()
    assert {"ptm", "render", "representations", "quilt", "kcoherence", "synthesis"} <= set(registry.bench_commands)
    assert [st.name for st in registry.stages_with_role("fit")] == ["bilinear.fit", "hsh.fit", "lafortune.fit",
                                                                  "neural.fit", "ptm.fit", "rbf.fit", "sh.fit"]
    with pytest.raises(BtforgeInputError, match="bench 'ptm'.*contributed by both"):
        registry.register(_plugin(BTFORGE_PLUGIN_API=1, btforge_bench_commands=btforge_bench_commands), name="mine")


def test_bench_lists_what_plugins_contribute():
    proc = subprocess.run([sys.executable, "-m", "btforge.cli", "bench"], capture_output=True, text=True)
    assert proc.returncode == 0
    assert "representations" in proc.stdout and "Fit time, relight time" in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "btforge.cli", "bench", "represent"], capture_output=True, text=True)
    assert proc.returncode == 2 and "did you mean 'representations'" in proc.stderr


def test_capabilities_a_class_lacks_are_clear_errors():
    numbers = toy_plugin.Numbers(__import__("numpy").zeros(3))
    with pytest.raises(BtforgeInputError, match="'Numbers': has no appearance features"):
        numbers.appearance_features()
    from btforge.plugins.lafortune.model import LafortuneModel
    assert LafortuneModel.evaluates_texels and not LafortuneModel.blendable
    sys.path.insert(0, str(FIXTURES))
    try:
        from third_party_plugin import LambertModel
    finally:
        sys.path.remove(str(FIXTURES))
    model = LambertModel(__import__("numpy").ones((2, 2, 3), "float32"))
    assert not LambertModel.evaluates_texels
    with pytest.raises(BtforgeInputError, match="'LambertModel': cannot be evaluated per texel"):
        model.evaluate_texels([0], [0], [[0, 0, 1]])
    assert model.appearance_features().shape == (2, 2, 25 * 3)  # a model of unknown form: sampled at probe lights


def test_bench_warnings_are_counted_not_flooded():
    import io
    import warnings

    from btforge import BtforgeWarning
    from btforge.bench import counted_warnings
    screen = io.StringIO()
    with counted_warnings(screen):
        for n in range(40):
            warnings.warn(f"node 'fit': {n} of 64 texels did not converge", BtforgeWarning)
        warnings.warn("ill-conditioned", BtforgeWarning)
    lines = screen.getvalue().splitlines()
    assert lines[0].startswith("41 warnings during the bench, 2 kinds")
    assert lines[1] == "  40 x node 'fit': 0 of 64 texels did not converge" and len(lines) == 3
