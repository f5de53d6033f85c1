import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"
FIXTURES = Path(__file__).resolve().parent / "fixtures"


@pytest.fixture
def shared_data() -> Path:
    """The real captures beside the checkout (../shared/data); tests using them skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data is not present")
    return SHARED_DATA


@pytest.fixture(autouse=True)
def _isolated_node_cache(tmp_path_factory, monkeypatch):
    # Node outputs are cached per test so runs never see each other's entries; PoCL's kernel cache stays shared.
    monkeypatch.setenv("BTFORGE_CACHE_DIR", str(tmp_path_factory.mktemp("btforge-cache")))
    monkeypatch.setenv("POCL_CACHE_DIR", os.environ.get("POCL_CACHE_DIR", str(Path.home() / ".cache/btforge/pocl")))
