"""Testing helpers of the Liu family: the geometric-consistency measurement and the fixture it runs on.

Do a synthesized BTF's dark regions fall where the template's shadows are?  The measurement behind the
"IoU >= 0.7 over at least 10 lights" figure, shared by the tests and by ``btforge bench liu`` so that both
measure the same thing.  A quilted height field is synthesized under a ring of
target lights that lie between the references' azimuths (so every reference is rotated by eq. 7); each image's
dark pixels are compared with its template's shadow mask.  The baseline quilts each light's nearest reference on
its own, as a per-light 2D synthesis would.
"""
from __future__ import annotations

import dataclasses

import numpy as np

DARK_FRACTION = 0.02      # a synthesized pixel is dark below this fraction of its image's median brightness
LOW_TILTS = (70, 75)      # the consistency test's lights: low, where cast shadows are substantial
TARGET_AZIMUTHS = (30, 90, 150, 210, 270, 330)
REFERENCE_AZIMUTHS = (0, 72, 144, 216, 288)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (0 when both are empty)."""
    return float((a & b).sum() / max((a | b).sum(), 1))


def dark_mask(image: np.ndarray) -> np.ndarray:
    """Pixels of ``image [H, W, C]`` below ``DARK_FRACTION`` of its median brightness: where a shadow (black in
    the references) was copied."""
    lum = image.mean(-1)
    return lum < DARK_FRACTION * np.median(lum)


@dataclasses.dataclass
class Consistency:
    lights: np.ndarray          # [L, 3] the target lights
    liu: np.ndarray             # [L] shadow IoU of liu.synthesize per light
    per_light_2d: np.ndarray    # [L] shadow IoU of quilting each light's nearest reference on its own
    shadow_fraction: np.ndarray  # [L] fraction of the template in shadow


#: Quilting's copy budget for the scenes these measures quilt: its default before version 20, so the scenes (a 96 x 96
#: field grown to 112 x 112, where the automatic budget would now be 0.5) stay the ones the figures were measured on.
SCENE_BUDGET = 1.5


def quilted_field(exemplar, size: int):
    """The height field ``exemplar`` quilted to ``size^2`` (wrapping, seed 4): the scene the shadows are measured on."""
    from btforge import stage
    coords = stage("synth.quilt")(exemplar=exemplar, size=[size, size], block=32, wrap=True, seed=4,
                                  budget=SCENE_BUDGET)["coords"]
    return stage("synth.materialize")(coords=coords, source=exemplar)["output"]


def shadow_fixture(size: int = 112, tilts=LOW_TILTS, seed: int = 1):
    """``(references, field)``: the built-in material rendered under ``tilts`` at the 5 reference azimuths, and
    its height field quilted to ``size^2``."""
    from btforge import SampleStack
    from btforge.plugins.demo.procedural import make_material, render_lights
    from btforge.plugins.height.field import HeightField

    from .settings import direction

    m = make_material(96, 96, bumps=20, bump_height=5.0, seed=seed)
    dirs = np.array([direction(t, a) for t in tilts for a in REFERENCE_AZIMUTHS], np.float32)
    refs = SampleStack(render_lights(m, dirs)[None], dirs, [[0.0, 0.0, 1.0]])
    exemplar = HeightField.from_height(m.height, m.albedo, wrap=True)
    return refs, quilted_field(exemplar, size)


def per_light_iou(refs, light: np.ndarray, shadow: np.ndarray, size: int, seed: int) -> float:
    """Shadow IoU of quilting the reference nearest ``light`` on its own (the per-light 2D baseline)."""
    from btforge import SampleStack, stage
    nearest = int(np.argmax(refs.lights @ light))
    one = SampleStack(refs.samples[:, nearest:nearest + 1], refs.lights[nearest:nearest + 1], refs.views)
    coords = stage("synth.quilt")(exemplar=one, size=[size, size], block=24, seed=seed, budget=SCENE_BUDGET)["coords"]
    flat = stage("synth.materialize")(coords=coords, source=one)["output"]
    return iou(dark_mask(flat.samples[0, 0]), shadow)


def measure(size: int = 112, tilts=LOW_TILTS, baseline: bool = True, seed: int = 1) -> Consistency:
    """Shadow IoU over ``len(tilts) x 6`` target lights on a quilted ``size^2`` height field (see module);
    references: the built-in material under the same tilts at 5 other azimuths."""
    from btforge import stage
    refs, field = shadow_fixture(size, tilts, seed)
    grid = {"view_tilts": [0], "view_azimuths": [0], "light_tilts": list(tilts),
            "light_azimuths": list(TARGET_AZIMUTHS)}
    out = stage("liu.synthesize")(height=field, references=refs, grid=grid, nearest=1)
    stack, templates = out["stack"], out["templates"]
    ours, independent, fraction = [], [], []
    for l in range(stack.n_light):
        shadow = templates.samples[0, l, ..., 0] <= 0
        fraction.append(shadow.mean())
        ours.append(iou(dark_mask(stack.samples[0, l]), shadow))
        if baseline:
            independent.append(per_light_iou(refs, stack.lights[l], shadow, size, l))
    return Consistency(stack.lights, np.array(ours), np.array(independent), np.array(fraction))


def block_seam_visibility(image: np.ndarray, source: np.ndarray, reference: np.ndarray, valid: np.ndarray,
                          band: int = 0) -> float:
    """Seam visibility of a block copy: the radiance jumps (colour norm) across block boundaries of ``image [H, W,
    C]`` (adjacent pixels whose ``source [H, W, 2]`` pixels are not adjacent in the reference), over the jumps
    between adjacent ``valid`` pixels of ``reference [h, w, C]`` (1: block boundaries look like the reference's
    own pixel-to-pixel changes).

    ``band``: texels on each side of a boundary that feathering blended.  A feathered boundary shows the mean of
    its two blocks on both sides, so the jump across it is small, and the step between the blocks moves to the
    pixels ``band`` texels in, which are not boundaries.  Each boundary therefore counts with the largest jump
    along its normal over the ``2 * band + 1`` pixel pairs centred on it, and the reference with the largest of
    as many consecutive jumps: a seamless copy scores about 1 at any ``band``, and a step spread over the band
    counts with its sharpest part.  ``band`` 0 is the jump across the boundary alone."""
    img, ref = image.astype(np.float64), reference.astype(np.float64)
    seam_peaks, reference_peaks = [], []
    for axis, step in ((1, (0, 1)), (0, (1, 0))):
        a = [slice(None), slice(None)]
        b = [slice(None), slice(None)]
        a[axis], b[axis] = slice(None, -1), slice(1, None)
        a, b = tuple(a), tuple(b)
        jumps = np.linalg.norm(img[b] - img[a], axis=-1)
        seams = np.any(source[b] != source[a] + np.array(step), axis=-1)
        peaks, whole = _band_peaks(jumps, np.ones(jumps.shape, bool), axis, band)
        seam_peaks.append(peaks[seams & whole])
        ref_peaks, ref_whole = _band_peaks(np.linalg.norm(ref[b] - ref[a], axis=-1), valid[a] & valid[b], axis, band)
        reference_peaks.append(ref_peaks[ref_whole])
    seam_peaks, reference_peaks = np.concatenate(seam_peaks), np.concatenate(reference_peaks)
    if not seam_peaks.size or not reference_peaks.size or reference_peaks.mean() <= 0:
        return 0.0
    return float(seam_peaks.mean() / reference_peaks.mean())


def _band_peaks(jumps: np.ndarray, valid: np.ndarray, axis: int, band: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pair, the largest of the ``2 * band + 1`` jumps centred on it along ``axis``, and whether all of them
    lie inside the image and are valid."""
    if band == 0:
        return jumps, valid
    from scipy.ndimage import maximum_filter1d, minimum_filter1d
    size = 2 * band + 1
    peaks = maximum_filter1d(np.where(valid, jumps, 0.0), size, axis=axis, mode="constant")
    whole = minimum_filter1d(valid.astype(np.uint8), size, axis=axis, mode="constant", cval=0).astype(bool)
    return peaks, whole


