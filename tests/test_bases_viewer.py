"""btforge view shows the hsh, rbf, bilinear and neural fits as relight shows them (headless Chromium; skipped, with the
reason, without a browser or Playwright)."""
from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import btforge
from btforge.plugins.web.server import start

sys.path.insert(0, str(Path(__file__).parent))
from test_viewer import SIZE, open_page, psnr, relit_display, screenshot  # noqa: E402,F401
from test_web_export import capture  # noqa: E402

FITS = {"hsh": ("hsh.fit", {}), "hsh_ycc": ("hsh.fit", {"colorspace": "ycc"}), "rbf": ("rbf.fit", {}),
        "yrbf": ("rbf.fit", {"colorspace": "ycc", "planes": 12}), "bilinear": ("bilinear.fit", {}),
        "ybilinear": ("bilinear.fit", {"colorspace": "ycc", "planes": 12, "resolution": 6}),
        # neural.fit: the harmonics decoder (default), NeuralRTI's network (as OpenLIME opens it) and a light
        # decoder of harmonic light features with a code of 5 (codes and layers both padded)
        "neural": ("neural.fit", {"hidden": 24, "epochs": 5, "texels": 2000}),
        "nrti": ("neural.fit", {"decoder": "light", "light_order": 0, "latent": 9, "layers": 2, "hidden": 24,
                                "epochs": 5, "texels": 2000}),
        "neural_l3": ("neural.fit", {"decoder": "light", "light_order": 3, "latent": 5, "hidden": 18, "epochs": 5,
                                     "texels": 2000})}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    root = tmp_path_factory.mktemp("view_bases")
    stack = capture(n=40, size=SIZE, seed=4)
    models = {}
    for name, (stage, params) in FITS.items():
        models[name] = btforge.stage(stage)(stack=stack, **params)["model"]
        btforge.stage("web.export")(model=models[name], dir=str(root / name))
    server, thread, scratch = start([root / name for name in FITS], 0)
    yield server, models
    server.shutdown()
    shutil.rmtree(scratch, ignore_errors=True)


@pytest.mark.parametrize("index,name", list(enumerate(FITS)))
def test_page_matches_relight_at_three_lights(served, browser, index, name):
    server, models = served
    for x, y in [(0.0, 0.0), (0.5, 0.3), (-0.4, -0.6)]:
        page = open_page(browser, f"{server.url}?model={index}&bar=0&zoom=1&light={x},{y}")
        assert page.evaluate("document.body.dataset.state") == "ready"
        light = [x, y, float(np.sqrt(1 - x * x - y * y))]
        # 8-bit planes and basis: a couple of levels off at worst, far above 35 dB on average
        assert psnr(screenshot(page), relit_display(models[name], light)) >= 35
        page.close()


def test_a_neural_layout_with_wrong_weights_shows_the_reason(served, browser, tmp_path):
    """btforge view refuses such a folder up front (web.read's check); a file damaged while the page is served
    is refused by the page itself."""
    import json
    from btforge.errors import BtforgeInputError
    _, models = served
    btforge.stage("web.export")(model=models["nrti"], dir=str(tmp_path / "bad"))
    info = json.loads((tmp_path / "bad" / "info.json").read_text())
    info["weights"][1] = info["weights"][1][:-4]
    server, thread, scratch = start([tmp_path / "bad"], 0)
    try:
        (tmp_path / "bad" / "info.json").write_text(json.dumps(info))
        page = open_page(browser, f"{server.url}?bar=0&zoom=1")
        assert page.evaluate("document.body.dataset.state") == "error"
        assert "weights[1] must hold 24 x 24 numbers" in page.inner_text("#message")
        page.close()
    finally:
        server.shutdown()
        shutil.rmtree(scratch, ignore_errors=True)
    with pytest.raises(BtforgeInputError, match=r"'weights\[1\]': expected 576 finite numbers"):
        start([tmp_path / "bad"], 0)
