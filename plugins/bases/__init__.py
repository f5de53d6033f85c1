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

from .fit import AUTO_PLANES, fit_bilinear, fit_hsh, fit_rbf, ycc_split
from .model import LightTableModel

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for

__all__ = ["LightTableModel", "fit_hsh", "fit_rbf", "fit_bilinear", "pca_precheck", "report_fit", "RIDGE_PARAM",
           "SPACE_PARAM", "check_ridge", "settle_choices"]

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


RIDGE_PARAM = Param("ridge", "any", "auto", "weight of the ridge penalty lambda |c|^2 on the coefficients of a "
                    "least-squares fit, lambda = ridge x the largest squared singular value of the basis at the "
                    "capture's lights (a number in [0, 1]; at least 1e-6, which only bounds coefficients the lights "
                    "leave undetermined); auto: the weight (1e-6 to 1e-2) whose fits best predict each sample left "
                    "out, judged in closed form on a grid of texels")


SPACE_PARAM = Param("space", "choice", "auto", "what the coefficients fit: srgb, the display values an 8-bit capture "
                    "holds (as relight's -I srgb and RTI viewers); linear, the linear radiance they stand for (as "
                    "relight's default), which evaluation clips to [0, 1] instead of decoding; auto: for an 8-bit "
                    "capture the one whose fits predict held-out lights of a grid of texels better, display values "
                    "otherwise", choices=("auto", "srgb", "linear"))


def check_ridge(ridge, stage: str) -> None:
    if ridge == "auto":
        return
    if isinstance(ridge, bool) or not isinstance(ridge, (int, float)) or not 0 <= ridge <= 1:
        raise BtforgeInputError(f"{stage} 'ridge'", f"expected 'auto' or a number in [0, 1], found {ridge!r}",
                                "use auto (chosen by leave-one-out on a grid of texels) or e.g. 0.001")


def settle_choices(stack, params: dict, choose) -> dict:
    """``space: auto`` and ``ridge: auto`` judged once on a grid of texels of the whole stack (``choose(stack,
    params)`` -> (space, ridge)), so every band of a distributed fit uses what the whole-stack fit would choose."""
    if "auto" not in (params.get("ridge"), params.get("space")) or stack.n_view != 1 or stack.n_channel != 3:
        return params  # nothing to choose, or a stack the fit refuses
    space, ridge = choose(stack, params)
    return {**params, "space": space, "ridge": ridge}


def pca_precheck(params, paths=None):
    if params["colorspace"] == "ycc":
        ycc_split(params["planes"] or AUTO_PLANES, params["yplanes"])  # planes 0 (bilinear.fit): at most AUTO_PLANES
    if params.get("resolution") == 1:
        raise BtforgeInputError("bilinear.fit 'resolution'", "expected 0 (automatic) or 2 .. 24, found 1",
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
