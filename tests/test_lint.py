"""The code passes the linter configured in pyproject.toml ([tool.ruff]), so the test command covers it."""
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    if importlib.util.find_spec("ruff") is None:
        pytest.fail("ruff is not installed: pip install -e '.[test]' (pyproject.toml's test extra has it)")
    done = subprocess.run([sys.executable, "-m", "ruff", "check", "framework", "plugins", "tests"], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 0, f"ruff check framework plugins tests:\n{done.stdout}{done.stderr}"
