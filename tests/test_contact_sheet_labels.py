"""Contact sheets people read: every tile labelled with its light; fit-vs-truth sheets name their sides and PSNR."""
from __future__ import annotations

import numpy as np
from PIL import Image

import btforge
from btforge import SampleStack
from btforge.plot import light_label
from btforge.plugins.relight import compare_stacks


def test_light_label_reads_elevation_and_azimuth():
    assert light_label([0, 0, 1]) == "el 90.0 az 0.0"
    assert light_label([0, -np.sqrt(0.5), np.sqrt(0.5)]) == "el 45.0 az 270.0"


def test_sheet_labels_tiles_and_sides(tmp_path):
    rng = np.random.default_rng(0)
    lights = [[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8]]
    truth = SampleStack(rng.uniform(0.2, 0.8, (1, 3, 40, 60, 3)).astype(np.float32), lights, [[0, 0, 1]])
    fit = SampleStack((truth.samples * 0.9).astype(np.float32), lights, [[0, 0, 1]])
    sheet = btforge.stage("stackio.contact_sheet")
    sheet(stack=fit, path=str(tmp_path / "plain.png"), columns=3)
    sheet(stack=fit, beside=truth, path=str(tmp_path / "pair.png"), columns=3, sides="fit,measured")
    plain = np.asarray(Image.open(tmp_path / "plain.png"))
    pair = np.asarray(Image.open(tmp_path / "pair.png"))
    strip = 12
    assert plain.shape == (40 + strip, 3 * 60, 3)            # a label strip above the tiles, covering none
    assert plain[:strip].max() > 200                          # the label is drawn
    assert pair.shape == (strip + 40 + strip, 3 * 120, 3)     # header, label strip, tiles twice as wide
    assert pair[:strip].max() > 200
    per_light = compare_stacks(fit, truth, per_light=True)["psnr_db_per_light"]
    assert len(per_light) == 3 and all(np.isfinite(per_light))
