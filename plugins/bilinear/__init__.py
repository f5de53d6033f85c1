"""PCA planes on a bilinear grid of light directions: relight's ``-b bilinear`` (the model and kernels:
``btforge.plugins.bases``)."""
from __future__ import annotations

from btforge import Param, declare_stage, hookimpl
from btforge.backend import single_threaded_blas
from btforge.plugins.bases import (COEFFICIENTS, COLORSPACE, ONE_VIEW, PLANES, SIGMA, SPACE_PARAM, YPLANES,
                                   fit_bilinear, pca_precheck, report_fit)
from btforge.plugins.bases.fit import AUTO_PLANES

AUTO_PLANES_DOC = (f"; 0: the fewest (at most {AUTO_PLANES}) whose truncation of the resampled grid stays within half "
                   "a display level (RMS) at the fitting lights, judged on a grid of texels")

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


@declare_stage(
    "bilinear.fit",
    role="fit",
    version="5",
    sweep=[{"planes": 9}, {"planes": 18}, {"planes": 12, "colorspace": "ycc"}],
    inputs={"stack": "SampleStack"},
    outputs={"model": "LightTableModel"},
    params=[Param("planes", "int", 0, PLANES.doc + AUTO_PLANES_DOC, low=0, high=PLANES.high),
            Param("resolution", "int", 0, "side of the light grid over the octahedral map of the hemisphere "
                  "(relight's -r); 0: for resampling spline the smallest side from 8 to 24 whose grid reproduces the "
                  "spline between the lights to within half a display level, for the others the side (every one "
                  "from 4 to 12) that predicts held-out lights best", low=0, high=24),
            COLORSPACE, YPLANES,
            Param("resampling", "choice", "spline", "how samples become grid values: spline: the values at the "
                  "nodes of a smoothing spline through the samples over the sphere of directions (weight "
                  "smoothness); smooth: the grid whose interpolation reproduces the samples while bending least "
                  "(weight smoothness); relight: relight's, pulled towards the Gaussian estimate (weights sigma, "
                  "regularization)", choices=("spline", "smooth", "relight")),
            Param("smoothness", "float", 0.0, "resampling spline: weight of the misfit at the lights against the "
                  "spline's bending (0: chosen with space by leave-one-out among 0.001 to 0.1); resampling smooth: "
                  "weight of the grid's bending (squared Laplacian) against the samples (0: 0.003)", low=0.0, high=1e3),
            SIGMA,
            Param("regularization", "float", 0.1, "resampling relight: pull of grid nodes the lights leave "
                  "undetermined towards their Gaussian estimate (relight's -R)", low=0.0, high=1e6), COEFFICIENTS,
            Param("space", "choice", "auto", SPACE_PARAM.doc.replace("auto: for", "auto (for resampling spline "
                  "chosen with smoothness by leave-one-out, for the others with resolution 0 on held-out lights): "
                  "for"), choices=SPACE_PARAM.choices)],
    expects={"stack": ONE_VIEW},
    precheck=pca_precheck,
)
def bilinear_fit(ctx, stack, *, planes, resolution, colorspace, yplanes, resampling, smoothness, sigma, regularization,
                 coefficients, space):
    """PCA planes on a ``resolution x resolution`` grid of light directions, interpolated bilinearly: relight's
    ``-b bilinear`` (``colorspace: ycc`` is ``-b ybilinear``).

    The grid is the octahedral map of the hemisphere rotated 45 degrees (the zenith at its centre, the horizon
    its border).  Each texel's samples are resampled onto the grid - by default as the values at the grid's
    nodes of a smoothing spline through them over the sphere of directions (so that what the grid holds
    between rings of lights does not depend on where its lines fall), with ``resampling: smooth`` as the thin
    plate on the grid itself (the grid whose bilinear interpolation reproduces the samples while bending least),
    or with ``resampling: relight`` as relight does (pulled towards a Gaussian estimate) - the leading principal
    components of the resampled responses become the planes, and each texel's coefficients are its resampled
    responses projected on them (``coefficients: lsq``: fitted at the capture's lights instead), on OpenCL.
    The samples are display values, or with ``space: linear`` the linear radiance of an 8-bit capture.  For the
    spline, ``space: auto`` and ``smoothness: 0`` are chosen together by how well the spline predicts each
    fitting light from the others (exact leave-one-out) and ``resolution: 0`` is the smallest side whose
    bilinear grid reproduces the spline to within half a display level; for the other resamplings
    ``resolution: 0`` and ``space: auto`` are chosen together on held-out lights.  ``planes: 0`` (the default)
    keeps the fewest principal components whose truncation of the resampled grid stays within half a display
    level (RMS) at the fitting lights, at most 27: a capture whose responses vary in few ways keeps few planes.
    ``resolution: 8,
    resampling: relight, space: srgb`` is relight's own fit.

    Outputs
    -------
    model : LightTableModel
        ``kind: bilinear``; exports to the web layout ``bilinear`` (OpenLIME's ``bln``).

    Notes
    -----
    ``resolution``, ``space`` and (but for relight's resampling) ``smoothness`` as used, ``planes``, ``condition_number`` of the interpolated basis
    at the capture's lights.
    """
    pca_precheck({"planes": planes, "colorspace": colorspace, "yplanes": yplanes, "resolution": resolution})
    with single_threaded_blas():  # small dense algebra: threads only contend
        model, stats = fit_bilinear(stack, planes, resolution, colorspace, yplanes, sigma, regularization,
                                     coefficients, resampling, smoothness, space=space)
    ctx.note("resolution", stats["resolution"])
    ctx.note("space", stats["space"])
    if resampling != "relight":  # relight's resampling is weighted by sigma and regularization instead
        ctx.note("smoothness", stats["smoothness"])
    return report_fit(ctx, model, stats)


@hookimpl
def btforge_stages():
    return [bilinear_fit]
