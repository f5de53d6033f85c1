"""Bad files reach the user as one clear message and exit code 2, never a traceback."""
import numpy as np

from btforge.cli import main
from btforge.plugins.stackio.images import write_exr


def capture(folder, sizes, nan_at=None):
    folder.mkdir(exist_ok=True)
    rows = []
    for i, (h, w) in enumerate(sizes):
        pixels = np.full((h, w, 3), 0.5, np.float32)
        if nan_at == i:
            pixels[1, 1, 0] = np.nan
            import OpenEXR
            OpenEXR.File({"type": OpenEXR.scanlineimage}, {"RGB": pixels}).write(str(folder / f"l{i}.exr"))
        else:
            write_exr(folder / f"l{i}.exr", pixels)
        rows.append(f"l{i}.exr 0.{i} 0.1 0.9")
    (folder / "dirs.lp").write_text(f"{len(sizes)}\n" + "\n".join(rows) + "\n")
    return folder / "dirs.lp"


def run_graph(tmp_path, lp):
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  read: {{stage: stackio.read, params: {{path: {lp}}}}}\n"
                     "  fit: {stage: ptm.fit, inputs: {stack: read.stack}}\n")
    return main(["run", str(graph), "--out", str(tmp_path / "out"), "--cache", str(tmp_path / "cache")])


def test_truncated_ptm(tmp_path, capsys):
    from btforge.plugins.ptm.ptmfile import write_ptm
    good = tmp_path / "good.ptm"
    write_ptm(good, "rgb", np.zeros((4, 4, 3, 6), np.float32), None)
    bad = tmp_path / "bad.ptm"
    bad.write_bytes(good.read_bytes()[:-10])
    assert main(["info", str(bad)]) == 2
    graph = tmp_path / "g.yaml"
    graph.write_text(f"nodes:\n  m: {{stage: ptm.read, params: {{path: {bad}}}}}\n"
                     "  r: {stage: relight.images, params: {lights: [[0, 0, 1]]}, inputs: {model: m.model}}\n")
    assert main(["run", str(graph), "--cache", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "bad.ptm" in err and "Traceback" not in err


def test_corrupt_light_file(tmp_path, capsys):
    lp = capture(tmp_path / "cap", [(4, 4)] * 7)
    lp.write_text(lp.read_text().replace("0.3 0.1 0.9", "0.3 zero 0.9"))
    assert run_graph(tmp_path, lp) == 2
    err = capsys.readouterr().err
    assert "dirs.lp, line 5" in err and "Traceback" not in err


def test_nan_pixels(tmp_path, capsys):
    lp = capture(tmp_path / "cap", [(4, 4)] * 7, nan_at=2)
    assert run_graph(tmp_path, lp) == 2
    err = capsys.readouterr().err
    assert "l2.exr" in err and "NaN" in err and "Traceback" not in err


def test_mismatched_image_sizes(tmp_path, capsys):
    lp = capture(tmp_path / "cap", [(4, 4)] * 6 + [(5, 4)])
    assert run_graph(tmp_path, lp) == 2
    err = capsys.readouterr().err
    assert "line 8" in err and "4 x 5" in err and "Traceback" not in err
