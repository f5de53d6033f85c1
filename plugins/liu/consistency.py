"""Geometric consistency of a synthesized BTF: do its dark regions fall where the template's shadows are?

The measurement behind the "IoU >= 0.7 over at least 10 lights" figure, shared by the test and by
``btforge bench liu`` so that both measure the same thing.  A quilted height field is synthesized under a ring of
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


def measure(size: int = 112, tilts=LOW_TILTS, baseline: bool = True, seed: int = 1) -> Consistency:
    """Shadow IoU over ``len(tilts) x 6`` target lights on a quilted ``size^2`` height field (see module);
    references: the built-in material under the same tilts at 5 other azimuths."""
    from btforge import SampleStack, stage
    from btforge.plugins.demo.procedural import make_material, render_lights
    from btforge.plugins.height.field import HeightField

    from .settings import direction

    m = make_material(96, 96, bumps=20, bump_height=5.0, seed=seed)
    dirs = np.array([direction(t, a) for t in tilts for a in REFERENCE_AZIMUTHS], np.float32)
    refs = SampleStack(render_lights(m, dirs)[None], dirs, [[0.0, 0.0, 1.0]])
    exemplar = HeightField.from_height(m.height, m.albedo, wrap=True)
    coords = stage("synth.quilt")(exemplar=exemplar, size=[size, size], block=32, wrap=True, seed=4)["coords"]
    field = stage("synth.materialize")(coords=coords, source=exemplar)["output"]
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
            nearest = int(np.argmax(refs.lights @ stack.lights[l]))
            one = SampleStack(refs.samples[:, nearest:nearest + 1], refs.lights[nearest:nearest + 1], refs.views)
            c2 = stage("synth.quilt")(exemplar=one, size=[size, size], block=24, seed=l)["coords"]
            flat = stage("synth.materialize")(coords=c2, source=one)["output"]
            independent.append(iou(dark_mask(flat.samples[0, 0]), shadow))
    return Consistency(stack.lights, np.array(ours), np.array(independent), np.array(fraction))
