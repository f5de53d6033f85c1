"""Light directions of a capture from the mirror spheres in its images: the whole calibration, its light file
and its report picture."""
from __future__ import annotations

import dataclasses
import glob
import math
import os
from pathlib import Path
from typing import Sequence

import numpy as np

from btforge.errors import BtforgeInputError

from .sphere import (Circle, Highlight, angular_uncertainty_deg, estimate_focal, find_highlight, find_spheres,
                     luminance, reflect)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".tga", ".exr", ".bmp")
MASK_WORDS = ("mask",)  # e.g. psm_uw's chrome.mask.tga is not a photograph
REPORT_SUFFIX = "calibration"  # our own report pictures (dirs_calibration.png) beside the photographs


@dataclasses.dataclass(frozen=True)
class Calibration:
    """Result of :func:`calibrate`: for image ``i`` of ``images``, ``lights[i]`` (NaN when not found),
    ``uncertainty_deg[i]`` and ``confidence[i]`` in [0, 1]; ``highlights[s][i]`` per sphere ``s``; the camera's
    ``focal`` length in pixels (None: orthographic) and, when it was estimated, ``focal_notes`` per sphere."""

    images: tuple[Path, ...]
    spheres: tuple[Circle, ...]
    highlights: tuple[tuple[Highlight, ...], ...]
    lights: np.ndarray
    uncertainty_deg: np.ndarray
    confidence: np.ndarray
    shape: tuple[int, int]
    excluded: frozenset[str] = frozenset()
    focal: float | None = None
    focal_notes: tuple[str, ...] = ()

    @property
    def found(self) -> np.ndarray:
        """Images with a light: a highlight was found and the user did not exclude them."""
        return np.isfinite(self.lights[:, 0]) & ~np.array([p.name in self.excluded for p in self.images])

    def problems(self) -> list[str]:
        """One line per image left without a light, naming the image and why."""
        out = []
        for i in np.flatnonzero(~self.found):
            if self.images[i].name in self.excluded:
                out.append(f"{self.images[i].name}: left out on request")
                continue
            reasons = "; ".join(f"sphere {s + 1}: {self.highlights[s][i].problem}" for s in range(len(self.spheres)))
            out.append(f"{self.images[i].name}: no light ({reasons})")
        return out

    def excluding(self, names) -> "Calibration":
        """The same calibration with the images ``names`` (file names) left out: a wrong light deleted."""
        names = frozenset(names)
        unknown = sorted(names - {p.name for p in self.images})
        if unknown:
            raise BtforgeInputError(f"exclude {', '.join(unknown)}", "names no calibrated image",
                                    f"give file names such as {self.images[0].name}")
        return dataclasses.replace(self, excluded=self.excluded | names)


