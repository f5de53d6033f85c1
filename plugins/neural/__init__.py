"""A learned basis: a latent code per texel and a small decoder network shared by every texel (NeuralRTI)."""
from __future__ import annotations

from btforge import Expect, Param, declare_stage, hookimpl
from btforge.backend import single_threaded_blas
from btforge.errors import BtforgeInputError

from .fit import fit_neural
from .model import MAX_LIGHT_ORDER, NeuralModel

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for

__all__ = ["NeuralModel", "fit_neural"]


def neural_precheck(params, paths=None):
    low = 2 if params.get("decoder", "harmonics") == "harmonics" else 0
    if params["light_order"] < low or params["light_order"] == 1:
        raise BtforgeInputError("neural.fit 'light_order'", f"expected {'0 or ' if low == 0 else ''}2 .. "
                                f"{MAX_LIGHT_ORDER} for the {params.get('decoder', 'harmonics')} decoder, found "
                                f"{params['light_order']}", "order 1 is the constant band alone; 0 (the direction's "
                                "x, y) is an input of the light decoder only")


@declare_stage(
    "neural.fit",
    role="fit",
    sweep=[{"latent": 9}, {"latent": 16}],
    inputs={"stack": "SampleStack"},
    outputs={"model": "NeuralModel"},
    params=[
        Param("decoder", "choice", "harmonics", "light: NeuralRTI's decoder, whose input is the code and the light "
              "direction, evaluated at every light; harmonics: a decoder from the code to the texel's spherical "
              "harmonic coefficients (of order light_order), evaluated once per texel, so that the function of the "
              "light stays smooth between the capture's lights", choices=("harmonics", "light")),
        Param("latent", "int", 12, "values of the latent code per texel (NeuralRTI: 9)", low=1, high=64),
        Param("hidden", "int", 50, "units of each hidden layer of the decoder", low=4, high=256),
        Param("layers", "int", 3, "hidden layers of the decoder", low=1, high=6),
        Param("light_order", "int", 4, "harmonics decoder: the order N of the harmonics it outputs (bands 0 .. "
              "N-1, N^2 coefficients per channel); light decoder: its light input, the harmonics of bands 1 .. N-1 "
              "of the direction (N^2 - 1 values), or for 0 the direction's x and y, as NeuralRTI (which predicts held-out "
              "lights better)", low=0,
              high=MAX_LIGHT_ORDER),
        Param("jitter", "float", 0.0, "light decoder: each step moves the lights at random by about this many "
              "radians, so the decoder sees their neighbourhoods (0: the measured lights only)", low=0.0, high=0.5),
        Param("epochs", "int", 20, "passes of Adam over the training texels (each with all its lights)",
              low=1, high=10000),
        Param("texels", "int", 20000, "texels sampled at random to train on; every texel is then encoded",
              low=1, high=1 << 26),
        Param("seed", "int", 0, "seed of the texel sample, the initial weights and the batch order", low=0,
              high=2 ** 31 - 1),
    ],
    expects={"stack": Expect("views", 1, "the decoder depends on the light only: select one view with "
                             "stackio.select first")},
    precheck=neural_precheck,
)
def neural_fit(ctx, stack, *, decoder, latent, hidden, layers, light_order, jitter, epochs, texels, seed):
    """Fit a learned basis (NeuralRTI, Dulecha et al. 2020): a latent code per texel and a decoder network,
    shared by every texel, from the code to the texel's function of the light.

    An encoder (two hidden layers of 64 ELU units) maps a texel's display values at the capture's lights (an
    8-bit capture's bytes / 255; a linear capture's radiance sRGB-encoded, so relighting clips it at 1) to its
    ``latent`` code.  The decoder (``layers`` hidden layers of ``hidden`` ELU units, linear output) maps the code
    to the texel's spherical-harmonic coefficients of order ``light_order``, weighted at a light by the
    harmonics there (``decoder: harmonics``), or maps the code and features of a light direction to the value
    (``decoder: light``, NeuralRTI's).  Both networks are trained together by mini-batch Adam (32 texels with
    all their lights per step, the step decaying from 5e-3 along a cosine, gradients clipped to norm 1) to
    reproduce the display values of ``texels`` texels sampled at random; then every texel is encoded.  Only the
    codes and the decoder are kept.  Training runs in NumPy on one thread (a fit is deterministic for a given
    ``seed``); relighting runs on the OpenCL device.  ``web.export`` writes the model in OpenLIME's neural
    layout (OpenLIME opens NeuralRTI's network: ``decoder: light``, ``light_order: 0``, ``latent: 9``,
    ``layers: 2``); ``btforge view`` shows both decoders.

    Outputs
    -------
    model : NeuralModel
        codes ``[H, W, latent]`` and the decoder's weights.

    Notes
    -----
    ``train_psnr_db`` on the training texels (their last epoch), ``texels`` trained on.
    """
    neural_precheck({"light_order": light_order, "decoder": decoder})
    if stack.n_view != 1:
        raise BtforgeInputError("neural.fit 'stack'", f"expected one view, found {stack.n_view}",
                                "select one view with stackio.select first")
    with single_threaded_blas():  # small products: threads only contend, and one thread is reproducible
        model, stats = fit_neural(stack, decoder, latent, hidden, layers, light_order, epochs, texels, seed, jitter)
    ctx.note("train_psnr_db", stats["train_psnr_db"])
    ctx.note("texels", stats["texels"])
    return {"model": model}


@hookimpl
def btforge_stages():
    return [neural_fit]


@hookimpl
def btforge_buffer_types():
    return [NeuralModel]


@hookimpl
def btforge_bench_commands():
    from .bench import bench_neural
    return {"neural": bench_neural}
