"""PCA planes on a bilinear grid of light directions: relight's ``-b bilinear`` (the model and kernels:
``btforge.plugins.bases``)."""
from __future__ import annotations

from btforge import Param, declare_stage, hookimpl
from btforge.backend import single_threaded_blas
from btforge.plugins.bases import (COEFFICIENTS, COLORSPACE, ONE_VIEW, PLANES, SIGMA, SPACE_PARAM, YPLANES,
                                   fit_bilinear, pca_precheck, report_fit)

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


@declare_stage(
    "bilinear.fit",
    role="fit",
    version="3",
    sweep=[{"planes": 9}, {"planes": 18}, {"planes": 12, "colorspace": "ycc"}],
    inputs={"stack": "SampleStack"},
    outputs={"model": "LightTableModel"},
    params=[PLANES, Param("resolution", "int", 0, "side of the light grid over the octahedral map of the hemisphere "
                          "(relight's -r); 0: the side (every one from 4 to 12) that predicts held-out lights best", low=0, high=20),
            COLORSPACE, YPLANES,
            Param("resampling", "choice", "smooth", "how samples become grid values: smooth: the grid whose "
                  "interpolation reproduces the samples while bending least (weight smoothness); relight: relight's, "
                  "pulled towards the Gaussian estimate (weights sigma, regularization)", choices=("smooth", "relight")),
            Param("smoothness", "float", 0.003, "resampling smooth: weight of the grid's bending (squared Laplacian) "
                  "against the samples", low=1e-6, high=1e3),
            SIGMA,
            Param("regularization", "float", 0.1, "resampling relight: pull of grid nodes the lights leave "
                  "undetermined towards their Gaussian estimate (relight's -R)", low=0.0, high=1e6), COEFFICIENTS,
            Param("space", "choice", "srgb", SPACE_PARAM.doc.replace("auto: for", "auto (chosen together with "
                  "resolution 0): for") + "; auto is not the default: held-out folds of a dome's lights leave holes in "
                  "the grid and misjudge linear fits (see the docs' benchmarks)", choices=SPACE_PARAM.choices)],
    expects={"stack": ONE_VIEW},
    precheck=pca_precheck,
)
def bilinear_fit(ctx, stack, *, planes, resolution, colorspace, yplanes, resampling, smoothness, sigma, regularization,
                 coefficients, space):
    """PCA planes on a ``resolution x resolution`` grid of light directions, interpolated bilinearly: relight's
    ``-b bilinear`` (``colorspace: ycc`` is ``-b ybilinear``).

    The grid is the octahedral map of the hemisphere rotated 45 degrees (the zenith at its centre, the horizon
    its border).  Each texel's samples are resampled onto the grid - by default as the thin plate through them
    (the grid whose bilinear interpolation reproduces the samples while bending least), or with
    ``resampling: relight`` as relight does (pulled towards a Gaussian estimate) - the leading principal
    components of the resampled responses become the planes, and each texel's coefficients are its resampled
    responses projected on them (``coefficients: lsq``: fitted at the capture's lights instead), on OpenCL.
    ``resolution: 0`` picks the grid side by held-out lights.  The samples are display values, or with ``space:
    linear`` the linear radiance of an 8-bit capture (``auto``: whichever predicts held-out lights better).  ``resolution: 8, resampling: relight`` is
    relight's own fit.

    Outputs
    -------
    model : LightTableModel
        ``kind: bilinear``; exports to the web layout ``bilinear`` (OpenLIME's ``bln``).

    Notes
    -----
    ``resolution`` and ``space`` (as used), ``planes``, ``condition_number`` of the interpolated basis at the capture's lights.
    """
    pca_precheck({"planes": planes, "colorspace": colorspace, "yplanes": yplanes, "resolution": resolution})
    with single_threaded_blas():  # small dense algebra: threads only contend
        model, stats = fit_bilinear(stack, planes, resolution, colorspace, yplanes, sigma, regularization,
                                     coefficients, resampling, smoothness, space=space)
    ctx.note("resolution", stats["resolution"])
    ctx.note("space", stats["space"])
    return report_fit(ctx, model, stats)


@hookimpl
def btforge_stages():
    return [bilinear_fit]