def block_copy_seams(feather: int, size: int = 112, seed: int = 1, relax: int | None = None,
                     colour: float | None = None) -> list[float]:
    """:func:`block_seam_visibility` of single block copies (one reference each) of the shadow fixture at four
    target lights between the references' azimuths (``relax``: the block copy's seam relaxation sweeps,
    ``colour``: its colour-agreement weight; None: their defaults)."""
    refs, field = shadow_fixture(size, (45, 65), seed)
    return field_block_seams(refs, field, feather, relax, colour)


SEAM_TARGETS = ((65, 30), (45, 100), (70, 200), (30, 300))   # (tilt, azimuth) of the block-seam measurements


def field_block_seams(refs, field, feather: int, relax: int | None = None, colour: float | None = None) -> list[float]:
    """:func:`block_seam_visibility` of single block copies from ``refs`` under ``field``'s templates at the
    :data:`SEAM_TARGETS` lights, view straight down (``relax``, ``colour`` None: the block copy's defaults)."""
    from . import blockcopy, settings, synthesis, template
    relax = blockcopy.RELAX if relax is None else relax
    colour = blockcopy.COLOUR if colour is None else colour
    views, lights, pairs = synthesis.reference_table(refs)
    view = np.float32([[0, 0, 1]])
    out = []
    for k, (tilt, azimuth) in enumerate(SEAM_TARGETS):
        light = np.float32([settings.direction(tilt, azimuth)])
        images, _ = template.render(field.heights, synthesis.grey_albedo(field), field.normals, view, light)
        choice = synthesis.choose_references(view[0], light[0], views, lights, 1, True)
        v, l = pairs[choice.indices[0]]
        warped, valid = blockcopy.warp(refs.image(v, l), float(choice.rotations[0]), bool(choice.mirrored[0]),
                                       images[0].shape)
        copy = blockcopy.block_copy(images[0], warped, valid, seed=k, feather=feather, relax=relax, colour=colour)
        out.append(block_seam_visibility(copy.image, copy.source, warped, valid, band=feather))
    return out


