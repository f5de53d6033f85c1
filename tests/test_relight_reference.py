"""`btforge bench representations` runs relight-cli on the bench's own split: a stand-in executable that
behaves like relight-cli (a folder with a .lp in, info.json and planes out; -L/-D renders) checks the plumbing
- which photographs it is given, the crop, how its renderings are read - against scores computed here."""
import os
import stat
import sys
import textwrap
import types

import numpy as np
import pytest

from btforge.buffers import SampleStack
from btforge.plugins.relight import compare_stacks
from btforge.plugins.relight.bench import bench_representations, crop_window, psnr_table
from btforge.plugins.relight.relightcli import RELIGHT_BASES, RELIGHT_COLOR_MODES, crop_option, find_relight_cli
from btforge.plugins.stackio.images import write_stack

from lightsets import dome

# The stand-in "fits" every basis as the mean of the photographs it is given (after the -k crop) and renders
# that mean at every light: as display values with -I srgb, as 8-bit linear RGB otherwise (relight's default).
STAND_IN = textwrap.dedent(f"""\
    #!{sys.executable}
    import json, sys
    from pathlib import Path
    import numpy as np
    from PIL import Image
    def srgb_to_linear(x):
        return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
    args = sys.argv[1:]
    def option(flag, default=None):
        return args[args.index(flag) + 1] if flag in args else default
    if "-L" in args:
        rti = Path(args[0])
        mean = np.load(rti / "mean.npy")
        Image.fromarray(np.concatenate([mean, np.full(mean.shape[:2] + (1,), 255, np.uint8)], 2)).save(option("-D"))
        sys.exit(0)
    capture, out = Path(args[-2]), Path(args[-1])
    rows = (capture / "lights.lp").read_text().split("\\n")[1:]
    images = [np.asarray(Image.open(capture / r.split()[0]).convert("RGB"), np.float64) / 255 for r in rows if r]
    crop = option("-k")
    mean = np.mean(images, axis=0)
    if crop:
        size, x, y = crop.split("+")
        w, h = map(int, size.split("x"))
        mean = mean[int(y):int(y) + h, int(x):int(x) + w]
    color = option("-I", "linear")
    if color != "srgb":
        mean = srgb_to_linear(mean)
    out.mkdir(parents=True, exist_ok=True)
    np.save(out / "mean.npy", np.rint(mean * 255).astype(np.uint8))
    (out / "info.json").write_text(json.dumps({{"colorprofile": "sRGB" if color == "srgb" else "RGB"}}))
""")


@pytest.fixture
def capture(tmp_path):
    rng = np.random.default_rng(4)
    lights = dome(15, seed=4)
    samples = rng.integers(20, 236, (1, 15, 10, 12, 3), dtype=np.uint8)
    write_stack(SampleStack(samples, lights, np.array([[0.0, 0.0, 1.0]]), encoding="srgb8"), tmp_path / "cap",
                fmt="png")
    return tmp_path / "cap" / "lights.lp", samples, lights


@pytest.fixture
def stand_in(tmp_path):
    path = tmp_path / "bin" / "relight-cli"
    path.parent.mkdir()
    path.write_text(STAND_IN)
    path.chmod(path.stat().st_mode | stat.S_IEXEC)
    return path


def test_relight_cli_is_scored_on_the_bench_split(capture, stand_in, tmp_path, monkeypatch):
    light_file, samples, lights = capture
    monkeypatch.setattr("btforge.plugins.relight.relightcli.RELIGHT_BASES", RELIGHT_BASES[2:4])  # ptm, hsh
    args = types.SimpleNamespace(stack=str(light_file), test=None, out=str(tmp_path / "bench"), crop=8, repeat=1,
                                 only=["none"], relight_cli=str(stand_in))
    rows = bench_representations(args)
    assert len(rows) == 2 * len(RELIGHT_COLOR_MODES)
    held = np.arange(15) % 5 == 0
    r0, c0, h, w = crop_window(10, 12, 8)
    part = samples[:, :, r0:r0 + h, c0:c0 + w]
    mean = np.rint(part[:, ~held].astype(np.float64).mean(axis=1)).astype(np.uint8)   # what the stand-in fits
    test = SampleStack(np.ascontiguousarray(part[:, held]), lights[held], np.array([[0.0, 0.0, 1.0]]),
                       encoding="srgb8")
    predicted = SampleStack(np.repeat(mean[:, None], held.sum(), axis=1), lights[held], test.views,
                            encoding="srgb8")
    expected = compare_stacks(predicted, test)["psnr_db"]
    for row in rows:
        # display values exactly; through 8-bit linear RGB the darkest steps are coarser
        tolerance = 0.05 if row["params"].endswith("color=srgb") else 1.0
        assert abs(row["psnr_db"] - expected) < tolerance, (row, expected)
    table = (tmp_path / "bench" / "representations.md").read_text()
    assert "relight-cli ptm planes=18 color=srgb" in table


def test_relight_cli_left_out_with_a_note_when_absent(capture, tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("BTFORGE_RELIGHT_CLI", str(tmp_path / "nowhere"))
    monkeypatch.setattr("btforge.plugins.relight.relightcli.shutil.which", lambda name: None)  # not on PATH
    assert find_relight_cli() is None
    args = types.SimpleNamespace(stack=str(capture[0]), test=None, out=str(tmp_path / "bench"), crop=0, repeat=1,
                                 only=["ptm"], defaults=True)
    rows = bench_representations(args)
    assert [(r["representation"], r["params"]) for r in rows] == [("ptm", "defaults")]   # once, at its defaults
    assert "relight-cli: not found" in capsys.readouterr().err


def test_found_through_the_environment(stand_in, monkeypatch):
    monkeypatch.setenv("BTFORGE_RELIGHT_CLI", str(stand_in))
    assert find_relight_cli() == stand_in
    assert find_relight_cli(os.fspath(stand_in)) == stand_in


def test_crop_option_and_table():
    assert crop_option(10, 12, None) == []
    assert crop_option(10, 12, (1, 2, 8, 8)) == ["-k", "8x8+2+1"]
    rows = [{"capture": "a", "representation": "sh", "params": "light_order=auto", "psnr_db": 30.0},
            {"capture": "b", "representation": "sh", "params": "light_order=auto", "psnr_db": 32.5},
            {"capture": "a", "representation": "ptm", "params": "", "psnr_db": 20.0}]
    table = psnr_table(rows).splitlines()
    assert table[0] == "| configuration | a | b | mean |"
    assert table[2] == "| sh light_order=auto | 30.00 | 32.50 | 31.25 |"
    assert table[3] == "| ptm | 20.00 | - | - |"