def image_list(pattern: str | os.PathLike | Sequence, base: Path | None = None) -> list[Path]:
    """Images named by a folder, a glob, or a list of files/globs, sorted by name; masks and calibration
    report pictures are left out."""
    items = [pattern] if isinstance(pattern, (str, os.PathLike)) else list(pattern)
    found: list[Path] = []
    for item in items:
        path = Path(os.path.expanduser(str(item)))
        if base is not None and not path.is_absolute():
            path = base / path
        if path.is_dir():
            found += [p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
        elif path.is_file():
            found.append(path)
        else:
            matches = [Path(p) for p in glob.glob(str(path))]
            if not matches:
                raise BtforgeInputError(str(item), "matches no image file", "give a folder, a glob such as "
                                        "'photos/*.jpg', or image files")
            found += [p for p in matches if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    unique = sorted(set(p for p in found if not any(w in p.stem.lower() for w in MASK_WORDS)
                        and not p.stem.lower().endswith(REPORT_SUFFIX)),
                    key=lambda p: _natural_key(p.name))
    if not unique:
        raise BtforgeInputError(str(pattern), "names no images", f"expected files ending in {', '.join(IMAGE_SUFFIXES)}")
    return unique


def _natural_key(name: str):
    import re
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def load_luminance(images: Sequence[Path]) -> np.ndarray:
    """``[N, H, W]`` float32 luminance of every image; all must have one size."""
    from btforge.plugins.stackio.images import read_image
    frames = []
    for path in images:
        pixels, _ = read_image(path)
        frame = luminance(pixels)
        if frames and frame.shape != frames[0].shape:
            raise BtforgeInputError(str(path), f"expected {frames[0].shape[1]} x {frames[0].shape[0]} pixels like "
                                    f"{images[0].name}, found {frame.shape[1]} x {frame.shape[0]}",
                                    "calibrate images of one capture (one camera position and size)")
        frames.append(frame)
    return np.stack(frames)


def calibrate(images: Sequence[Path], spheres: Sequence[Circle] | None = None, focal: float | str | None = None,
              principal: tuple[float, float] | None = None) -> Calibration:
    """Find the spheres (unless given), every image's highlight on each, and the light directions (orthographic,
    or a pinhole camera with ``focal`` pixels and the principal point ``principal``, default the image centre).

    ``focal="auto"`` estimates the focal length from how much each sphere's outline is stretched toward the
    principal point (:func:`sphere.estimate_focal`; the geometric mean over the spheres that show a stretch), and
    stays orthographic when none does.

    With several spheres each image's direction is the confidence-weighted mean of the spheres' directions; a
    sphere without a highlight in an image is left out of that image's mean.
    """
    if len(images) < 2:
        raise BtforgeInputError(", ".join(str(p) for p in images) or "images", f"expected at least 2 images, found "
                                f"{len(images)}", "calibrate the whole capture at once: the median image removes "
                                "static reflections")
    lum = load_luminance(images)
    shape = lum.shape[1:]
    if spheres is None:
        spheres = find_spheres(lum)
        if not spheres:
            raise BtforgeInputError(str(images[0].parent), "found no sphere outline in the images",
                                    "give the sphere with --sphere X,Y,R (centre column, row and radius in pixels)")
    background = np.median(lum, axis=0) if len(images) >= 5 else lum.min(axis=0)
    notes: tuple[str, ...] = ()
    if focal == "auto":
        centre = principal or ((shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0)
        estimates = [estimate_focal(c, np.median(lum, axis=0), centre) for c in spheres]
        notes = tuple(note for _, note in estimates)
        found = [f for f, _ in estimates if f is not None]
        focal = float(np.exp(np.mean(np.log(found)))) if found else None
        principal = principal if focal is not None else None
    per_sphere = tuple(tuple(find_highlight(frame, background, c) for frame in lum) for c in spheres)
    n = len(images)
    lights = np.full((n, 3), np.nan)
    uncertainty = np.full(n, np.nan)
    confidence = np.zeros(n)
    for i in range(n):
        dirs, weights, spreads = [], [], []
        for circle, highlights in zip(spheres, per_sphere):
            h = highlights[i]
            if not h.found:
                continue
            dirs.append(reflect(np.array([[h.x, h.y]]), circle, shape, focal, principal)[0])
            sigma = angular_uncertainty_deg(h, circle)
            weights.append(1.0 / sigma ** 2)
            spreads.append(sigma)
        if not dirs:
            continue
        d = np.average(np.array(dirs), axis=0, weights=weights)
        lights[i] = d / np.linalg.norm(d)
        sigma = 1.0 / math.sqrt(sum(weights))
        if len(dirs) > 1:  # the spheres' disagreement counts too
            disagreement = max(math.degrees(math.acos(min(1.0, float(v @ lights[i])))) for v in dirs)
            sigma = math.hypot(sigma, disagreement)
        uncertainty[i] = sigma
        contrast = min(h.contrast for h in (hs[i] for hs in per_sphere) if h.found)
        confidence[i] = math.exp(-sigma / 2.0) * (1.0 - math.exp(-contrast / (4 * 8.0)))
    return Calibration(tuple(images), tuple(spheres), per_sphere, lights, uncertainty, confidence, tuple(shape),
                       focal=focal, focal_notes=notes)


def _numbers(text: str, names: str, meaning: str, example: str, where: str) -> list[float]:
    """The comma-separated finite numbers ``names`` (e.g. 'X,Y,R') of an option or parameter ``where``."""
    parts = [p for p in str(text).replace(" ", "").split(",") if p]
    count = len(names.split(","))
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != count:
        raise BtforgeInputError(f"{where} {text}", f"expected {count} numbers {names} ({meaning})", f"e.g. {example}")
    if not all(math.isfinite(v) for v in values):
        raise BtforgeInputError(f"{where} {text}", f"expected finite numbers, found {parts}")
    return values


def parse_sphere(text: str, where: str = "--sphere") -> Circle:
    """``'X,Y,R'`` (centre column, centre row, radius, in pixels) -> a :class:`Circle`; ``where`` names the
    option or parameter in messages."""
    x, y, r = _numbers(text, "X,Y,R", "centre column, row, radius in pixels", "253.5,148,119.5", where)
    if r <= 0:
        raise BtforgeInputError(f"{where} {text}", f"expected a positive radius, found {r}")
    return Circle(x, y, r)


def parse_focal(text, where: str = "--focal") -> float | str:
    """A focal length in pixels (a positive number) or ``'auto'`` (estimate it from the spheres' outlines)."""
    if str(text).strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise BtforgeInputError(f"{where} {text}", "expected a positive focal length in pixels, or 'auto'",
                                "e.g. --focal 4200, or --focal auto to estimate it from the sphere's outline")
    return value


def parse_principal(text: str, where: str = "--principal") -> tuple[float, float]:
    """``'X,Y'`` (the principal point's column and row in pixels) -> ``(x, y)``; ``where`` names the option."""
    x, y = _numbers(text, "X,Y", "the principal point's column and row in pixels", "255.5,169.5; leave it out "
                    "for the image centre", where)
    return x, y


def _relative_name(image: Path, folder: Path) -> str:
    """The image's path relative to the light file's folder, or absolute when they share no folder but the root."""
    image, folder = Path(os.path.abspath(image)), Path(os.path.abspath(folder))
    common = Path(os.path.commonpath([image, folder]))
    if common == Path(common.anchor):
        return image.as_posix()
    return Path(os.path.relpath(image, folder)).as_posix()


def write_calibration(result: Calibration, light_file: Path, apply_to: Sequence[Path] | None = None) -> list[str]:
    """Write the light file for the images found (or, with ``apply_to``, the lights of those images given to a
    later capture's images in the same order).  Returns the names of the images left out."""
    from btforge.plugins.stackio.lightfile import write_light_file
    targets = list(apply_to) if apply_to is not None else list(result.images)
    if len(targets) != len(result.images):
        raise BtforgeInputError(", ".join(p.name for p in targets[:3]) + ("..." if len(targets) > 3 else ""),
                                f"expected one image per calibrated light ({len(result.images)}), found {len(targets)}",
                                "the later capture must repeat the lights of the sphere capture, in the same order")
    keep = np.flatnonzero(result.found)
    names = [_relative_name(targets[i], light_file.parent) for i in keep]
    if not len(keep):
        raise BtforgeInputError(str(light_file), "no light was found in any image, nothing to write",
                                "; ".join(result.problems()[:3]))
    write_light_file(light_file, names, result.lights[keep])
    return [targets[i].name for i in np.flatnonzero(~result.found)]


def report_picture(result: Calibration, path: Path, lum: np.ndarray | None = None) -> None:
    """Write a PNG of every sphere (the capture's maximum image, brightened) with each highlight marked and
    numbered by its image's position in the light file order, and the images without a light listed in red."""
    from PIL import Image, ImageDraw, ImageFont
    from btforge.atomic import atomic_write
    lum = load_luminance(result.images) if lum is None else lum
    summary = np.sqrt(np.clip(lum.max(axis=0), 0.0, 1.0))
    font = ImageFont.load_default()
    tiles = []
    for s, circle in enumerate(result.spheres):
        pad = 0.15 * circle.r
        r0, r1 = max(0, int(circle.y - circle.r - pad)), min(result.shape[0], int(circle.y + circle.r + pad) + 1)
        c0, c1 = max(0, int(circle.x - circle.r - pad)), min(result.shape[1], int(circle.x + circle.r + pad) + 1)
        zoom = max(1.0, 480.0 / max(r1 - r0, c1 - c0))
        crop = Image.fromarray((summary[r0:r1, c0:c1] * 255).astype(np.uint8)).convert("RGB")
        crop = crop.resize((int((c1 - c0) * zoom), int((r1 - r0) * zoom)), Image.BILINEAR)
        draw = ImageDraw.Draw(crop)

        def px(x, y):
            return ((x - c0 + 0.5) * zoom - 0.5, (y - r0 + 0.5) * zoom - 0.5)

        cx, cy = px(circle.x, circle.y)
        draw.ellipse([cx - circle.r * zoom, cy - circle.r * zoom, cx + circle.r * zoom, cy + circle.r * zoom],
                     outline=(0, 170, 255))
        for i, h in enumerate(result.highlights[s]):
            if not h.found:
                continue
            x, y = px(h.x, h.y)
            colour = (255, 60, 60) if not result.found[i] else (80, 255, 80) if result.confidence[i] >= 0.5 \
                else (255, 200, 0)
            draw.ellipse([x - 4, y - 4, x + 4, y + 4], outline=colour)
            draw.text((x + 5, y - 12), str(i + 1), fill=colour, font=font)
        draw.text((4, 4), f"sphere {s + 1}: centre ({circle.x:.1f}, {circle.y:.1f}), radius {circle.r:.1f} px",
                  fill=(0, 170, 255), font=font)
        tiles.append(crop)
    lines = [f"{len(result.images)} images, {int(result.found.sum())} lights found; numbers = image order; "
             "green: confidence >= 0.5, yellow: below, red: left out"] + result.problems()
    width = max(sum(t.width for t in tiles), 480)
    height = max(t.height for t in tiles) + 14 * len(lines) + 8
    sheet = Image.new("RGB", (width, height), (0, 0, 0))
    x = 0
    for t in tiles:
        sheet.paste(t, (x, 0))
        x += t.width
    draw = ImageDraw.Draw(sheet)
    y = max(t.height for t in tiles) + 4
    for k, line in enumerate(lines):
        draw.text((4, y + 14 * k), line[:160], fill=(255, 255, 255) if k == 0 else (255, 80, 80), font=font)
    with atomic_write(path) as handle:
        sheet.save(handle, format="PNG")


def summary_lines(result: Calibration) -> list[str]:
    """A table: image, direction, elevation/azimuth, uncertainty and confidence, or why it has no light."""
    rows = [f"{'#':>3}  {'image':24} {'x':>8} {'y':>8} {'z':>8} {'elev':>6} {'azim':>7} {'+-deg':>6} {'conf':>5}"]
    for i, path in enumerate(result.images):
        if not result.found[i]:
            problem = "left out on request" if path.name in result.excluded else \
                "no light: " + "; ".join(hs[i].problem for hs in result.highlights)
            rows.append(f"{i + 1:>3}  {path.name[:24]:24} {problem}")
            continue
        x, y, z = result.lights[i]
        elev, azim = math.degrees(math.asin(max(-1.0, min(1.0, z)))), math.degrees(math.atan2(y, x)) % 360
        rows.append(f"{i + 1:>3}  {path.name[:24]:24} {x:8.4f} {y:8.4f} {z:8.4f} {elev:6.1f} {azim:7.1f} "
                    f"{result.uncertainty_deg[i]:6.2f} {result.confidence[i]:5.2f}")
    return rows
