"""Exposure and near-light fall-off correction of multi-light captures (hand-held flash, shot-to-shot jitter)."""
from __future__ import annotations

import numpy as np

from btforge import Param, declare_stage, hookimpl

from .exposure import corrected, estimate_exposure

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


@declare_stage(
    "normalize.stack", deprecated_names=("stack.normalize",),
    inputs={"stack": "SampleStack"},
    outputs={"stack": "SampleStack"},
    keeps_facts={"stack": "stack"},  # gains change the samples, not the views or lights
    params=[
        Param("reference", "ints", None, "a white target or matte patch as [row, col, height, width] in pixels that "
              "sets each image's intensity; leave out to estimate it robustly from the whole capture", length=4),
        Param("falloff", "bool", False, "also correct light fall-off across the frame (a light close to the "
              "surface): a smooth per-image field, quadratic in log intensity"),
    ],
)
def stack_normalize(ctx, stack, *, reference, falloff):
    """Correct each image's light intensity (and optionally its fall-off across the frame) in a single-view capture.

    A hand-held lamp or flash gives a different intensity in every shot, which no reflectance model can fit.
    Each image gets a gain: from a ``reference`` region (a white target or matte patch), or robustly from the
    whole capture by alternating a per-pixel PTM and the per-image gains, with Tukey weights so shadows,
    highlights and clipped pixels do not steer them.  A gain that the light direction explains (as a surface's
    own shading would be) is left in the images: only what no reflectance function explains is removed.  Run it
    on the whole capture, before splitting off test lights.

    Outputs
    -------
    stack : SampleStack
        Image ``i`` divided by its gain; 8-bit captures stay 8-bit (re-encoded).

    Notes
    -----
    ``scales`` (each image's gain at the frame centre, median 1), ``scale_range``, ``residual_before`` and
    ``residual_after`` (robust relative residual of the fit without and with the gains).
    """
    exposure = estimate_exposure(stack, list(reference) if reference else None, falloff)
    scales = exposure.scales
    ctx.note("scales", [round(float(s), 4) for s in scales])
    ctx.note("scale_range", [round(float(scales.min()), 4), round(float(scales.max()), 4)])
    ctx.note("residual_before", round(exposure.rms_before, 5))
    ctx.note("residual_after", round(exposure.rms_after, 5))
    if np.ptp(np.log(scales)) > np.log(4.0):
        ctx.warn(f"image intensities differ by {scales.max() / scales.min():.1f}x: check the darkest and brightest "
                 "shots for a missed flash or a changed exposure")
    return {"stack": corrected(stack, exposure)}


@hookimpl
def btforge_stages():
    return [stack_normalize]


@hookimpl
def btforge_bench_commands():
    from .bench import bench_normalize
    return {"normalize": bench_normalize}
