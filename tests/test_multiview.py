"""Multi-view captures: UBO-style BTF folders, .lvp round trips, relighting at views, and the representations bench."""
import csv
import math
import types

import numpy as np
import pytest
from PIL import Image

import btforge
from btforge import BtforgeInputError
from btforge.plugins.stackio.images import load_stack, write_stack


def test_btf_folder_names_carry_the_angles(tmp_path):
    rng = np.random.default_rng(0)
    for tv, pv in [(0, 0), (30, 90)]:
        for tl, pl in [(15, 0), (45, 120), (60, 240)]:
            pixels = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
            Image.fromarray(pixels).save(tmp_path / f"sample_tl{tl}_pl{pl}_tv{tv}_pv{pv}.png")
    (tmp_path / "notes.txt").write_text("ignored")
    stack = btforge.stage("stackio.read")(path=str(tmp_path))["stack"]
    assert stack.samples.shape == (2, 3, 4, 5, 3)
    theta, phi = math.radians(45), math.radians(120)
    np.testing.assert_allclose(stack.lights[1], [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi),
                                                 math.cos(theta)], atol=1e-6)
    np.testing.assert_allclose(stack.views[1], [0, math.sin(math.radians(30)), math.cos(math.radians(30))], atol=1e-6)
    expected = np.asarray(Image.open(tmp_path / "sample_tl60_pl240_tv30_pv90.png"))
    np.testing.assert_array_equal(stack.samples[1, 2], expected)


def test_folder_without_btf_names_is_a_clear_error(tmp_path):
    Image.fromarray(np.zeros((2, 2, 3), np.uint8)).save(tmp_path / "photo.png")
    with pytest.raises(BtforgeInputError, match="tl15_pl0_tv30_pv120"):
        load_stack(tmp_path)


def test_demo_btf_round_trips_through_lvp(tmp_path):
    stack = btforge.stage("demo.btf")(size=[12, 10], lights=6, views=3)["stack"]
    assert stack.samples.shape == (3, 6, 12, 10, 3)
    assert np.isfinite(stack.samples).all() and stack.samples.min() >= 0
    write_stack(stack, tmp_path / "btf", fmt="exr")
    back = load_stack(tmp_path / "btf" / "lights.lvp")
    np.testing.assert_allclose(back.samples, stack.samples, rtol=1e-6)
    np.testing.assert_allclose(back.views, stack.views, atol=1e-6)


def test_glossy_btf_depends_on_the_view():
    stack = btforge.stage("demo.btf")(size=[16, 16], lights=8, views=4, specular=1.0)["stack"]
    assert np.abs(stack.samples[0] - stack.samples[1]).max() > 0.05


def test_relight_at_views_of_a_view_dependent_model():
    stack = btforge.stage("demo.btf")(size=[8, 8], lights=16, views=4)["stack"]
    model = btforge.stage("sh.fit")(stack=stack, light_order=3, view_order=2)["model"]
    views = [[0, 0, 1], [0.5, 0, 0.866]]
    out = btforge.stage("relight.images")(model=model, lights=[[0.3, 0.2, 0.93]], views=views)["stack"]
    assert out.samples.shape == (2, 1, 8, 8, 3)
    ptm = btforge.stage("ptm.fit")(stack=btforge.stage("demo.material")(size=[8, 8], lights=12)["stack"])["model"]
    flat = btforge.stage("relight.images")(model=ptm, lights=[[0.3, 0.2, 0.93]], views=views)["stack"]
    np.testing.assert_array_equal(flat.samples[0], flat.samples[1])  # a PTM looks the same from every view


def test_representations_bench_writes_csv_and_plot(tmp_path):
    from btforge.plugins.relight.bench import bench_representations
    write_stack(btforge.stage("demo.material")(size=[16, 16], lights=20)["stack"], tmp_path / "cap", fmt="exr")
    args = types.SimpleNamespace(stack=str(tmp_path / "cap" / "lights.lp"), test=None, out=str(tmp_path / "bench"),
                                 crop=0, repeat=1, only=["ptm", "sh", "lafortune"])
    rows = bench_representations(args)
    with open(tmp_path / "bench" / "representations.csv") as handle:
        table = list(csv.DictReader(handle))
    assert {"representation", "params", "fit_seconds", "relight_seconds_per_megapixel", "bytes_per_texel",
            "psnr_db", "max_abs_error"} <= set(table[0])
    assert {r["representation"] for r in rows} == {"ptm", "sh", "lafortune"}
    # 16 fitting lights cannot determine 4 lobes (17 unknowns): that row is skipped, the others are measured
    assert {r["params"] for r in rows if r["representation"] == "lafortune"} == {
        f"lobes={n}" for n in (1, 2, 3)}
    assert (tmp_path / "bench" / "representations.png").stat().st_size > 1000
