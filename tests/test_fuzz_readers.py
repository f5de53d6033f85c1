"""Mutation fuzz of every file reader: a damaged file is read or refused cleanly, never a crash or a hang.

Valid files come from btforge itself (a small graph writes a capture, a .ptm, a saved model, a web layout, a
height mesh, a tile set, a coordinate EXR and a store; an HSH .rti, an OBJ mesh and a scene are written by the
plugins' writers or as text).  Each case damages one of them (tests/fuzzing.py) and runs the reader as a user would:
``btforge info FILE``, or a one-node graph under ``btforge run`` whose stage reads it.  Cases run in worker
processes, so a segmentation fault or a hang in native code is a failed case, not a dead test run.

CI runs ``BTFORGE_FUZZ_CASES`` (default 240, 10 per reader) cases with a fixed seed (``BTFORGE_FUZZ_SEED``,
default 0); set them higher (e.g. 10000) to explore, and ``BTFORGE_FUZZ_READERS`` (e.g. ``.ply,scene``) to fuzz
only some readers.  A failure lists the reader, the damaged file, the mutation
and the case seed.
"""
from __future__ import annotations

import os
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import btforge

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fuzzing import Reader, make_cases, run_cases, summary  # noqa: E402

CASES = int(os.environ.get("BTFORGE_FUZZ_CASES", "240"))
SEED = int(os.environ.get("BTFORGE_FUZZ_SEED", "0"))
ONLY = os.environ.get("BTFORGE_FUZZ_READERS", "")  # fuzz only readers whose name contains one of these (comma-separated)

SEED_GRAPH = """
nodes:
  material: {stage: demo.material, params: {size: [24, 24], lights: 10, bumps: 6, seed: 3}}
  capture:  {stage: stackio.write, params: {dir: capture, format: exr}, inputs: {stack: material.stack}}
  png:      {stage: stackio.write, params: {dir: capture_png, format: png}, inputs: {stack: material.stack}}
  fit:      {stage: ptm.fit, params: {variant: rgb, space: srgb}, inputs: {stack: material.stack}}
  ptm:      {stage: ptm.write, params: {path: model.ptm}, inputs: {model: fit.model}}
  saved:    {stage: models.write, params: {path: model.btfm}, inputs: {model: fit.model}}
  web:      {stage: web.export, params: {dir: web}, inputs: {model: fit.model}}
  web_jpg:  {stage: web.export, params: {dir: web_jpg, format: jpg}, inputs: {model: fit.model}}
  neural:   {stage: neural.fit, params: {latent: 5, hidden: 8, layers: 2, epochs: 1, texels: 50}, inputs: {stack: material.stack}}
  web_nn:   {stage: web.export, params: {dir: web_neural}, inputs: {model: neural.model}}
  height:   {stage: height.from_shading, params: {iterations: 3, rounds: 1}, inputs: {stack: material.stack}}
  ply:      {stage: height.write, params: {path: height.ply}, inputs: {height: height.height}}
  tiles:    {stage: wang.tiles, params: {tile: 8, edge: 2, seed: 1}, inputs: {exemplar: material.stack}}
  wang:     {stage: wang.write_tiles, params: {path: set.wang}, inputs: {tiles: tiles.tiles}}
  tiling:   {stage: wang.tiling, params: {rows: 2, cols: 2}, inputs: {tiles: tiles.tiles}}
  coords:   {stage: synth.write_coords, params: {path: coords.exr}, inputs: {coords: tiling.coords}}
  btf:      {stage: demo.btf, params: {size: [8, 8], lights: 4, views: 2, store: store.zarr, block: [4, 4]}}
"""

OBJ = """# a textured quad and a triangle, with normals
v -1 -1 0
v 1 -1 0
v 1 1 0.25
v -1 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vn 0 0 1
f 1/1/1 2/2/1 3/3/1 4/4/1
f 1/1/1 3/3/1 2/2/1
"""

SCENE = """camera: {type: perspective, width: 16, height: 16, position: [0, -4, 3], look_at: [0, 0, 0], up: [0, 0, 1]}
meshes:
  ground: {file: quad.obj, material: stone}
  hill: {file: height.ply, material: stone, scale: [0.05, 0.05, 0.05], position: [0, 0, 0.2]}
lights:
  - {type: point, position: [0, 0, 5], intensity: 2}
"""


