"""relight's bases: hemispherical harmonics (``hsh.fit``), PCA planes with RBF interpolation over the light set
(``rbf.fit``) and PCA planes on a bilinear light grid (``bilinear.fit``).

One family because the three share one model (:class:`LightTableModel`: coefficient planes over a light table),
one projection and one evaluation kernel, the PCA and the luma-chroma (YCoCg) machinery; they differ only in
how the table is built and how a light direction weighs its entries (:mod:`.lightfuncs`).
"""
from __future__ import annotations

from btforge import Expect, Param, declare_stage, hookimpl
from btforge.backend import single_threaded_blas
from btforge.errors import BtforgeInputError

from .fit import fit_bilinear, fit_hsh, fit_rbf, ycc_split
from .model import LightTableModel

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for

__all__ = ["LightTableModel", "fit_hsh", "fit_rbf", "fit_bilinear"]

ONE_VIEW = Expect("views", 1, "these bases depend on the light only: select one view with stack.select first")
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
COEFFICIENTS = Param("coefficients", "choice", "projection", "projection: each texel's (resampled) responses projected "
                     "on the principal components, as relight does; lsq: least squares against the interpolated "
                     "basis at the capture's lights (closer at those lights, can be worse between them)",
                     choices=("projection", "lsq"))


def _hsh_precheck(params, paths=None):
    if params["planes"] not in (12, 27):
        raise BtforgeInputError("hsh.fit 'planes'", f"expected 12 or 27, found {params['planes']}",
                                "12 for second-order HSH, 27 for third order")


def _pca_precheck(params, paths=None):
    if params["colorspace"] == "ycc":
        ycc_split(params["planes"], params["yplanes"])
    if params.get("resolution") == 1:
        raise BtforgeInputError("bilinear.fit 'resolution'", "expected 0 (automatic) or 2 .. 20, found 1",
                                "a grid needs at least 2 x 2 nodes")


def _report(ctx, model, stats):
    ctx.note("planes", stats["planes"])
    ctx.note("condition_number", round(stats["condition_number"], 3))
    if stats["rank"] < stats["planes"]:
        ctx.warn(f"the lights determine only {stats['rank']} of {stats['planes']} coefficients (too few, clustered "
                 "or grazing lights): the regularisation keeps the rest small")
    return {"model": model}


@declare_stage(
    "hsh.fit",
    role="fit",
    sweep=[{"planes": 12}, {"planes": 27}, {"planes": 27, "colorspace": "ycc"}],
    inputs={"stack": "SampleStack"},
    outputs={"model": "LightTableModel"},
    params=[
        Param("planes", "int", 27, "12 (order 2: 4 terms x 3 channels) or 27 (order 3: 9 terms x 3), relight's -p",
              low=12, high=27),
        Param("colorspace", "choice", "rgb", "rgb: every channel has all terms; ycc (YCoCg): luma has all terms and "
              "each chroma component those of the order below (27: 9 + 4 + 4 = 17 planes; 12: 4 + 1 + 1 = 6)",
              choices=("rgb", "ycc")),
    ],
    per_texel=True,
    expects={"stack": ONE_VIEW},
    precheck=_hsh_precheck,
)
def hsh_fit(ctx, stack, *, planes, colorspace):
    """Fit hemispherical harmonics (HSH, Gautron et al. 2004) per texel, as relight's ``-b hsh`` does.

    The basis is the one RTI viewers evaluate (OpenLIME's, with the light's polar angle clamped 0.15 rad above
    the horizon); coefficients fit display values (sRGB), like an ``.rti`` file's, by least squares with a small
    ridge (see ``plugins/bases/fit.py``) that keeps them bounded when the lights are few, clustered or grazing.
    The projection runs on OpenCL and reads an 8-bit capture's bytes in place.

    Outputs
    -------
    model : LightTableModel
        ``kind: hsh``; exports to the web layout ``hsh`` (colorspace rgb).

    Notes
    -----
    ``planes``, ``condition_number`` of the light design.
    """
    _hsh_precheck({"planes": planes})
    with single_threaded_blas():  # small dense algebra: threads only contend
        model, stats = fit_hsh(stack, planes, colorspace)
    return _report(ctx, model, stats)


