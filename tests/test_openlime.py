"""OpenLIME opens btforge's web exports and relights them as btforge does (headless Chromium).

Skipped unless BTFORGE_OPENLIME names an OpenLIME checkout.  OpenLIME ships no prebuilt bundle in its repository
(dist/js is built by npm and ignored by git), so its src/ folder is served as it is and the page imports it as ES
modules; the server only adds the ".js" that some of its relative imports leave to the bundler.  Only a loopback
server this module starts is contacted.

    BTFORGE_OPENLIME=/path/to/openlime python3 tests/test_openlime.py            # prints the table of PSNRs
    BTFORGE_OPENLIME=/path/to/openlime python3 -m pytest -q tests/test_openlime.py
"""
from __future__ import annotations

import http.server
import os
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import btforge

sys.path.insert(0, str(Path(__file__).parent))
from test_viewer import psnr, relit_display, screenshot  # noqa: E402

OPENLIME = os.environ.get("BTFORGE_OPENLIME")
ICON = Path(__file__).resolve().parents[1] / "graphs" / "data" / "icon_san_michele" / "dirs.lp"
CROP = {"origin": [120, 120], "size": [128, 128]}
# OpenLIME's image layout always asks for plane_N.jpg, so the exports it opens are written as JPEG
FITS = {"ptm": ("ptm.fit", {"space": "srgb"}), "lrgb": ("ptm.fit", {"space": "srgb", "variant": "lrgb"}),
        "sh": ("sh.fit", {"space": "srgb", "light_order": 3}), "hsh": ("hsh.fit", {}),
        "rbf": ("rbf.fit", {}), "yrbf": ("rbf.fit", {"colorspace": "ycc", "planes": 12}),
        "bilinear": ("bilinear.fit", {}), "ybilinear": ("bilinear.fit", {"colorspace": "ycc", "planes": 12}),
        # OpenLIME's mycc shader takes relight's order of planes only with as many luma planes as chroma planes
        "ybilinear_even": ("bilinear.fit", {"colorspace": "ycc", "planes": 12, "yplanes": 4}),
        "neural": ("neural.fit", {"decoder": "light", "light_order": 0, "latent": 9, "layers": 2})}
LIGHTS = [(0.0, 0.0), (0.5, 0.3), (-0.4, -0.6), (0.15, 0.98)]  # the last 7.5 degrees high: hsh clamps it to 8.6

PAGE = """<!DOCTYPE html><html><body style="margin:0;background:#000">
<link rel="stylesheet" href="/openlime-css/skin.css">
<div id="lime" class="openlime" style="position:absolute;left:0;top:0;width:{w}px;height:{h}px"></div>
<script type="module">
import {{ Viewer }} from '/openlime/Viewer.js';
import {{ Layer }} from '/openlime/Layer.js';
import '/openlime/LayerRTI.js';
import '/openlime/LayerNeuralRTI.js';
const q = new URLSearchParams(location.search);
const lime = new Viewer('#lime', {{ background: [0, 0, 0, 1] }});
const layer = new Layer({{ type: q.get('type'), layout: 'image', url: q.get('url'), normals: false }});
lime.addLayer('model', layer);
window.olime = {{ lime, layer }};
</script></body></html>"""


def _handler(openlime: Path, exports: Path, size):
    class Handler(http.server.SimpleHTTPRequestHandler):
        def translate_path(self, path):
            path = path.split("?")[0]
            if path.startswith("/openlime-css/"):  # its skin sizes the canvas to the viewer's div
                return str(openlime / "dist" / "css" / path[len("/openlime-css/"):])
            if path.startswith("/openlime/"):
                file = openlime / "src" / path[len("/openlime/"):]
                return str(file if file.suffix else file.with_suffix(".js"))  # the bundler's job, done here
            return str(exports / path.lstrip("/"))

        def do_GET(self):
            if self.path.split("?")[0] != "/":
                return super().do_GET()
            body = PAGE.format(w=size[1], h=size[0]).encode()
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):
            pass

    Handler.extensions_map = {**Handler.extensions_map, ".js": "text/javascript"}
    return Handler


def serve(openlime: Path, exports: Path, size):
    """A loopback server for OpenLIME's sources (/openlime/), the exports (/NAME/info.json) and the page (/)."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _handler(openlime, exports, size))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}/"


def icon_crop():
    """The shipped hand-held icon, its exposure corrected as graphs/relight_bases.yaml does, cropped."""
    stack = btforge.stage("stackio.read")(path=str(ICON))["stack"]
    stack = btforge.stage("normalize.stack")(stack=stack, falloff=True)["stack"]
    return btforge.stage("synth.crop")(input=stack, **CROP)["output"]


def export_all(stack, root: Path, names):
    """Fits and exports each model as JPEG; returns the fitted models and the exports as web.read reads them."""
    fitted, exported = {}, {}
    for name in names:
        stage, params = FITS[name]
        fitted[name] = btforge.stage(stage)(stack=stack, **params)["model"]
        btforge.stage("web.export")(model=fitted[name], dir=str(root / name), format="jpg")
        exported[name] = btforge.stage("web.read")(path=str(root / name / "info.json"))["model"]
    return fitted, exported


def openlime_view(browser, url, name, layer_type, light, size):
    """OpenLIME's rendering of one export at one light, as display values in [0, 1]."""
    page = browser.new_page(viewport={"width": size[1], "height": size[0]}, device_scale_factor=1)
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(f"{url}?type={layer_type}&url=/{name}/info.json")
    try:
        # polled: a layer whose layout is ready at once emits 'ready' before the page could listen
        page.wait_for_function("window.olime && olime.layer.status === 'ready'", timeout=30000)
    except Exception:
        page.close()
        return None, errors or ["the layer never became ready"]
    # the neural layer relights at a fraction of the resolution while the frame rate is below the target: a
    # target of 1 fps keeps it whole on SwiftShader, so what is measured is the shading, not the adaptation
    page.evaluate(f"olime.lime.canvas.targetfps = 1; olime.layer.currentRelightFraction = 1;"
                  f"olime.layer.setLight([{light[0]}, {light[1]}], 0); olime.lime.redraw()")
    before = screenshot(page)
    for _ in range(20):  # settled when two screenshots agree (the neural layer refines after a pause)
        page.wait_for_timeout(500)
        after = screenshot(page)
        if np.array_equal(before, after):
            break
        before = after
    page.close()
    return after, errors