def _one_node(stage: str, path: str) -> str:
    return f"nodes:\n  reader: {{stage: {stage}, params: {{path: {path}}}}}\n"


def _write_extra_files(folder: Path) -> None:
    from ubo2014_files import random_factors, write_dfmf

    from btforge.plugins.web.hsh import HSHModel, write_rti
    rng = np.random.default_rng(0)
    write_rti(folder / "model.rti", HSHModel(rng.uniform(-1, 1, (6, 5, 3, 9)).astype(np.float32)))
    lights = np.array([[0.2, 0.0], [0.5, 1.0], [0.9, 2.0]])
    write_dfmf(folder / "capture.btf", lights, np.array([[0.0, 0.0], [0.6, 1.5]]), 4, 3,
               random_factors(rng, 6, 12))
    _jpeg_capture(folder / "capture_png", folder / "capture_jpg")
    (folder / "quad.obj").write_text(OBJ)
    (folder / "scene.yaml").write_text(SCENE)
    graphs = {"read_stack.yaml": _one_node("stackio.read", "capture/lights.lp"),
              "read_ptm.yaml": _one_node("ptm.read", "model.ptm"),
              "read_model.yaml": _one_node("models.read", "model.btfm"),
              "read_tiles.yaml": _one_node("wang.read_tiles", "set.wang"),
              "read_web.yaml": _one_node("web.read", "web/info.json"),
              "read_scene.yaml": _one_node("render.read_scene", "scene.yaml"),
              "read_btf.yaml": _one_node("stackio.read", "capture.btf"),
              "read_png.yaml": _one_node("stackio.read", "capture_png/lights.lp"),
              "read_jpg.yaml": _one_node("stackio.read", "capture_jpg/lights.lp"),
              "fit_jpg.yaml": _one_node("ptm.fit_capture", "capture_jpg/lights.lp"),
              "read_web_jpg.yaml": _one_node("web.read", "web_jpg/info.json"),
              "read_web_neural.yaml": _one_node("web.read", "web_neural/info.json")}
    for name, text in graphs.items():
        (folder / name).write_text(text)


def _jpeg_capture(png_folder: Path, folder: Path) -> None:
    """The PNG capture as JPEG files (the format of most RTI domes) with its light file."""
    from PIL import Image
    folder.mkdir()
    lines = (png_folder / "lights.lp").read_text().splitlines()
    for i, line in enumerate(lines[1:], 1):
        name = line.split()[0]
        Image.open(png_folder / name).convert("RGB").save(folder / name.replace(".png", ".jpg"), quality=90)
        lines[i] = line.replace(".png", ".jpg")
    (folder / "lights.lp").write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="session")
