"""relight-cli (CNR-ISTI's RTI builder, https://github.com/cnr-isti-vclab/relight) as a reference in
``btforge bench representations``: the same fitting lights, the same held-out lights, the same scores.

relight-cli is not a dependency: the bench finds it through ``BTFORGE_RELIGHT_CLI`` (the executable's path) or
``relight-cli`` on ``PATH`` and leaves it out, with a note, when neither exists.  For each basis it builds an
RTI from the fitting photographs (``relight-cli -b BASIS -p PLANES FOLDER OUT``, coefficient planes stored
as JPEG at relight's default quality) and renders every held-out light (``relight-cli OUT -L x:y:z -D
image.png``).  By default relight-cli converts 8-bit sRGB photographs to 8-bit linear RGB before fitting
and renders linear RGB (``info.json`` says ``"colorprofile": "RGB"``); with ``-I srgb`` it fits and renders
display values (``"sRGB"``).  The bench runs both and reads each rendering as its ``info.json`` says, so both
are scored on display values like the photographs.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

RELIGHT_ENV = "BTFORGE_RELIGHT_CLI"
#: (basis, planes) relight-cli builds: its default RBF at 9 and 18 planes, RGB PTM (18 = 6 per channel),
#: HSH at 27 planes (9 per channel) and bilinear at 18.
RELIGHT_BASES = (("rbf", 9), ("rbf", 18), ("ptm", 18), ("hsh", 27), ("bilinear", 18))
#: relight-cli's colour modes (``-I``): its default converts the photographs to 8-bit linear RGB before fitting
#: (and renders linear RGB); ``srgb`` fits the display values as they are.
RELIGHT_COLOR_MODES = ("linear", "srgb")


def find_relight_cli(explicit: str | None = None) -> Path | None:
    """relight-cli's executable: ``explicit``, else ``$BTFORGE_RELIGHT_CLI``, else ``relight-cli`` on PATH."""
    for candidate in (explicit, os.environ.get(RELIGHT_ENV), shutil.which("relight-cli")):
        if candidate and Path(candidate).is_file() and os.access(candidate, os.X_OK):
            return Path(candidate)
    return None


def write_capture(folder: Path, entries) -> None:
    """A folder relight-cli reads: links to the photographs of ``entries`` (light-file rows with an absolute
    ``path`` and a ``light``) and a ``.lp`` file of their directions."""
    folder.mkdir(parents=True, exist_ok=True)
    lines = [str(len(entries))]
    for index, (path, light) in enumerate(entries):
        name = f"image{index:03d}{Path(path).suffix.lower()}"
        os.symlink(Path(path).resolve(), folder / name)
        lines.append(f"{name} {light[0]:.7f} {light[1]:.7f} {light[2]:.7f}")
    (folder / "lights.lp").write_text("\n".join(lines) + "\n")


def crop_option(height: int, width: int, crop: tuple[int, int, int, int] | None) -> list[str]:
    """relight-cli's ``-k WxH+X+Y`` for a crop ``(row, col, rows, cols)`` of an ``height x width`` capture."""
    if crop is None or (crop[2] >= height and crop[3] >= width):
        return []
    row, col, rows, cols = crop
    return ["-k", f"{cols}x{rows}+{col}+{row}"]


def _run(argv: list[str], what: str) -> float:
    from btforge.errors import BtforgeError
    start = time.perf_counter()
    done = subprocess.run(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise BtforgeError(f"relight-cli failed to {what} (exit {done.returncode}): {' '.join(argv)}\n"
                           f"{done.stdout[-1500:]}")
    return seconds


def build_rti(exe: Path, capture: Path, out: Path, basis: str, planes: int, color: str,
              crop_args: list[str]) -> float:
    """Fit one basis with relight-cli; the wall seconds of the whole process (image decoding included)."""
    return _run([str(exe), "-b", basis, "-p", str(planes), "-I", color, *crop_args, str(capture), str(out)],
                f"build a {basis} RTI with {planes} planes")


def rendered_encoding(rti: Path) -> str:
    """How relight-cli's renderings of ``rti`` hold values: ``srgb8`` (display values) for an ``sRGB`` colour
    profile, ``linear`` (8-bit linear RGB) otherwise (its default, ``RGB``)."""
    import json
    profile = json.loads((rti / "info.json").read_text()).get("colorprofile", "RGB")
    return "srgb8" if profile.lower() == "srgb" else "linear"


def render_lights(exe: Path, rti: Path, lights: np.ndarray, scratch: Path) -> np.ndarray:
    """relight-cli's renderings of ``rti`` at ``lights [L, 3]``: uint8 ``[L, H, W, 3]`` display values."""
    from PIL import Image
    images = []
    for index, light in enumerate(np.asarray(lights, np.float64)):
        target = scratch / f"relit{index:03d}.png"
        _run([str(exe), str(rti), "-L", f"{light[0]:.7f}:{light[1]:.7f}:{light[2]:.7f}", "-D", str(target)],
             f"render light {index}")
        with Image.open(target) as image:
            images.append(np.asarray(image.convert("RGB")))
    return np.stack(images)


def plane_bytes(rti: Path) -> int:
    """The bytes relight-cli wrote for a model: its coefficient planes and ``info.json``."""
    return sum(f.stat().st_size for f in rti.iterdir() if f.is_file())


def measure_relight(exe: Path, fit_entries, test, crop, full_shape: tuple[int, int]) -> list[dict]:
    """One row per :data:`RELIGHT_BASES` entry, in the bench's columns: relight-cli fitted on ``fit_entries``
    (``(path, light)`` rows) and scored on the held-out stack ``test`` (already cropped like ``synth.crop``)."""
    from btforge.buffers import SampleStack

    from . import compare_stacks
    rows = []
    with tempfile.TemporaryDirectory(prefix="btforge-relight-") as tmp:
        capture = Path(tmp) / "capture"
        write_capture(capture, fit_entries)
        crop_args = crop_option(*full_shape, crop)
        for (basis, planes), color in ((b, c) for b in RELIGHT_BASES for c in RELIGHT_COLOR_MODES):
            out = Path(tmp) / f"{basis}{planes}{color}"
            fit_seconds = build_rti(exe, capture, out, basis, planes, color, crop_args)
            start = time.perf_counter()
            relit = render_lights(exe, out, test.lights, Path(tmp))
            relight_s = time.perf_counter() - start
            if rendered_encoding(out) == "linear":
                relit = (relit / np.float32(255.0)).astype(np.float32)
            predicted = SampleStack(relit[None], test.lights, test.views, test.channels,
                                    "srgb8" if relit.dtype == np.uint8 else "linear")
            scores = compare_stacks(predicted, test)
            megapixels = test.n_light * test.height * test.width / 1e6
            rows.append({"representation": f"relight-cli {basis}", "params": f"planes={planes} color={color}",
                         "fit_seconds": round(fit_seconds, 4),
                         "relight_seconds_per_megapixel": round(relight_s / megapixels, 5),
                         "bytes_per_texel": round(plane_bytes(out) / (test.height * test.width), 2),
                         "psnr_db": scores["psnr_db"], "psnr_db_worst_light": scores["psnr_db_worst_light"],
                         "max_abs_error": scores["max_abs_error"], "domain": scores["domain"]})
    return rows
