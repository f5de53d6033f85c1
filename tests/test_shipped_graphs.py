"""What a user runs first: every graph in graphs/ and the README's first command, from a plain clone.

The graphs run as a user runs them (the `btforge` command in a fresh process), from a copy of the checkout's
tracked files with no ``../shared`` beside it, so an example that reads data the repository does not ship fails
here.  Heavy graphs run with smaller sizes set through ``--set``, as their descriptions allow; every node still
runs.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import REPO

GRAPHS = sorted(p.name for p in (REPO / "graphs").glob("*.yaml"))

# Smaller sizes for the graphs whose shipped sizes take long on 2 cores; each still runs every node.
SMALLER = {
    "liu_btf.yaml": ["btf.size=[64, 64]", "grow.size=[128, 128]"],
    "synth_quilt.yaml": ["synth.size=[128, 128]"],
    "synth_kcoherence.yaml": ["synth.size=[128, 128]"],
    "synth_jumpmap.yaml": ["synth.size=[128, 128]"],
    "wang_tiles.yaml": ["tiling.rows=4", "tiling.cols=4"],
    "render_torus_environment.yaml": ["synth.size=[128, 128]"],
}


def _tracked_files() -> list[str]:
    """The checkout's tracked files (what a clone holds), or every file when this is not a git checkout."""
    try:
        listed = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z"], capture_output=True, check=True)
        names = [n for n in listed.stdout.decode().split("\0") if n]
        if names:
            return names
    except (OSError, subprocess.CalledProcessError):
        pass
    return [str(p.relative_to(REPO)) for p in REPO.rglob("*") if p.is_file() and ".git" not in p.parts]


@pytest.fixture(scope="module")
def plain_clone(tmp_path_factory) -> Path:
    """A copy of the tracked files in a folder with no ``shared`` sibling."""
    root = tmp_path_factory.mktemp("clone") / "btforge"
    for name in _tracked_files():
        source = REPO / name
        if source.is_file():
            target = root / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)
    assert not (root.parent / "shared").exists()
    return root


@pytest.fixture(scope="module")
def graph_cache(tmp_path_factory) -> Path:
    # One node cache for all graphs: several read the same capture, as a user's repeated runs would.
    return tmp_path_factory.mktemp("graph-cache")


def _btforge_command() -> list[str]:
    found = shutil.which("btforge", path=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))
    return [found] if found else [sys.executable, "-m", "btforge.cli"]


@pytest.mark.parametrize("graph", GRAPHS)
def test_every_shipped_graph_runs_from_a_plain_clone(graph, plain_clone, graph_cache, tmp_path):
    sets = [arg for item in SMALLER.get(graph, []) for arg in ("--set", item)]
    env = dict(os.environ, BTFORGE_CACHE_DIR=str(graph_cache))
    done = subprocess.run([*_btforge_command(), "run", f"graphs/{graph}", "--out", str(tmp_path / "out"), *sets],
                          cwd=plain_clone, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, f"{graph} failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    complaints = [line for line in done.stderr.splitlines() if line.lower().startswith(("error", "internal error"))]
    assert not complaints and "Traceback" not in done.stderr, done.stderr[-2000:]


def readme_first_command() -> str:
    """The first command of the README's first bash block, without its trailing comment."""
    text = (REPO / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", text, re.S)
    assert block, "README.md has no bash block"
    first = block.group(1).strip().splitlines()[0]
    return first.split("  #")[0].strip()


def test_readme_first_command_is_the_demo():
    command = readme_first_command()
    assert command.startswith("bash .ci/setup && ") and "graphs/demo.yaml" in command, command


def test_readme_first_command_runs_as_written(plain_clone, tmp_path):
    """The command exactly as the README gives it, in the plain clone, with its installer.

    ``.ci/setup`` installs into a virtual environment (with no pip of its own) that sees this machine's packages,
    so the test neither re-points the installation under test nor downloads anything: ``PIP_NO_INDEX`` makes any
    download an error.
    """
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", str(venv)], check=True)
    env = dict(os.environ, PATH=f"{venv / 'bin'}{os.pathsep}{os.environ['PATH']}", PYTHON=str(venv / "bin/python3"),
               VIRTUAL_ENV=str(venv), BTFORGE_CACHE_DIR=str(tmp_path / "cache"), PIP_NO_INDEX="1")
    done = subprocess.run(["bash", "-c", readme_first_command()], cwd=plain_clone, env=env, capture_output=True,
                          text=True, timeout=1200)
    assert done.returncode == 0, f"{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    out = plain_clone / "out"
    for name in ("relit_sheet.png", "heldout_fit_vs_truth.png", "relit/lights.lp"):
        assert (out / name).is_file(), f"the demo did not write out/{name}"
    assert list((out / "relit").glob("*.exr")), "the demo wrote no relit EXR images"