def seed_files(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz-seed")
    (folder / "seed.yaml").write_text(SEED_GRAPH)
    btforge.run(folder / "seed.yaml", out_dir=folder, use_cache=False)
    _write_extra_files(folder)
    return folder


def _run(graph: str) -> tuple[str, ...]:
    return ("run", f"{{dir}}/{graph}", "--no-cache", "--out", "{dir}/out")


def _info(name: str) -> tuple[str, ...]:
    return ("info", f"{{dir}}/{name}")


def readers(seed: Path) -> list[Reader]:
    store = tuple(str(p.relative_to(seed)) for p in sorted((seed / "store.zarr").rglob("*")) if p.is_file())
    web = ("web/info.json", "web/plane_0.png", "web/plane_4.png")
    return [
        Reader("info .lp", ("capture/lights.lp",), _info("capture/lights.lp")),
        Reader("stackio.read (.lp + EXR)", ("capture/lights.lp", "capture/light_000.exr", "capture/light_007.exr"),
               _run("read_stack.yaml")),
        Reader("stackio.read (.lp + PNG)", ("capture_png/lights.lp", "capture_png/light_002.png"),
               _run("read_png.yaml")),
        Reader("stackio.read (.lp + JPEG)", ("capture_jpg/light_000.jpg", "capture_jpg/light_004.jpg"),
               _run("read_jpg.yaml")),
        Reader("ptm.fit_capture (.lp + JPEG)", ("capture_jpg/light_001.jpg", "capture_jpg/light_006.jpg"),
               _run("fit_jpg.yaml")),
        Reader("info .exr (image)", ("capture/light_003.exr",), _info("capture/light_003.exr")),
        Reader("info .exr (coordinates)", ("coords.exr",), _info("coords.exr")),
        Reader("info .ptm", ("model.ptm",), _info("model.ptm")),
        Reader("ptm.read", ("model.ptm",), _run("read_ptm.yaml")),
        Reader("info .btfm", ("model.btfm",), _info("model.btfm")),
        Reader("models.read", ("model.btfm",), _run("read_model.yaml")),
        Reader("info .ply (height mesh)", ("height.ply",), _info("height.ply")),
        Reader("render.read_scene (YAML + OBJ + PLY)", ("scene.yaml", "quad.obj", "height.ply"), _run("read_scene.yaml")),
        Reader("info .wang", ("set.wang",), _info("set.wang")),
        Reader("wang.read_tiles", ("set.wang",), _run("read_tiles.yaml")),
        Reader("info web layout", web, _info("web/info.json")),
        Reader("web.read", web, _run("read_web.yaml")),
        Reader("web.read (JPEG planes)", ("web_jpg/plane_1.jpg", "web_jpg/info.json"), _run("read_web_jpg.yaml")),
        Reader("web.read (neural)", ("web_neural/info.json", "web_neural/plane_2.png"), _run("read_web_neural.yaml")),
        Reader("info .rti (HSH)", ("model.rti",), _info("model.rti")),
        Reader("info .zarr store", store, _info("store.zarr")),
        Reader("info .btf (UBO2014)", ("capture.btf",), _info("capture.btf")),
        Reader("stackio.read (.btf)", ("capture.btf",), _run("read_btf.yaml")),
        Reader("validate graph", ("seed.yaml",), ("validate", "{dir}/seed.yaml")),
    ]


def test_seed_files_are_read_cleanly(seed_files, tmp_path):
    """Undamaged, every reader reads its file: the fuzz starts from files that work."""
    from fuzzing import Case, run_case
    for reader in readers(seed_files):
        got = run_case(reader, Case(reader.name, "", 0), seed_files, tmp_path, mutate_member=False)
        assert got["verdict"] == "read", (reader.name, got)


def test_damaged_files_are_read_or_refused_cleanly(seed_files, tmp_path):
    all_readers = [r for r in readers(seed_files) if not ONLY or any(w and w in r.name for w in ONLY.split(","))]
    per_reader = max(1, CASES // len(all_readers))
    cases = make_cases(all_readers, per_reader, SEED)
    started = time.perf_counter()
    outcomes = run_cases(all_readers, cases, seed_files, tmp_path, workers=2, timeout=120)
    seconds = time.perf_counter() - started
    table = summary(outcomes)
    lines = [f"{len(outcomes)} cases in {seconds:.0f} s (seed {SEED})"]
    lines += [f"  {name}: {row}" for name, row in table.items()]
    print("\n".join(lines))
    failures = [o for o in outcomes if not o.clean]
    assert len(outcomes) == len(cases)
    assert not failures, "\n".join(lines + [textwrap.shorten(
        f"{o.case.reader} | {o.case.member} | {o.mutation} | seed {o.case.seed} | {o.verdict}: {o.detail}", 400)
        for o in failures[:40]])


def test_a_crash_in_native_code_is_a_failed_case_not_a_dead_run(seed_files, tmp_path):
    """The harness itself: a reader that kills its process (here a deliberate segmentation fault) is recorded as
    a crash of that case, and the next case runs on a fresh worker."""
    from fuzzing import Case
    crash = Reader("segfault", ("seed.yaml",), call="fuzzing:crash", entry="seed.yaml")
    fine = Reader("validate graph", ("seed.yaml",), ("validate", "{dir}/seed.yaml"))
    cases = [Case("segfault", "seed.yaml", 1), Case("validate graph", "seed.yaml", 2)]
    first, second = run_cases([crash, fine], cases, seed_files, tmp_path, workers=1, timeout=120)
    assert first.verdict == "crash" and "-11" in first.detail and first.mutation
    assert second.clean
