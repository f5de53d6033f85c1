"""Cold start: `btforge run --profile` and the report's startup; kernel binaries reused by the next process."""
import json
import os
import subprocess
import sys

GRAPH = """nodes:
  material: {stage: demo.material, params: {size: [8, 8], lights: 9, bumps: 2}}
  fit: {stage: ptm.fit, inputs: {stack: material.stack}}
"""


def _run(tmp_path, *extra):
    return subprocess.run([sys.executable, "-m", "btforge.cli", "run", str(tmp_path / "g.yaml"), "--out",
                           str(tmp_path / "out"), "--report", str(tmp_path / "report.json"), *extra],
                          capture_output=True, text=True)


def test_profile_and_report_show_where_a_fresh_process_spends_its_time(tmp_path, monkeypatch):
    monkeypatch.setenv("BTFORGE_CACHE_DIR", str(tmp_path / "cache"))  # no binaries yet: this process builds
    (tmp_path / "g.yaml").write_text(GRAPH)
    first = _run(tmp_path, "--profile", "--no-cache")
    assert first.returncode == 0, first.stderr
    for label in ("interpreter and imports", "plugins loaded", "OpenCL device started", "kernel builds",
                  "material (demo.material)", "fit (ptm.fit)", "whole process so far"):
        assert label in first.stderr
    startup = json.loads((tmp_path / "report.json").read_text())["startup"]
    assert 0 < startup["interpreter_and_imports_s"] < startup["process_s"]
    assert startup["device_start_s"] > 0
    built = {(b["file"], b["options"]): b["from"] for b in startup["kernel_builds"]}
    assert ("ptm.cl", "-DSAMPLE_T=float") in built and ("procedural.cl", "") in built
    second = _run(tmp_path, "--no-cache")  # a new process: every program comes from the binaries on disk
    assert second.returncode == 0, second.stderr
    again = json.loads((tmp_path / "report.json").read_text())["startup"]
    assert {(b["file"], b["options"]): b["from"] for b in again["kernel_builds"]} == {
        key: "binary cache" for key in built}


def test_rendering_code_does_not_load_the_plotting_stack():
    code = ("import sys; from btforge.plugins.render.o3d import open3d; o3d = open3d(); "
            "o3d.t.geometry.RaycastingScene(); print(sorted(m for m in ('dash', 'plotly', 'IPython') if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "[]"


def test_public_names_and_submodules_load_on_first_use():
    code = ("import sys, btforge; before = [m for m in ('numpy', 'btforge.runner') if m in sys.modules]; "
            "from btforge import SampleStack, run; "
            "print(before, run.__module__, SampleStack.__module__, btforge.streaming.__name__, hasattr(btforge, 'nope'))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["[]", "btforge.runner", "btforge.buffers", "btforge.streaming", "False"]


def test_the_command_line_shortens_blas_spin_before_numpy_loads_and_a_users_setting_wins():
    code = ("import os, sys, btforge.cli as cli; before = 'numpy' in sys.modules; "
            "sys.argv = ['btforge', 'stages', 'ptm.fit']; cli.main(); import numpy; "
            "print(before, os.environ.get('OPENBLAS_THREAD_TIMEOUT'))")
    env = {key: value for key, value in os.environ.items() if key != "OPENBLAS_THREAD_TIMEOUT"}
    for given, expected in ((None, "20"), ("26", "26")):
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              env=env if given is None else {**env, "OPENBLAS_THREAD_TIMEOUT": given})
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.split()[-2:] == ["False", expected]
