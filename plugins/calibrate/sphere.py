"""Finding mirror spheres in a capture and the highlight of every light on them.

The outline of a sphere is found in the per-pixel maximum and median images (a static reflection of the room or
the lamp's moving highlight makes the sphere stand out from the background in one or the other): strong edge
pixels vote along their gradient for circle centres at every radius (a Hough transform), the best-supported
circles are kept, and each is refined by a robust least-squares circle fit to the edge pixels near it, then by a
geometric circle fit to the outline located to a fraction of a pixel in the median image (where radial profiles
cross half-way between the ball and its background).  The same sub-pixel outline measures how much a wide lens
stretches it toward the principal point, from which the focal length can be estimated.

A highlight is searched for in each image after subtracting the per-pixel median of the capture (so static
reflections on the ball drop out).  The brightness threshold adapts, from the peak down, until a small share of
the sphere is lit; the weighted centroid of what lies above it is refined in a shrinking window, so flare and
bloom around the lamp do not pull it.  Highlights that are too dim or too large are rejected with a reason.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from btforge.lazy import lazy_module

ndimage = lazy_module("scipy.ndimage")

DETECT_MAX_SIDE = 800           # sphere search runs on images scaled down to this longer side
EDGE_SHARE = 0.06               # the strongest share of gradient pixels that vote for circles
MIN_RADIUS_SHARE = 0.04         # smallest sphere: this share of the image's shorter side
SECOND_SPHERE_SUPPORT = 0.6     # another sphere must have this share of the best one's outline support
DISC_SHARE = 0.97               # highlights are searched inside this share of the radius (the rim is unreliable)
LIT_SHARE = 0.002               # the threshold is lowered until this share of the disc is lit ...
LOWEST_THRESHOLD = 0.35         # ... but never below this share of the peak
MAX_HIGHLIGHT_SHARE = 0.03      # a lit area above this share of the disc at half the peak is not a point light ...
BLUR_PIXELS = 25                # ... unless it is no larger than the lens blur of a point (on small spheres)
MIN_CONTRAST = 8.0              # peak over the noise (median absolute deviation) of the disc
MIN_PEAK = 0.04                 # peak above the median image, in units of the image's full range
VALIDATION_IMAGES = 12          # a candidate sphere must show highlights in most of this many images
LIMB_BAND = 0.05                # the sub-pixel outline is searched within this share of the radius of the circle ...
LIMB_SECTOR_PIXELS = 6.0        # ... in sectors of about this many pixels of arc ...
LIMB_CONTRAST = 4.0             # ... whose step between inside and outside is this many times the noise
STRETCH_SIGMAS = 3.0            # a focal length is estimated from an outline stretched this many standard errors ...
STRETCH_FLOOR = 0.1             # ... and at least this many pixels toward the principal point


@dataclasses.dataclass(frozen=True)
class Circle:
    """A sphere's outline in pixels: centre column ``x``, centre row ``y``, radius ``r``; ``support`` in [0, 1]
    is the share of the outline backed by edge pixels (1.0 for a circle the user gave)."""

    x: float
    y: float
    r: float
    support: float = 1.0


@dataclasses.dataclass(frozen=True)
class Highlight:
    """The highlight of one image on one sphere: pixel position (column ``x``, row ``y``), its contrast over the
    disc's noise, its lit area in pixels, a localisation spread in pixels, or ``problem`` when none was found."""

    x: float = math.nan
    y: float = math.nan
    contrast: float = 0.0
    area: int = 0
    spread_px: float = math.nan
    problem: str = ""

    @property
    def found(self) -> bool:
        return not self.problem


# ----------------------------------------------------------------------------------------------- images


def luminance(image: np.ndarray) -> np.ndarray:
    """``[H, W]`` float32 in [0, 1]: the largest channel (a highlight saturates whichever channel first)."""
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(image.dtype, 1.0)
    values = image.astype(np.float32) / np.float32(scale)
    return values.max(axis=2) if values.ndim == 3 else values


def _downscale(image: np.ndarray, factor: int) -> np.ndarray:
    if factor == 1:
        return image
    h, w = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    return image[:h, :w].reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))


