"""Hemispherical harmonics fitted per texel, as relight's ``-b hsh`` (the model and kernels:
``btforge.plugins.bases``)."""
from __future__ import annotations

from btforge import Param, declare_stage, hookimpl
from btforge.backend import single_threaded_blas
from btforge.errors import BtforgeInputError
from btforge.plugins.bases import (ONE_VIEW, RIDGE_PARAM, SPACE_PARAM, check_ridge, fit_hsh, report_fit,
                                   settle_choices)

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


def hsh_precheck(params, paths=None):
    if params["planes"] not in (12, 27):
        raise BtforgeInputError("hsh.fit 'planes'", f"expected 12 or 27, found {params['planes']}",
                                "12 for second-order HSH, 27 for third order")
    if "ridge" in params:
        check_ridge(params["ridge"], "hsh.fit")


@declare_stage(
    "hsh.fit",
    role="fit",
    version="2",
    sweep=[{"planes": 12}, {"planes": 27}, {"planes": 27, "colorspace": "ycc"}],
    inputs={"stack": "SampleStack"},
    outputs={"model": "LightTableModel"},
    params=[
        Param("planes", "int", 27, "12 (order 2: 4 terms x 3 channels) or 27 (order 3: 9 terms x 3), relight's -p",
              low=12, high=27),
        Param("colorspace", "choice", "rgb", "rgb: every channel has all terms; ycc (YCoCg): luma has all terms and "
              "each chroma component those of the order below (27: 9 + 4 + 4 = 17 planes; 12: 4 + 1 + 1 = 6)",
              choices=("rgb", "ycc")),
        SPACE_PARAM,
        RIDGE_PARAM,
    ],
    per_texel=True,
    settle=lambda inputs, params: settle_choices(inputs["stack"], params, _hsh_settings),
    expects={"stack": ONE_VIEW},
    precheck=hsh_precheck,
)
def hsh_fit(ctx, stack, *, planes, colorspace, space, ridge):
    """Fit hemispherical harmonics (HSH, Gautron et al. 2004) per texel, as relight's ``-b hsh`` does.

    The basis is the one RTI viewers evaluate (OpenLIME's, with the light's polar angle clamped 0.15 rad above
    the horizon); coefficients fit display values (sRGB), like an ``.rti`` file's, or with ``space: linear`` the
    linear radiance they stand for (``auto``: whichever predicts held-out lights of a grid of texels better, see
    ``ptm.fit``), by ridge least squares (see
    ``plugins/bases/fit.py``): the ridge keeps them bounded when the lights are few, clustered or grazing, and
    ``ridge: auto`` weighs it by how well the fits predict each light left out of a grid of texels (closed-form
    leave-one-out; the constant term is not penalised).
    The projection runs on OpenCL and reads an 8-bit capture's bytes in place.

    Outputs
    -------
    model : LightTableModel
        ``kind: hsh``; exports to the web layout ``hsh`` (colorspace rgb).

    Notes
    -----
    ``planes``, ``condition_number`` of the light design, ``ridge`` (as used).
    """
    hsh_precheck({"planes": planes, "ridge": ridge})
    with single_threaded_blas():  # small dense algebra: threads only contend
        model, stats = fit_hsh(stack, planes, colorspace, ridge=ridge, space=space)
    ctx.note("space", stats["space"])
    ctx.note("ridge", stats["ridge"])
    return report_fit(ctx, model, stats)


def _hsh_settings(stack, params):
    from btforge.plugins.bases.fit import hsh_settings
    return hsh_settings(stack, params["planes"], params["colorspace"], params["ridge"], params["space"])


@hookimpl
def btforge_stages():
    return [hsh_fit]