def exemplar_fixture(kind: str, size: int = 128):
    """``(references, field)`` for the block-seam measurements: a 96 x 96 exemplar (``bumps`` or a kind of
    :mod:`demo.patterns` rendered at 10 lights, tilts 45 and 65, or a capture's ``.lp`` file, whose 96 x 96 crop at
    ``origin`` is given as ``"path@row,col"``, with its height from ``height.from_shading``) and its height field
    quilted to ``size^2``."""
    from btforge import SampleStack, stage
    from btforge.plugins.height.field import HeightField
    from .settings import direction
    if "@" in kind:
        path, origin = kind.split("@")
        stack = stage("stackio.read")(path=path)["stack"]
        refs = stage("synth.crop")(input=stack, origin=[int(v) for v in origin.split(",")], size=[96, 96])["output"]
        exemplar = stage("height.from_shading")(stack=refs)["height"]
    else:
        from btforge.plugins.demo.patterns import make_pattern
        from btforge.plugins.demo.procedural import make_material, render_lights
        m = make_material(96, 96, seed=1) if kind == "bumps" else make_pattern(kind, 96, 96, seed=1)
        dirs = np.array([direction(t, a) for t in (45, 65) for a in REFERENCE_AZIMUTHS], np.float32)
        refs = SampleStack(render_lights(m, dirs)[None], dirs, [[0.0, 0.0, 1.0]])
        exemplar = HeightField.from_height(m.height, m.albedo, wrap=True)
    return refs, quilted_field(exemplar, size)
