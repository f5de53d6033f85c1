"""btforge view: the local server, and the page in a real headless Chromium (skipped, with the reason, when
there is no browser or no Playwright)."""
from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import btforge
from btforge.buffers import linear_to_srgb
from btforge.plugins.web.hsh import HSHModel
from btforge.plugins.web.server import start

sys.path.insert(0, str(Path(__file__).parent))
from test_web_export import capture  # noqa: E402

SIZE = (60, 80)  # model rows, columns: the page shows it at 1:1 with ?zoom=1&bar=0


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    root = tmp_path_factory.mktemp("view")
    stack = capture(size=SIZE, seed=4)
    ptm = btforge.stage("ptm.fit")(stack=stack)["model"]
    sh = btforge.stage("sh.fit")(stack=capture(size=SIZE, seed=4, encoding="linear"), light_order=3)["model"]
    lrgb = btforge.stage("ptm.fit")(stack=stack, variant="lrgb")["model"]
    rng = np.random.default_rng(5)
    hsh = HSHModel((rng.normal(0, 0.1, SIZE + (3, 9)) + np.array([0.9] + [0.0] * 8)).astype(np.float32))
    models = {"ptm": ptm, "sh": sh, "lrgb": lrgb, "hsh": hsh}
    for name, model in models.items():
        btforge.stage("web.export")(model=model, dir=str(root / name))
    shutil.copytree(root / "ptm", root / "broken")
    (root / "broken" / "plane_3.png").unlink()
    server, thread, scratch = start([root / "ptm", root / "sh", root / "broken", root / "lrgb", root / "hsh"], 0)
    yield server, models
    server.shutdown()
    shutil.rmtree(scratch, ignore_errors=True)


def test_server_lists_models_and_serves_only_their_files(served):
    server, _ = served
    listing = json.loads(urllib.request.urlopen(server.url + "models.json").read())
    assert [m["name"] for m in listing] == ["ptm", "sh", "broken", "lrgb", "hsh"]
    assert json.loads(urllib.request.urlopen(server.url + "m/0/info.json").read())["type"] == "ptm"
    for bad in ("m/0/../../../etc/passwd", "m/9/info.json", "m/0/secret.txt", "../pyproject.toml"):
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(server.url + bad)
        assert err.value.code == 404
    assert server.server_address[0] == "127.0.0.1"


def test_cli_prints_its_address(tmp_path):
    model = btforge.stage("ptm.fit")(stack=capture(size=(8, 8)))["model"]
    btforge.stage("web.export")(model=model, dir=str(tmp_path / "m"))
    scratch_root = tmp_path / "tmp"
    scratch_root.mkdir()
    proc = subprocess.Popen([sys.executable, "-m", "btforge.cli", "view", str(tmp_path / "m"), "--port", "0"],
                            stdout=subprocess.PIPE, text=True, env={**os.environ, "TMPDIR": str(scratch_root)})
    try:
        line = proc.stdout.readline()
        url = line.split(" at ")[1].split()[0]
        assert url.startswith("http://127.0.0.1:")
        assert json.loads(urllib.request.urlopen(url + "models.json", timeout=10).read())[0]["name"] == "m"
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    assert list(scratch_root.iterdir()) == []  # terminated, it still removed its scratch folder


def open_page(browser, url):
    page = browser.new_page(viewport={"width": SIZE[1], "height": SIZE[0]}, device_scale_factor=1)
    page.goto(url)
    page.wait_for_function("['ready', 'error'].includes(document.body.dataset.state)", timeout=30000)
    return page


def screenshot(page) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), np.float64) / 255.0


def relit_display(model, light) -> np.ndarray:
    return linear_to_srgb(btforge.stage("relight.images")(model=model, lights=[light])["stack"].samples[0, 0])


def psnr(a, b) -> float:
    return float(10 * np.log10(1.0 / max(np.mean((a - b) ** 2), 1e-12)))


