"""Small scatter plots for benchmark reports, drawn with Pillow (no plotting library needed)."""
from __future__ import annotations

import math
from typing import Sequence

from PIL import Image, ImageDraw, ImageFont

PALETTE = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (148, 103, 189), (255, 127, 14), (140, 86, 75),
           (227, 119, 194), (127, 127, 127)]


def pareto_front(xs: Sequence[float], ys: Sequence[float], higher_is_better: bool = True) -> list[int]:
    """Indices of points no other point beats on both axes (smaller x, better y), ordered by x."""
    sign = 1.0 if higher_is_better else -1.0
    order = sorted(range(len(xs)), key=lambda i: (xs[i], -sign * ys[i]))
    front, best = [], -math.inf
    for i in order:
        if sign * ys[i] > best:
            front.append(i)
            best = sign * ys[i]
    return front


def scatter_png(path, xs, ys, labels, groups, *, title: str, xlabel: str, ylabel: str, log_x: bool = True,
                higher_is_better: bool = True, size=(960, 640)) -> None:
    """Write a labelled scatter plot with the Pareto front (less x, better y) marked, atomically, as PNG."""
    from .atomic import atomic_write
    width, height = size
    left, right, top, bottom = 80, 30, 50, 70
    img = Image.new("RGB", size, "white")
    draw = ImageDraw.Draw(img)
    font = ImageFont.load_default()
    finite = [(x, y) for x, y in zip(xs, ys) if x > 0 and math.isfinite(y)]
    fx = [math.log10(x) if log_x else x for x, _ in finite] or [0.0, 1.0]
    fy = [y for _, y in finite] or [0.0, 1.0]
    x0, x1 = min(fx), max(fx)
    y0, y1 = min(fy), max(fy)
    pad_x = max((x1 - x0) * 0.08, 0.1)
    pad_y = (y1 - y0) * 0.08 or max(abs(y1) * 0.05, 1e-3)  # relative: scores may span 0.01 or 10 dB
    x0, x1, y0, y1 = x0 - pad_x, x1 + pad_x, y0 - pad_y, y1 + pad_y

    def to_px(x, y):
        xv = math.log10(x) if log_x else x
        return (left + (xv - x0) / (x1 - x0) * (width - left - right),
                height - bottom - (y - y0) / (y1 - y0) * (height - top - bottom))

    draw.rectangle([left, top, width - right, height - bottom], outline="black")
    for k in range(6):  # ticks
        yv = y0 + (y1 - y0) * k / 5
        py = height - bottom - (yv - y0) / (y1 - y0) * (height - top - bottom)
        draw.line([left - 4, py, left, py], fill="black")
        draw.text((8, py - 6), f"{yv:.3g}", fill="black", font=font)
        xv = x0 + (x1 - x0) * k / 5
        px = left + (xv - x0) / (x1 - x0) * (width - left - right)
        draw.line([px, height - bottom, px, height - bottom + 4], fill="black")
        draw.text((px - 18, height - bottom + 8), f"{10 ** xv:.3g}" if log_x else f"{xv:.3g}", fill="black", font=font)
    draw.text((left, 15), title, fill="black", font=font)
    draw.text((width // 2 - 60, height - 30), xlabel + (" (log scale)" if log_x else ""), fill="black", font=font)
    draw.text((8, top - 30), ylabel, fill="black", font=font)

    valid = [i for i, (x, y) in enumerate(zip(xs, ys)) if x > 0 and math.isfinite(y)]
    front = [valid[j] for j in pareto_front([xs[i] for i in valid], [ys[i] for i in valid], higher_is_better)]
    if len(front) > 1:
        draw.line([to_px(xs[i], ys[i]) for i in front], fill=(120, 120, 120), width=2)
    colours = {g: PALETTE[k % len(PALETTE)] for k, g in enumerate(dict.fromkeys(groups))}
    for i in valid:
        px, py = to_px(xs[i], ys[i])
        r = 6 if i in front else 4
        draw.ellipse([px - r, py - r, px + r, py + r], fill=colours[groups[i]], outline="black" if i in front else None)
        draw.text((px + 8, py - 6), labels[i], fill=colours[groups[i]], font=font)
    draw.text((width - right - 260, top + 8), "outlined + grey line: Pareto front", fill=(90, 90, 90), font=font)
    with atomic_write(path) as handle:
        img.save(handle, format="PNG")


def light_label(light) -> str:
    """``'el 45.0 az 120.0'``: a light's elevation above the surface and azimuth (degrees, from +x toward +y)."""
    x, y, z = (float(v) for v in light)
    elevation = math.degrees(math.asin(max(-1.0, min(1.0, z))))
    azimuth = math.degrees(math.atan2(y, x)) % 360.0
    return f"el {elevation:.1f} az {azimuth:.1f}"


def labelled_grid(tiles, labels: Sequence[str], columns: int, header: str = "", strip: int = 12):
    """One RGB uint8 image of ``tiles`` (equal-size ``[h, w, 3]`` uint8) in a grid, each with its label in a strip
    above it (so the label covers no pixel of the tile), and an optional header line on top."""
    import numpy as np
    h, w = tiles[0].shape[:2]
    rows = -(-len(tiles) // columns)
    top = strip if header else 0
    sheet = Image.new("RGB", (columns * w, top + rows * (h + strip)), "black")
    draw = ImageDraw.Draw(sheet)
    font = ImageFont.load_default()
    if header:
        draw.text((2, 0), header, fill=(255, 255, 0), font=font)
    for i, (tile, label) in enumerate(zip(tiles, labels)):
        r, q = divmod(i, columns)
        y0 = top + r * (h + strip)
        sheet.paste(Image.fromarray(np.ascontiguousarray(tile)), (q * w, y0 + strip))
        draw.text((q * w + 2, y0), label, fill=(255, 255, 255), font=font)
    return sheet