def layer_type(name: str) -> str:
    """OpenLIME's layer type of an export: its neural layer, or the RTI layer for every other basis."""
    return "neural" if name == "neural" else "rti"


def direction(x: float, y: float) -> list[float]:
    """The unit light direction of the upper hemisphere with components ``x, y``."""
    return [x, y, float(np.sqrt(max(0.0, 1 - x * x - y * y)))]


def through_framebuffer(display: np.ndarray) -> np.ndarray:
    """Display values as OpenLIME's canvas shows them: it composes the layers in an 8-bit framebuffer of linear
    values (its shaders' simplified gamma 2.2), which costs the darkest values most of their precision."""
    return (np.round(np.clip(display, 0, 1) ** 2.2 * 255) / 255) ** (1 / 2.2)


def measure(browser, url, fitted, exported, size):
    """Rows of (name, light, PSNR against the fitted model, against the export read back, the same through
    OpenLIME's framebuffer, and with y mirrored)."""
    rows = []
    for name in fitted:
        for x, y in LIGHTS:
            shown, errors = openlime_view(browser, url, name, layer_type(name), (x, y), size)
            if shown is None:
                rows.append((name, (x, y), None, None, None, None, "; ".join(errors)))
                continue
            read = relit_display(exported[name], direction(x, y))
            rows.append((name, (x, y), psnr(shown, relit_display(fitted[name], direction(x, y))), psnr(shown, read),
                         psnr(shown, through_framebuffer(read)),
                         psnr(shown, relit_display(exported[name], direction(x, -y))), "; ".join(errors)))
    return rows


def print_table(rows):
    print("| basis | light (x, y) | vs fitted model | vs export (web.read) | the same through OpenLIME's "
          "framebuffer | vs export, y mirrored | page errors |")
    print("|---|---|---|---|---|---|---|")
    for name, light, *psnrs, errors in rows:
        cells = ["no" if v is None else f"{v:.2f} dB" for v in psnrs]
        print(f"| {name} | {light[0]:+.2f}, {light[1]:+.2f} | " + " | ".join(cells) + f" | {errors} |")


needs_openlime = pytest.mark.skipif(not OPENLIME, reason="BTFORGE_OPENLIME does not name an OpenLIME checkout")
# Lowest PSNR (dB) between OpenLIME's canvas and web.read's model of the same export passed through OpenLIME's
# framebuffer, at every light.  The bases it evaluates as btforge does stay near 58 dB (8-bit planes on both
# sides); the neural layer relights through a framebuffer of its own (44-51 dB); rbf: OpenLIME weights the lights
# with its own adaptive Gaussians; ybilinear: its mycc shader reads the fourth image, three luma planes, as
# (Y, Co, Cg).
FLOOR = {"neural": 42, "rbf": 28, "yrbf": 28, "ybilinear": 35}
OPENLIME_LRGB = pytest.mark.xfail(strict=True, reason="OpenLIME's lrgb shader returns the luminance as alpha, and "
                                  "the colour comes out multiplied by it (about relit x luminance^2): an rgb PTM "
                                  "shows right")


@pytest.fixture(scope="module")
def openlime_site(tmp_path_factory):
    root = tmp_path_factory.mktemp("openlime")
    _, exported = export_all(icon_crop(), root, list(FITS))
    server, url = serve(Path(OPENLIME), root, CROP["size"])
    yield url, exported
    server.shutdown()


@needs_openlime
@pytest.mark.parametrize("name", [pytest.param(n, marks=OPENLIME_LRGB) if n == "lrgb" else n for n in FITS])
def test_openlime_relights_the_export_as_btforge_does(openlime_site, browser, name):
    url, exported = openlime_site
    for x, y in LIGHTS:
        shown, errors = openlime_view(browser, url, name, layer_type(name), (x, y), CROP["size"])
        assert shown is not None and not errors, errors
        expected = through_framebuffer(relit_display(exported[name], direction(x, y)))
        assert psnr(shown, expected) >= FLOOR.get(name, 55), (x, y)


def main():
    import tempfile
    from playwright.sync_api import sync_playwright
    from conftest import CHROMIUM, FLAGS
    names = sys.argv[1:] or list(FITS)
    with tempfile.TemporaryDirectory() as scratch:
        fitted, exported = export_all(icon_crop(), Path(scratch), names)
        server, url = serve(Path(OPENLIME), Path(scratch), CROP["size"])
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=FLAGS)
            print_table(measure(browser, url, fitted, exported, CROP["size"]))
            browser.close()
        server.shutdown()


if __name__ == "__main__":
    main()