@pytest.mark.parametrize("index,name", [(0, "ptm"), (1, "sh"), (3, "lrgb"), (4, "hsh")])
def test_page_matches_relight_at_three_lights(served, browser, index, name):
    server, models = served
    for x, y in [(0.0, 0.0), (0.5, 0.3), (-0.4, -0.6)]:
        page = open_page(browser, f"{server.url}?model={index}&bar=0&zoom=1&light={x},{y}")
        assert page.evaluate("document.body.dataset.state") == "ready"
        assert "SwiftShader" in page.evaluate("document.body.dataset.renderer")  # --disable-gpu: WebGL on the CPU
        light = [x, y, float(np.sqrt(1 - x * x - y * y))]
        assert psnr(screenshot(page), relit_display(models[name], light)) >= 35
        page.close()


def test_dragging_moves_the_light_and_snapshot_saves_the_view(served, browser):
    server, _ = served
    page = open_page(browser, f"{server.url}?bar=0&zoom=1")
    before = screenshot(page)
    page.mouse.move(10, 10)
    page.mouse.down()
    page.mouse.move(70, 15, steps=4)
    page.mouse.up()
    light = page.evaluate("window.btforgeViewer.light")
    assert light[0] > 0.5 and light[1] > 0.3
    after = screenshot(page)
    assert np.abs(after - before).mean() > 0.01
    page.close()
    page = browser.new_page(viewport={"width": 400, "height": 300}, device_scale_factor=1, accept_downloads=True)
    page.goto(server.url)
    page.wait_for_function("document.body.dataset.state === 'ready'", timeout=30000)
    with page.expect_download() as download:
        page.click("#snapshot")
    data = Path(download.value.path()).read_bytes()
    assert Image.open(io.BytesIO(data)).size == (400, 300)
    zoom = page.evaluate("window.btforgeViewer.zoom")
    page.mouse.move(200, 150)
    page.mouse.wheel(0, -300)
    page.wait_for_function(f"window.btforgeViewer.zoom > {zoom}", timeout=10000)
    pan, light = page.evaluate("window.btforgeViewer.pan"), page.evaluate("window.btforgeViewer.light")
    page.keyboard.down("Shift")  # shift-drag pans and leaves the light alone
    page.mouse.move(200, 150)
    page.mouse.down()
    page.mouse.move(260, 190, steps=3)
    page.mouse.up()
    page.keyboard.up("Shift")
    moved = page.evaluate("window.btforgeViewer.pan")
    assert abs(moved[0] - pan[0] - 60) < 1 and abs(moved[1] - pan[1] - 40) < 1
    assert page.evaluate("window.btforgeViewer.light") == light
    page.close()


def test_a_model_that_fails_to_load_shows_a_message(served, browser):
    server, _ = served
    page = open_page(browser, f"{server.url}?model=2")
    assert page.evaluate("document.body.dataset.state") == "error"
    message = page.inner_text("#message")
    assert "Could not load model 'broken'" in message and "plane_3" in message
    page.select_option("#models", "0")  # switching to a good model clears it
    page.wait_for_function("document.body.dataset.state === 'ready'", timeout=30000)
    assert not page.is_visible("#message")
    page.close()


def test_ptm_and_rti_files_are_exported_for_the_page(tmp_path):
    from btforge.plugins.web.hsh import write_rti
    model = btforge.stage("ptm.fit")(stack=capture(size=(8, 10)), space="srgb")["model"]
    btforge.stage("ptm.write")(model=model, path=str(tmp_path / "a.ptm"))
    write_rti(tmp_path / "b.rti", HSHModel(np.ones((6, 5, 3, 9), np.float32)))
    server, thread, scratch = start([tmp_path / "a.ptm", tmp_path / "b.rti"], 0)
    try:
        listing = json.loads(urllib.request.urlopen(server.url + "models.json").read())
        assert [m["name"] for m in listing] == ["a", "b"]
        infos = [json.loads(urllib.request.urlopen(server.url + f"m/{i}/info.json").read()) for i in range(2)]
        assert [(i["type"], i["width"], i["height"]) for i in infos] == [("ptm", 10, 8), ("hsh", 5, 6)]
    finally:
        server.shutdown()
        shutil.rmtree(scratch, ignore_errors=True)
    assert not scratch.exists()