# ----------------------------------------------------------------------------------------------- spheres


def _edges(image: np.ndarray, sigma: float, share: float):
    """Rows, columns, unit gradient and magnitude of the strongest ``share`` of gradient pixels."""
    smooth = ndimage.gaussian_filter(np.sqrt(np.maximum(image, 0.0)), sigma)  # sqrt: dark rims count too
    gy, gx = ndimage.sobel(smooth, axis=0), ndimage.sobel(smooth, axis=1)
    mag = np.hypot(gx, gy)
    floor = max(float(np.quantile(mag, 1.0 - share)), 1e-6)
    rows, cols = np.nonzero(mag > floor)
    m = mag[rows, cols]
    return rows, cols, gx[rows, cols] / m, gy[rows, cols] / m, m


def _hough(shape, edges, radii) -> tuple[np.ndarray, np.ndarray]:
    """Votes per radius and centre, normalised by the circumference: ``[R, H, W]`` float32 and the radii."""
    h, w = shape
    rows, cols, ux, uy, _ = edges
    out = np.zeros((len(radii), h, w), np.float32)
    for k, r in enumerate(radii):
        for sign in (1.0, -1.0):  # the sphere may be brighter or darker than what surrounds it
            cy = np.rint(rows - sign * r * uy).astype(np.int64)
            cx = np.rint(cols - sign * r * ux).astype(np.int64)
            ok = (cy >= 0) & (cy < h) & (cx >= 0) & (cx < w)
            out[k] += np.bincount(cy[ok] * w + cx[ok], minlength=h * w).reshape(h, w)
        out[k] = ndimage.uniform_filter(out[k], 3) * 9 / (2 * math.pi * r)
    return out, np.asarray(radii, np.float64)


def _refine(circle: Circle, edges, scale: float, iterations: int = 12) -> Circle:
    """Robust algebraic circle fit to the edge pixels near ``circle`` whose gradient points along the radius."""
    rows, cols, ux, uy, mag = edges
    x, y, r = circle.x, circle.y, circle.r
    band = max(3.0 * scale, 0.06 * r)
    for _ in range(iterations):
        dx, dy = cols - x, rows - y
        dist = np.hypot(dx, dy) + 1e-9
        radial = (dx * ux + dy * uy) / dist
        close = np.abs(dist - r) < band
        # Keep the outline's dominant polarity: the inner edge of a bright reflection on the rim points inward.
        polarity = 1.0 if (mag[close] * radial[close]).sum() >= 0 else -1.0
        near = close & (polarity * radial > 0.85)
        if near.sum() < 12:
            break
        px, py, weight = cols[near].astype(np.float64), rows[near].astype(np.float64), mag[near].astype(np.float64)
        residual = np.abs(dist[near] - r)
        weight = weight * np.clip(1.0 - (residual / band) ** 2, 0.0, None) ** 2  # Tukey's biweight
        a = np.stack([px, py, np.ones_like(px)], axis=1) * np.sqrt(weight)[:, None]
        b = (px * px + py * py) * np.sqrt(weight)
        (c0, c1, c2), *_ = np.linalg.lstsq(a, b, rcond=None)
        step = math.hypot(c0 / 2 - x, c1 / 2 - y)
        x, y = c0 / 2, c1 / 2
        new_r = math.sqrt(max(c2 + x * x + y * y, 1e-9))
        step += abs(new_r - r)
        r = new_r
        if step < 0.25 * band:  # narrow the band once the circle has settled, not before
            band = max(1.5 * scale, band * 0.7)
    return Circle(float(x), float(y), float(r), circle.support)


