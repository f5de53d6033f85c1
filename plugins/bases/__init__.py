"""What relight's bases share: the model (:class:`LightTableModel`: coefficient planes over a light table), one
projection and one evaluation kernel, the PCA and the luma-chroma (YCoCg) machinery, and the params the fits have
in common.

The fits themselves are the families ``hsh`` (hemispherical harmonics, ``hsh.fit``), ``rbf`` (PCA planes with
RBF interpolation over the light set, ``rbf.fit``) and ``bilinear`` (PCA planes on a bilinear light grid,
``bilinear.fit``); they differ only in how the table is built and how a light direction weighs its entries
(:mod:`.lightfuncs`).
"""
from __future__ import annotations

from btforge import Expect, Param, hookimpl
from btforge.errors import BtforgeInputError

from .fit import fit_bilinear, fit_hsh, fit_rbf, ycc_split
from .model import LightTableModel

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for

__all__ = ["LightTableModel", "fit_hsh", "fit_rbf", "fit_bilinear", "pca_precheck", "report_fit"]

ONE_VIEW = Expect("views", 1, "these bases depend on the light only: select one view with stackio.select first")
COLORSPACE = Param("colorspace", "choice", "rgb", "rgb: planes mix all three channels (relight's mrgb); ycc: "
                   "planes of luma and of chroma (YCoCg) are separate, so fewer chroma planes can be kept (relight's "
                   "yrbf / ybilinear, colorspace mycc)", choices=("rgb", "ycc"))
YPLANES = Param("yplanes", "int", 0, "for colorspace ycc, how many planes are luma (relight's -y); the rest split "
                "evenly between the two chroma components, so planes - yplanes must be even; 0: planes - 2 * "
                "(planes // 4)", low=0, high=64)
PLANES = Param("planes", "int", 9, "coefficient planes per texel: PCA components kept (relight's -p)", low=1, high=64)
SIGMA = Param("sigma", "float", 0.125, "width of the Gaussian interpolation between lights, exp(-d^2 / sigma^2) for "
              "d the distance between unit light directions (relight's -S; 0.125 suits ~100 lights)",
              low=1e-3, high=10.0)
COEFFICIENTS = Param("coefficients", "choice", "projection", "projection: each texel's (resampled) responses projected "
                     "on the principal components, as relight does; lsq: least squares against the interpolated "
                     "basis at the capture's lights (closer at those lights, can be worse between them)",
                     choices=("projection", "lsq"))


def pca_precheck(params, paths=None):
    if params["colorspace"] == "ycc":
        ycc_split(params["planes"], params["yplanes"])
    if params.get("resolution") == 1:
        raise BtforgeInputError("bilinear.fit 'resolution'", "expected 0 (automatic) or 2 .. 20, found 1",
                                "a grid needs at least 2 x 2 nodes")


def report_fit(ctx, model, stats):
    ctx.note("planes", stats["planes"])
    ctx.note("condition_number", round(stats["condition_number"], 3))
    if stats["rank"] < stats["planes"]:
        ctx.warn(f"the lights determine only {stats['rank']} of {stats['planes']} coefficients (too few, clustered "
                 "or grazing lights): the regularisation keeps the rest small")
    return {"model": model}


@hookimpl
def btforge_buffer_types():
    return [LightTableModel]
