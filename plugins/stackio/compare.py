"""How close one stack is to another at the same lights: the figures ``relight.compare`` and contact sheets
report."""
from __future__ import annotations

import numpy as np

from btforge import SampleStack
from btforge.buffers import linear_to_srgb


def compare_stacks(stack: SampleStack, reference: SampleStack, peak: float = 1.0, per_light: bool = False) -> dict:
    """PSNR (overall, worst and median light), RMSE and max error of ``stack`` against ``reference``.

    On display values (sRGB-encoded, clipped) when the reference is an 8-bit capture, as RTI tools report it;
    on linear values otherwise.  Streams over bands of rows.  ``per_light`` adds ``psnr_db_per_light``.
    """
    display = reference.encoding == "srgb8"
    per_light_sq = np.zeros(reference.n_light)
    worst = 0.0
    for rows in reference.row_bands():
        a, b = stack.linear(rows), reference.linear(rows)
        if display:
            a, b = linear_to_srgb(a), linear_to_srgb(b)
        diff = np.abs(a.astype(np.float64) - b)
        per_light_sq += (diff ** 2).sum(axis=(0, 2, 3, 4))
        worst = max(worst, float(diff.max()))
    per_light_mse = per_light_sq / (reference.n_view * reference.height * reference.width * reference.n_channel)

    def psnr(mse):
        return float("inf") if mse == 0 else float(10 * np.log10(peak ** 2 / mse))

    mse = float(per_light_mse.mean())
    light_psnrs = [psnr(m) for m in per_light_mse]
    scores = {"psnr_db": round(psnr(mse), 3), "psnr_db_worst_light": round(min(light_psnrs), 3),
              "psnr_db_median_light": round(float(np.median(light_psnrs)), 3), "rmse": round(mse ** 0.5, 6),
              "max_abs_error": round(worst, 6), "domain": "srgb" if display else "linear"}
    if per_light:
        scores["psnr_db_per_light"] = light_psnrs
    return scores