def _limb_points(circle: Circle, image: np.ndarray, noise: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel points of the sphere's outline near ``circle`` in one image: columns, rows and the step from
    inside to outside ``[K]``.

    In each sector of the outline the radial profiles are averaged (the outline of a chrome ball may stand out
    from a dark background by a level or two, so one ray is too noisy); a sector gives a point where its profile
    crosses half-way between its inside and outside levels, the edge's position whatever its polarity and blur.
    Sectors whose step is not clear of the noise give none.
    """
    half_width = max(3.0, LIMB_BAND * circle.r)
    offsets = np.arange(-half_width, half_width + 1e-9, 0.25)
    sectors = max(36, min(360, int(2 * math.pi * circle.r / LIMB_SECTOR_PIXELS)))
    rays = max(1, int(round(2 * math.pi * circle.r / sectors)))  # about one ray per pixel of arc
    angles = (np.arange(sectors * rays) + 0.5) * (2 * math.pi / (sectors * rays))
    radius = circle.r + offsets
    cols = circle.x + np.cos(angles)[:, None] * radius[None]
    rows = circle.y - np.sin(angles)[:, None] * radius[None]
    values = ndimage.map_coordinates(image, [rows.ravel(), cols.ravel()], order=1, mode="nearest")
    profiles = values.reshape(sectors, rays, len(offsets)).mean(axis=1)
    quarter = len(offsets) // 4
    inside = np.median(profiles[:, :quarter], axis=1)
    outside = np.median(profiles[:, -quarter:], axis=1)
    crossing = _half_level_crossing(profiles, inside, outside, offsets)
    step = outside - inside
    keep = (np.abs(step) > LIMB_CONTRAST * noise / math.sqrt(rays)) & np.isfinite(crossing)
    centre_angles = angles.reshape(sectors, rays).mean(axis=1)[keep]
    r = circle.r + crossing[keep]
    return circle.x + r * np.cos(centre_angles), circle.y - r * np.sin(centre_angles), step[keep]


def _half_level_crossing(profiles, inside, outside, offsets) -> np.ndarray:
    """Per profile ``[S, P]``, the offset where it crosses the half level between ``inside`` and ``outside`` (linear
    between samples; the crossing nearest the middle of the profile), or NaN when it never does."""
    signed = (profiles - ((inside + outside) / 2)[:, None]) * np.sign(outside - inside)[:, None]
    rising = (signed[:, :-1] < 0) & (signed[:, 1:] >= 0)
    middle = len(offsets) // 2
    distance = np.where(rising, np.abs(np.arange(len(offsets) - 1) - middle + 0.5)[None], np.inf)
    k = np.argmin(distance, axis=1)
    found = np.isfinite(distance[np.arange(len(k)), k])
    below, above = signed[np.arange(len(k)), k], signed[np.arange(len(k)), k + 1]
    fraction = -below / np.where(above - below > 0, above - below, 1.0)
    at = offsets[k] + fraction * (offsets[1] - offsets[0])
    return np.where(found, at, np.nan)


def _fit_circle(cols: np.ndarray, rows: np.ndarray, start: Circle, iterations: int = 20) -> Circle | None:
    """Geometric least-squares circle through points, with Tukey weights on their distances from it (a reflection
    of the room near the rim, or the stand the ball sits on, leaves outliers); None with too few points."""
    if len(cols) < 12:
        return None
    x, y, r = start.x, start.y, start.r
    weight = np.ones_like(cols)
    for _ in range(iterations):
        dx, dy = cols - x, rows - y
        dist = np.hypot(dx, dy) + 1e-12
        residual = dist - r
        scale = max(1.4826 * float(np.median(np.abs(residual))), 0.05)
        weight = np.clip(1.0 - (residual / (4.685 * scale)) ** 2, 0.0, None) ** 2
        if weight.sum() < 12:
            return None
        jacobian = np.stack([-dx / dist, -dy / dist, -np.ones_like(dist)], axis=1)  # d(residual)/d(x, y, r)
        sw = np.sqrt(weight)
        step, *_ = np.linalg.lstsq(jacobian * sw[:, None], -residual * sw, rcond=None)
        x, y, r = x + step[0], y + step[1], r + step[2]
        if np.abs(step).max() < 1e-4:
            break
    return Circle(float(x), float(y), float(r), start.support)


def _outline_points(circle: Circle, images) -> tuple[np.ndarray, np.ndarray]:
    """The sub-pixel outline points of every image (:func:`_limb_points`) whose step has the polarity of most of
    them (counted, not summed: a bright reflection just inside the rim has a strong edge of its own)."""
    points = [_limb_points(circle, image, _noise_level(image)) for image in images]
    cols, rows, step = (np.concatenate(parts) for parts in zip(*points))
    same = np.sign(step) == (1.0 if (step > 0).sum() >= (step < 0).sum() else -1.0)
    return cols[same], rows[same]


def refine_limb(circle: Circle, images) -> Circle:
    """The circle through the sub-pixel outline of the sphere in every image of ``images`` (see
    :func:`_limb_points`; each photograph shows the outline where its light makes the background differ from the
    ball, so their points are pooled), or ``circle`` unchanged when too little of the outline is clear or the fit
    moves implausibly far."""
    fitted = _fit_circle(*_outline_points(circle, images), circle)
    if fitted is None or math.hypot(fitted.x - circle.x, fitted.y - circle.y) + abs(fitted.r - circle.r) \
            > max(2.0, LIMB_BAND * circle.r):
        return circle
    return fitted


def _noise_level(image: np.ndarray) -> float:
    """Per-pixel noise of an image in [0, 1]: the median absolute deviation of its differences along rows, and at
    least the rounding noise of 8 bits (0.29 of a level: most captures are 8-bit, and a flat dark background has
    no deviation at all)."""
    difference = np.diff(image[:, ::2], axis=1)
    return max(1.4826 * float(np.median(np.abs(difference))) / math.sqrt(2), 0.29 / 255.0)


def _coverage(circle: Circle, edges, bins: int = 90) -> float:
    """Share of the outline's angular bins holding an edge pixel on the circle whose gradient is radial."""
    rows, cols, ux, uy, _ = edges
    dx, dy = cols - circle.x, rows - circle.y
    dist = np.hypot(dx, dy) + 1e-9
    on = (np.abs(dist - circle.r) < max(2.0, 0.02 * circle.r)) & (np.abs(dx * ux + dy * uy) / dist > 0.85)
    angles = np.arctan2(dy[on], dx[on])
    hit = np.unique(((angles + math.pi) / (2 * math.pi) * bins).astype(int) % bins)
    return len(hit) / bins


def _candidates(score: np.ndarray, radii: np.ndarray, factor: int, count: int) -> list[Circle]:
    """The ``count`` best circles of the vote volume ``[R, H, W]``, each the best in its neighbourhood of centre
    and radius (the volume is first reduced to the best radius per centre)."""
    best_k = np.argmax(score, axis=0)
    best = np.take_along_axis(score, best_k[None], axis=0)[0].reshape(-1)
    top = np.argpartition(best, -min(best.size, 4000))[-4000:] if best.size > 4000 else np.arange(best.size)
    out: list[Circle] = []
    width = score.shape[2]
    for index in top[np.argsort(best[top])[::-1]]:
        cy, cx = divmod(int(index), width)
        c = Circle((cx + 0.5) * factor - 0.5, (cy + 0.5) * factor - 0.5, float(radii[best_k.flat[index]] * factor),
                   float(best[index]))
        if any(math.hypot(c.x - o.x, c.y - o.y) < 0.3 * max(c.r, o.r) and abs(c.r - o.r) < 0.3 * max(c.r, o.r)
               for o in out):
            continue
        out.append(c)
        if len(out) == count:
            break
    return out


def find_spheres(lum: np.ndarray, max_spheres: int = 4, background: np.ndarray | None = None) -> list[Circle]:
    """Mirror spheres in a capture ``[N, H, W]`` (luminance), best-supported first; empty when none is found.

    Circles voted for in the maximum and median images are refined and kept when their outline is well covered by
    edges and most images show a highlight on them; of two overlapping circles the larger wins unless its outline
    is much less complete (a highlight's blob inside a sphere is a circle too).  Circles are in full-resolution
    pixel coordinates (pixel centres at integers).
    """
    n, height, width = lum.shape
    factor = max(1, int(math.ceil(max(height, width) / DETECT_MAX_SIDE)))
    summaries = [lum.max(axis=0), np.median(lum, axis=0)]
    background = summaries[1] if background is None else background
    radii = np.arange(max(6, int(MIN_RADIUS_SHARE * min(height, width) / factor)),
                      int(0.5 * min(height, width) / factor) + 1)
    full_edges = [_edges(s, 1.0, EDGE_SHARE) for s in summaries]
    merged = tuple(np.concatenate(parts) for parts in zip(*full_edges))
    candidates = []
    for image in summaries:
        small = _downscale(image, factor)
        votes, _ = _hough(small.shape, _edges(small, 1.5, EDGE_SHARE), radii)
        low = 0
        while low < len(radii):  # the best few per band of radii: small blobs must not crowd out the spheres
            high = int(np.searchsorted(radii, radii[low] * 1.5))
            candidates += _candidates(votes[low:high], radii[low:high], factor, 4)
            low = high
    kept: list[tuple[Circle, float]] = []
    for c in candidates:
        c = _refine(c, merged, float(factor))
        if any(abs(c.x - o.x) + abs(c.y - o.y) + abs(c.r - o.r) < 1.0 for o, _ in kept):
            continue  # two candidates refined to one circle
        if not (c.r > 3 and -0.1 * c.r < c.x - c.r and c.x + c.r < width + 0.1 * c.r
                and -0.1 * c.r < c.y - c.r and c.y + c.r < height + 0.1 * c.r):
            continue  # a sphere mostly outside the frame gives no usable highlights
        coverage = _coverage(c, merged)
        if coverage < 0.35:
            continue
        sample = lum[np.linspace(0, n - 1, min(n, VALIDATION_IMAGES)).round().astype(int)]
        found = sum(find_highlight(frame, background, c).found for frame in sample)
        if found < max(2, 0.5 * len(sample)):
            continue
        # The outline to sub-pixel precision in the median image: the ball as it looks in most shots (the maximum
        # image also holds every shot's reflections inside the rim, which pull the outline inward).
        kept.append((dataclasses.replace(refine_limb(c, summaries[1:]), support=coverage), coverage))
    # Best outline first; a larger circle nearly as well covered wins over one inside it (a highlight's blob).
    kept.sort(key=lambda item: -item[1])
    chosen: list[Circle] = []
    for c, coverage in kept:
        clash = [o for o in chosen if math.hypot(c.x - o.x, c.y - o.y) < c.r + o.r]
        if not clash:
            chosen.append(c)
        elif all(o.r < 0.8 * c.r and coverage >= 0.85 * o.support for o in clash):
            chosen = [o for o in chosen if o not in clash] + [c]
    chosen.sort(key=lambda c: -c.support)
    best = chosen[0].support if chosen else 0.0
    return [c for c in chosen if c.support >= SECOND_SPHERE_SUPPORT * best][:max_spheres]


# ----------------------------------------------------------------------------------------------- highlights


def disc_mask(shape, circle: Circle, share: float = DISC_SHARE):
    """Bounding slices of the circle and the mask of the disc of ``share`` x its radius inside them."""
    h, w = shape
    r0, r1 = max(0, int(circle.y - circle.r) - 1), min(h, int(circle.y + circle.r) + 2)
    c0, c1 = max(0, int(circle.x - circle.r) - 1), min(w, int(circle.x + circle.r) + 2)
    yy, xx = np.mgrid[r0:r1, c0:c1]
    mask = (xx - circle.x) ** 2 + (yy - circle.y) ** 2 <= (share * circle.r) ** 2
    return (slice(r0, r1), slice(c0, c1)), mask


def _weighted_centroid(values: np.ndarray, threshold: float, y: float, x: float, half: float):
    r0, r1 = max(0, int(math.floor(y - half))), min(values.shape[0], int(math.ceil(y + half)) + 1)
    c0, c1 = max(0, int(math.floor(x - half))), min(values.shape[1], int(math.ceil(x + half)) + 1)
    window = np.clip(values[r0:r1, c0:c1] - threshold, 0.0, None)
    total = float(window.sum())
    if total <= 0:
        return y, x
    yy, xx = np.mgrid[r0:r1, c0:c1]
    return float((window * yy).sum() / total), float((window * xx).sum() / total)


def find_highlight(image: np.ndarray, background: np.ndarray, circle: Circle) -> Highlight:
    """The highlight of a point light on one sphere in one luminance image (see the module docs)."""
    box, disc = disc_mask(image.shape, circle)
    residual = np.where(disc, image[box] - background[box], 0.0).astype(np.float32)
    smooth = ndimage.gaussian_filter(residual, 1.0)
    inside = smooth[disc]
    spread = inside[::7] if inside.size > 7000 else inside  # a sample is enough for the noise level
    noise = 1.4826 * float(np.median(np.abs(spread - np.median(spread)))) + 1e-4
    peak = float(inside.max())
    contrast = peak / noise
    if peak < MIN_PEAK or contrast < MIN_CONTRAST:
        return Highlight(contrast=contrast, problem=f"too dim (peak {peak:.3f} over the median image, "
                                                    f"{contrast:.1f} x the noise)")
    py, px = np.unravel_index(int(np.argmax(np.where(disc, smooth, -np.inf))), smooth.shape)
    disc_area = int(disc.sum())
    # Components are labelled in a window around the peak wider than any acceptable highlight: one that
    # reaches the window's border at half the peak is too large whatever its full extent.
    largest = max(MAX_HIGHLIGHT_SHARE * disc_area, BLUR_PIXELS)
    reach = int(2.0 * math.sqrt(largest / math.pi)) + 3
    w0, w1 = max(0, py - reach), max(0, px - reach)
    window = smooth[w0:py + reach + 1, w1:px + reach + 1]
    wy, wx = py - w0, px - w1
    half_max = _component(window >= 0.5 * peak, wy, wx)
    touches = half_max[0].any() or half_max[-1].any() or half_max[:, 0].any() or half_max[:, -1].any()
    if touches or half_max.sum() > largest:
        share = 100 * half_max.sum() / disc_area
        return Highlight(contrast=contrast, area=int(half_max.sum()),
                         problem=f"too large ({'over ' if touches else ''}{share:.1f}% of the sphere above half the "
                                 f"peak: a matte or a second light?)")
    threshold = 0.9 * peak
    lit = _component(window >= threshold, wy, wx)
    while lit.sum() < max(4, LIT_SHARE * disc_area) and threshold > LOWEST_THRESHOLD * peak:
        threshold *= 0.9
        lit = _component(window >= threshold, wy, wx)
    ys, xs = np.nonzero(lit)
    first = (float(ys.mean()) + w0, float(xs.mean()) + w1)
    y, x = first
    half = 2.0 * math.sqrt(lit.sum() / math.pi) + 2.0
    while True:
        y, x = _weighted_centroid(np.where(disc, residual, 0.0), threshold, y, x, half)
        if half <= 2.0:
            break
        half = max(2.0, half * 0.75)
    spread = math.hypot(y - first[0], x - first[1])
    return Highlight(x=x + box[1].start, y=y + box[0].start, contrast=contrast, area=int(lit.sum()), spread_px=spread)


def _component(mask: np.ndarray, row: int, col: int) -> np.ndarray:
    labels, _ = ndimage.label(mask)
    label = labels[row, col]
    return labels == label if label else np.zeros_like(mask)


# ----------------------------------------------------------------------------------------------- directions


def reflect(highlight_xy: np.ndarray, circle: Circle, shape, focal: float | None = None,
            principal: tuple[float, float] | None = None) -> np.ndarray:
    """Light directions ``[N, 3]`` (x right, y up, z toward the camera) for highlights ``[N, 2]`` (column, row).

    Orthographic when ``focal`` is None (the view is (0, 0, 1) everywhere); otherwise a pinhole camera with that
    focal length in pixels and the principal point ``principal`` (column, row; default the image centre: a
    cropped photograph has it elsewhere).
    """
    xy = np.asarray(highlight_xy, np.float64)
    if focal is None:
        nx = (xy[:, 0] - circle.x) / circle.r
        ny = -(xy[:, 1] - circle.y) / circle.r
        rho2 = np.minimum(nx * nx + ny * ny, 1.0)
        normal = np.stack([nx, ny, np.sqrt(1.0 - rho2)], axis=1)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        view = np.array([0.0, 0.0, 1.0])
    else:
        px, py = principal if principal is not None else ((shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0)

        def ray(u, v):
            d = np.stack([(u - px) / focal, -(v - py) / focal, -np.ones_like(u)], axis=-1)
            return d / np.linalg.norm(d, axis=-1, keepdims=True)

        offset = np.array([circle.x - px, circle.y - py])
        distance = float(np.linalg.norm(offset))
        radial = offset / distance if distance > 1e-9 else np.array([1.0, 0.0])
        tilt, alpha = _cone_of_outline(distance, circle.r, focal)
        axis = np.array([math.sin(tilt) * radial[0], -math.sin(tilt) * radial[1], -math.cos(tilt)])
        centre = axis / math.sin(alpha)                      # unit sphere radius, distance 1 / sin(alpha)
        d = ray(xy[:, 0], xy[:, 1])
        b = d @ centre
        disc = np.maximum(b * b - (centre @ centre - 1.0), 0.0)
        point = (b - np.sqrt(disc))[:, None] * d
        normal = point - centre
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        view = -d
    cos = np.sum(normal * view, axis=-1, keepdims=True)
    light = 2.0 * cos * normal - view
    return light / np.linalg.norm(light, axis=1, keepdims=True)


def _cone_of_outline(distance: float, radius: float, focal: float) -> tuple[float, float]:
    """The tilt of a sphere's axis from the optical axis and its angular radius (radians), from the circle fitted
    to its outline: ``distance`` of the circle's centre from the principal point and its ``radius`` (pixels).

    Under perspective the outline is the image of the cone tangent to the sphere, an ellipse stretched along the
    line through the principal point: its centre lies farther out than the axis, with semi-axes
    ``a = f (tan(t + s) - tan(t - s)) / 2`` along that line and ``b = f sin s / sqrt(cos^2 t - sin^2 s)`` across
    it.  A circle fitted to the whole outline has about its centre and the mean radius ``(a + b) / 2`` (taking
    the circle's radius for ``a`` instead: 0.87 degrees mean instead of 0.55 on a render tilted 15 degrees).
    """
    from scipy.optimize import fsolve

    def mismatch(p):
        tilt, alpha = p
        near, far = math.tan(tilt - alpha), math.tan(tilt + alpha)
        across = math.sin(alpha) / math.sqrt(max(math.cos(tilt) ** 2 - math.sin(alpha) ** 2, 1e-12))
        return [focal * (near + far) / 2 - distance, focal * ((far - near) / 2 + across) / 2 - radius]

    start = [math.atan2(distance, focal), math.atan2(radius, math.hypot(distance, focal))]
    (tilt, alpha), _, ok, _ = fsolve(mismatch, start, full_output=True, xtol=1e-12)
    if ok != 1 or not (0.0 < alpha < math.pi / 2 and abs(tilt) + alpha < math.pi / 2):
        return start[0], start[1]  # an outline perspective cannot explain: keep the first guess
    return float(tilt), float(alpha)


def outline_stretch(circle: Circle, focal: float, principal) -> float:
    """How much longer (pixels) the outline's axis toward the principal point is than the one across it, for a
    sphere seen as ``circle`` by a pinhole camera of ``focal`` pixels (see :func:`_cone_of_outline`)."""
    distance = math.hypot(circle.x - principal[0], circle.y - principal[1])
    tilt, alpha = _cone_of_outline(distance, circle.r, focal)
    along = focal * (math.tan(tilt + alpha) - math.tan(tilt - alpha)) / 2
    across = focal * math.sin(alpha) / math.sqrt(max(math.cos(tilt) ** 2 - math.sin(alpha) ** 2, 1e-12))
    return along - across


def measure_stretch(circle: Circle, image: np.ndarray) -> tuple[float, float, float]:
    """The outline's stretch in ``image``: twice the amplitude (pixels) of the second harmonic of its sub-pixel
    points' distances from the centre (an ellipse of axes a, b has amplitude (a - b) / 2), its standard error, and
    the long axis's direction (degrees, counter-clockwise from the image's x axis, in [-90, 90)); Tukey-weighted.
    NaN when too little of the outline is clear."""
    cols, rows = _outline_points(circle, [image])
    fitted = _fit_circle(cols, rows, circle)
    if fitted is None:
        return math.nan, math.nan, math.nan
    angle = np.arctan2(-(rows - fitted.y), cols - fitted.x)
    design = np.stack([np.ones_like(angle), np.cos(angle), np.sin(angle), np.cos(2 * angle), np.sin(2 * angle)], 1)
    distance = np.hypot(cols - fitted.x, rows - fitted.y)
    weight = np.ones_like(distance)
    for _ in range(10):
        coef, *_ = np.linalg.lstsq(design * weight[:, None], distance * weight, rcond=None)
        residual = distance - design @ coef
        scale = 1.4826 * float(np.median(np.abs(residual))) + 1e-3
        weight = np.clip(1.0 - (residual / (4.685 * scale)) ** 2, 0.0, None)
    normal = (design * weight[:, None] ** 2).T @ design
    se = scale * float(np.sqrt(np.diag(np.linalg.pinv(normal))[3:].mean()))
    direction = (0.5 * math.degrees(math.atan2(coef[4], coef[3])) + 90.0) % 180.0 - 90.0
    return 2.0 * float(math.hypot(coef[3], coef[4])), 2.0 * se, float(direction)


def _axis_toward(circle: Circle, principal) -> float:
    """The direction (degrees in [-90, 90), counter-clockwise from the x axis) of the line from the circle's
    centre to the principal point."""
    return (math.degrees(math.atan2(circle.y - principal[1], principal[0] - circle.x)) + 90.0) % 180.0 - 90.0


def estimate_focal(circle: Circle, image: np.ndarray, principal) -> tuple[float | None, str]:
    """The focal length (pixels) that stretches the sphere's outline in ``image`` as much as measured along the
    line to the ``principal`` point, or None (orthographic) when the stretch there is not clear of its
    uncertainty; with the reason in words."""
    stretch, se, direction = measure_stretch(circle, image)
    if not math.isfinite(stretch):
        return None, "too little of the outline is clear"
    # The measured second harmonic's component along the line to the principal point (perspective stretches
    # the outline only along it).
    along = stretch * math.cos(2 * math.radians(direction - _axis_toward(circle, principal)))
    if along < max(STRETCH_SIGMAS * se, STRETCH_FLOOR):
        return None, f"outline stretch {along:+.2f} +- {se:.2f} px toward the principal point: orthographic"
    # The stretch grows as the focal length shrinks, until the sphere no longer fits in front of the camera (where
    # the tangent cone has no solution): step down from a telephoto until it is reached, then bisect.
    high, previous = 1e4 * circle.r, 0.0
    while True:
        low = high / 1.25
        stretch_low = outline_stretch(circle, low, principal)
        if stretch_low >= along:
            break
        if stretch_low <= previous or low < 0.2 * circle.r:
            return None, f"outline stretch {along:.2f} px is more than any pinhole camera gives: orthographic"
        high, previous = low, stretch_low
    for _ in range(40):
        middle = math.sqrt(low * high)
        low, high = (middle, high) if outline_stretch(circle, middle, principal) > along else (low, middle)
    return math.sqrt(low * high), f"outline stretch {along:.2f} +- {se:.2f} px toward the principal point"


def angular_uncertainty_deg(highlight: Highlight, circle: Circle) -> float:
    """How far (degrees) the direction moves for the highlight's localisation spread (at least half a pixel).

    The light's angle from the view is ``2 asin(rho)`` at ``rho`` radii from the centre, so a pixel's error costs
    ``2 / (r sqrt(1 - rho^2))`` radians: highlights near the rim are the least certain.
    """
    rho = min(math.hypot(highlight.x - circle.x, highlight.y - circle.y) / circle.r, 0.999)
    pixels = max(0.5, highlight.spread_px)
    return math.degrees(2.0 * pixels / (circle.r * math.sqrt(1.0 - rho * rho)))
