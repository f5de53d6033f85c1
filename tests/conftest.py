import os
import shutil
from pathlib import Path

import pytest
from hypothesis import settings

# A red CI does not land, so by default every run draws the same examples (fixed per test) and CI cannot fail on
# one nobody has seen yet.  `HYPOTHESIS_PROFILE=explore python3 -m pytest` draws new ones; a failure it finds
# becomes an @example of its test.
settings.register_profile("ci", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False, max_examples=200)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

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


# Debian's chromium, driven by Playwright for the viewer tests (Playwright's own browsers are never fetched)
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync"]


@pytest.fixture(scope="module")
def browser():
    if CHROMIUM is None:
        pytest.skip("no Chromium on PATH (.ci/setup installs Debian's chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="Playwright is not installed (pip install playwright)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
        yield b
        b.close()


@pytest.fixture(scope="session")
def tileable_stack():
    """A maker of tileable procedural materials (bumps and colour waves wrap around) under 8 lights from above:
    ``tileable_stack(side, bumps)`` is a one-view SampleStack of a side x side material with that many bumps."""
    import numpy as np

    from btforge.buffers import SampleStack
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights

    def make(side: int, bumps: int) -> SampleStack:
        lights = hemisphere_lights(8)
        material = make_material(side, side, bumps=bumps, seed=5)
        return SampleStack(render_lights(material, lights)[None], lights, np.array([[0.0, 0.0, 1.0]]))
    return make