@declare_stage(
    "rbf.fit",
    role="fit",
    sweep=[{"planes": 9}, {"planes": 18}, {"planes": 12, "colorspace": "ycc"}],
    inputs={"stack": "SampleStack"},
    outputs={"model": "LightTableModel"},
    params=[PLANES, COLORSPACE, YPLANES, RBF_SIGMA, TABLE, RBF_COEFFICIENTS],
    expects={"stack": ONE_VIEW},
    precheck=_pca_precheck,
)
def rbf_fit(ctx, stack, *, planes, colorspace, yplanes, sigma, table, coefficients):
    """PCA-compressed light responses with Gaussian (RBF) interpolation over the light set: relight's default
    basis (``-b rbf``; ``colorspace: ycc`` is ``-b yrbf``).

    The leading principal components of the texels' responses over all lights (display values, up to 65536
    texels sampled) are the planes.  The table of components over the capture's lights is stored in the web
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
    ``sigma`` (as used), ``planes``, ``condition_number`` of the interpolated basis at the capture's lights.
    """
    with single_threaded_blas():  # small dense algebra: threads only contend
        model, stats = fit_rbf(stack, planes, colorspace, yplanes, sigma, coefficients, table)
    ctx.note("sigma", round(stats["sigma"], 4))
    return _report(ctx, model, stats)


@declare_stage(
    "bilinear.fit",
    role="fit",
    sweep=[{"planes": 9}, {"planes": 18}, {"planes": 12, "colorspace": "ycc"}],
    inputs={"stack": "SampleStack"},
    outputs={"model": "LightTableModel"},
    params=[PLANES, Param("resolution", "int", 0, "side of the light grid over the octahedral map of the hemisphere "
                          "(relight's -r); 0: the side (4 to 12) that predicts held-out lights best", low=0, high=20),
            COLORSPACE, YPLANES,
            Param("resampling", "choice", "smooth", "how samples become grid values: smooth: the grid whose "
                  "interpolation reproduces the samples while bending least (weight smoothness); relight: relight's, "
                  "pulled towards the Gaussian estimate (weights sigma, regularization)", choices=("smooth", "relight")),
            Param("smoothness", "float", 0.003, "resampling smooth: weight of the grid's bending (squared Laplacian) "
                  "against the samples", low=1e-6, high=1e3),
            SIGMA,
            Param("regularization", "float", 0.1, "resampling relight: pull of grid nodes the lights leave "
                  "undetermined towards their Gaussian estimate (relight's -R)", low=0.0, high=1e6), COEFFICIENTS],
    expects={"stack": ONE_VIEW},
    precheck=_pca_precheck,
)
def bilinear_fit(ctx, stack, *, planes, resolution, colorspace, yplanes, resampling, smoothness, sigma, regularization,
                 coefficients):
    """PCA planes on a ``resolution x resolution`` grid of light directions, interpolated bilinearly: relight's
    ``-b bilinear`` (``colorspace: ycc`` is ``-b ybilinear``).

    The grid is the octahedral map of the hemisphere rotated 45 degrees (the zenith at its centre, the horizon
    its border).  Each texel's samples are resampled onto the grid - by default as the thin plate through them
    (the grid whose bilinear interpolation reproduces the samples while bending least), or with
    ``resampling: relight`` as relight does (pulled towards a Gaussian estimate) - the leading principal
    components of the resampled responses become the planes, and each texel's coefficients are its resampled
    responses projected on them (``coefficients: lsq``: fitted at the capture's lights instead), on OpenCL.
    ``resolution: 0`` picks the grid side by held-out lights.  ``resolution: 8, resampling: relight`` is
    relight's own fit.

    Outputs
    -------
    model : LightTableModel
        ``kind: bilinear``; exports to the web layout ``bilinear`` (OpenLIME's ``bln``).

    Notes
    -----
    ``resolution`` (as used), ``planes``, ``condition_number`` of the interpolated basis at the capture's lights.
    """
    _pca_precheck({"planes": planes, "colorspace": colorspace, "yplanes": yplanes, "resolution": resolution})
    with single_threaded_blas():  # small dense algebra: threads only contend
        model, stats = fit_bilinear(stack, planes, resolution, colorspace, yplanes, sigma, regularization,
                                     coefficients, resampling, smoothness)
    ctx.note("resolution", stats["resolution"])
    return _report(ctx, model, stats)


@hookimpl
def btforge_stages():
    return [hsh_fit, rbf_fit, bilinear_fit]


@hookimpl
def btforge_buffer_types():
    return [LightTableModel]
