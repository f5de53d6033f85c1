"""``btforge view``: a local HTTP server for the relighting page and the models it shows."""
from __future__ import annotations

import argparse
import http.server
import json
import shutil
import signal
import sys
import tempfile
import threading
from pathlib import Path
from urllib.parse import unquote, urlparse

from btforge.errors import BtforgeInputError

STATIC = Path(__file__).with_name("static")
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".json": "application/json", ".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}


def web_folder(path: Path, scratch: Path) -> Path:
    """The web-layout folder for ``path``: itself (a folder with info.json, or the info.json), or an export of
    the model a ``.ptm``, ``.rti`` or saved-buffer ``.npz`` file holds, written under ``scratch``."""
    from .layout import read_info, write_web
    if path.is_dir() or path.suffix.lower() == ".json":
        info = read_info(path)
        return Path(info["_folder"])
    if not path.is_file():
        raise BtforgeInputError(str(path), "not found", "give an exported folder (with info.json), a .ptm, .rti or "
                                "a saved model (.npz)")
    suffix = path.suffix.lower()
    if suffix == ".ptm":
        from btforge.plugins.ptm.model import PTMModel
        from btforge.plugins.ptm.ptmfile import read_ptm
        content = read_ptm(path)
        albedo = content.albedo if content.albedo is not None else content.coeffs[..., :0, 0]
        model = PTMModel(content.coeffs, albedo.astype("float32"), content.variant, "srgb")
    elif suffix == ".rti":
        from .hsh import read_rti
        model = read_rti(path)
    elif suffix == ".npz":
        from btforge.buffers import Buffer
        from btforge.registry import default_registry
        model = Buffer.from_file(path, default_registry().types)
    else:
        raise BtforgeInputError(str(path), f"expected a web layout, .ptm, .rti or .npz, found '{suffix}'")
    target = scratch / f"{len(list(scratch.iterdir()))}_{path.stem}"
    write_web(model, target)
    return target


class ViewServer(http.server.ThreadingHTTPServer):
    """Serves the page, ``models.json`` and, under ``/m/<index>/``, the files of each model's folder."""

    daemon_threads = True

    def __init__(self, folders: list[tuple[str, Path]], port: int = 0):
        self.folders = folders
        super().__init__(("127.0.0.1", port), _Handler)

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_address[1]}/"


class _Handler(http.server.BaseHTTPRequestHandler):
    server: ViewServer

    def log_message(self, format, *args):  # quiet: the terminal shows the address, not every request
        pass

    def do_GET(self):
        route = unquote(urlparse(self.path).path)
        if route in ("/", "/index.html"):
            return self._file(STATIC / "index.html")
        if route in ("/viewer.js", "/neural.js"):
            return self._file(STATIC / route[1:])
        if route == "/favicon.ico":
            return self._send(204, b"", "image/x-icon")
        if route == "/models.json":
            listing = [{"name": name, "url": f"m/{i}/"} for i, (name, _) in enumerate(self.server.folders)]
            return self._send(200, json.dumps(listing).encode(), CONTENT_TYPES[".json"])
        parts = route.strip("/").split("/")
        if len(parts) == 3 and parts[0] == "m" and parts[1].isdigit() and int(parts[1]) < len(self.server.folders):
            name = parts[2]
            if name == "info.json" or (name.startswith("plane_") and Path(name).suffix.lower() in CONTENT_TYPES):
                return self._file(self.server.folders[int(parts[1])][1] / name)
        self._send(404, b"not found", "text/plain")

    def _file(self, path: Path):
        try:
            body = path.read_bytes()
        except OSError:
            return self._send(404, b"not found", "text/plain")
        self._send(200, body, CONTENT_TYPES.get(path.suffix.lower(), "application/octet-stream"))

    def _send(self, status: int, body: bytes, content_type: str):
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        self.wfile.write(body)


def start(paths: list[Path], port: int = 0) -> tuple[ViewServer, threading.Thread, Path]:
    """Prepare the models and serve them in a background thread; returns the server, its thread and the scratch
    folder (remove it when done)."""
    scratch = Path(tempfile.mkdtemp(prefix="btforge-view-"))
    try:
        folders = [(p.stem if p.name != "info.json" else p.parent.name, web_folder(p, scratch)) for p in paths]
        names = [n if n else f"model {i}" for i, (n, _) in enumerate(folders)]
        server = ViewServer([(n, f) for n, (_, f) in zip(names, folders)], port)
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    return server, thread, scratch


def view_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("paths", nargs="+", metavar="PATH", help="exported folders (info.json), .ptm, .rti or saved "
                        "models (.npz); several: switch between them on the page")
    parser.add_argument("--port", type=int, default=8765, help="port on 127.0.0.1 (0: any free port; default 8765)")


def _stop_on_terminate(signum, frame):
    """A terminated server (kill, a service manager, a test) stops as on Ctrl-C, so its scratch folder goes too."""
    raise KeyboardInterrupt


def view_run(args) -> int:
    """Relight models in the browser: a local page with WebGL shading (drag the light, zoom, pan, snapshot)."""
    if not 0 <= args.port <= 65535:
        raise BtforgeInputError(f"--port {args.port}", "expected a port number in 0..65535")
    try:
        server, thread, scratch = start([Path(p) for p in args.paths], args.port)
    except OSError as exc:
        raise BtforgeInputError(f"--port {args.port}", f"cannot listen on 127.0.0.1 ({exc.strerror or exc})",
                                "give another --port, or 0 for any free one") from None
    print(f"btforge view: {len(server.folders)} model(s) at {server.url}  (Ctrl-C stops)", flush=True)
    try:
        signal.signal(signal.SIGTERM, _stop_on_terminate)
        thread.join()
    except KeyboardInterrupt:
        print("stopped", file=sys.stderr)
    finally:
        server.shutdown()
        shutil.rmtree(scratch, ignore_errors=True)
    return 0
