"""PCA planes with Gaussian (RBF) interpolation over the light set: relight's default basis (the model and
kernels: ``btforge.plugins.bases``)."""
from __future__ import annotations

from btforge import Param, declare_stage, hookimpl
from btforge.backend import single_threaded_blas
from btforge.plugins.bases import (COLORSPACE, ONE_VIEW, PLANES, SPACE_PARAM, YPLANES, fit_rbf, pca_precheck,
                                   report_fit)

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


RBF_SIGMA = Param("sigma", "float", 0.0, "width of the Gaussian interpolation between lights, exp(-d^2 / sigma^2) "
                  "for d the distance between unit light directions (relight's -S, 0.125 there); 0: the multiple of "
                  "the lights' spacing (0.7 to 2.8 x the median nearest-neighbour distance) that predicts held-out "
                  "lights best", low=0.0, high=10.0)
TABLE = Param("table", "choice", "interpolating", "responses: the table holds the principal components at the "
              "lights, so the Gaussian weights average neighbouring lights (relight); interpolating: the table is "
              "solved so that the interpolation passes through the components at the lights, which predicts the "
              "lights between them better", choices=("interpolating", "responses"))
RBF_COEFFICIENTS = Param("coefficients", "choice", "lsq", "projection: each texel's responses projected on the "
                         "principal components, as relight does (only with table: responses); lsq: least squares "
                         "against the interpolated basis at the capture's lights", choices=("projection", "lsq"))


@declare_stage(
    "rbf.fit",
    role="fit",
    version="2",
    sweep=[{"planes": 9}, {"planes": 18}, {"planes": 12, "colorspace": "ycc"}],
    inputs={"stack": "SampleStack"},
    outputs={"model": "LightTableModel"},
    params=[PLANES, COLORSPACE, YPLANES, RBF_SIGMA, TABLE, RBF_COEFFICIENTS, SPACE_PARAM],
    expects={"stack": ONE_VIEW},
    precheck=pca_precheck,
)
def rbf_fit(ctx, stack, *, planes, colorspace, yplanes, sigma, table, coefficients, space):
    """PCA-compressed light responses with Gaussian (RBF) interpolation over the light set: relight's default
    basis (``-b rbf``; ``colorspace: ycc`` is ``-b yrbf``).

    The leading principal components of the texels' responses over all lights (display values, or with
    ``space: linear`` linear radiance; ``auto`` picks by held-out lights; up to 65536 texels sampled) are the
    planes.  The table of components over the capture's lights is stored in the web
    layout and interpolated at any light with relight's normalised weights ``exp(-|l - l_i|^2 / sigma^2)``.
    By default (``table: interpolating``) the table is solved so that this interpolation passes through the
    components at the lights, and ``sigma`` is chosen among multiples of the lights' spacing by held-out
    lights: relit images between the lights are then blends, not averages of neighbours.  Each texel's
    ``planes`` coefficients are fitted by least squares against the interpolated basis at the capture's lights,
    on OpenCL.  ``sigma: 0.125, table: responses, coefficients: projection`` is relight's own fit.

    Outputs
    -------
    model : LightTableModel
        ``kind: rbf``; exports to the web layout ``rbf`` (colorspace mrgb or mycc).

    Notes
    -----
    ``sigma`` and ``space`` (as used), ``planes``, ``condition_number`` of the interpolated basis at the capture's lights.
    """
    with single_threaded_blas():  # small dense algebra: threads only contend
        model, stats = fit_rbf(stack, planes, colorspace, yplanes, sigma, coefficients, table, space=space)
    ctx.note("sigma", round(stats["sigma"], 4))
    ctx.note("space", stats["space"])
    return report_fit(ctx, model, stats)


@hookimpl
def btforge_stages():
    return [rbf_fit]
