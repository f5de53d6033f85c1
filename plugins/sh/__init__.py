"""Double spherical harmonics (light x view): constrained least-squares fit on OpenCL, optional 8-bit quantization."""
from __future__ import annotations

from btforge import Param, declare_stage, hookimpl

from .model import DEFAULT_ENERGY_FACTOR, MAX_ORDER, SHModel, compression_rate, fit_sh, real_sh

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for

__all__ = ["SHModel", "fit_sh", "real_sh", "compression_rate"]


@declare_stage(
    "sh.fit",
    role="fit",
    sweep=[{"light_order": "auto"}] + [{"light_order": n, "smoothness": 0} for n in (2, 3, 4, 5, 6)],
    inputs={"stack": "SampleStack"},
    outputs={"model": "SHModel"},
    params=[
        Param("light_order", "choice", "auto", "SH order over the light: bands 0..N-1, N^2 coefficients; auto: the "
              "order (2 to 6, and the space, when space is auto) whose fits predict held-out lights of a sample of "
              "texels best", choices=("auto",) + tuple(range(1, MAX_ORDER + 1))),
        Param("view_order", "int", 1, "SH order over the view (N^2 coefficients); ignored, with a note, for a "
              "single-view stack", low=1, high=MAX_ORDER),
        Param("quantize", "bool", False, "store coefficients as 8 bits with a per-coefficient scale and bias"),
        Param("space", "choice", "auto", "what the harmonics fit: linear radiance, or sRGB display values (the bytes "
              "of an 8-bit capture); auto: for an 8-bit capture the one that predicts held-out lights of a sample of "
              "texels better, linear otherwise", choices=("auto", "linear", "srgb")),
        Param("smoothness", "any", "auto", "weight of a penalty on the fitted function's squared gradient over the "
              "sphere (relative to the fit to the samples): a number >= 0 (0: none), or auto: the weight (0 or "
              "0.003 to 0.03), with the light order, whose fits predict held-out lights of a sample of texels best"),
        Param("energy_factor", "float", DEFAULT_ENERGY_FACTOR, "scales the energy bound of the constrained fit; 1 "
              "lets the function hold as much energy below the horizon as above (the mirror rule), smaller "
              "regularises more, larger less", low=1e-6, high=1e6),
    ],
    # quantization scales over all texels; auto judges its order, space and smoothness on a grid of all of
    # them, once, before the texels are split (settle)
    per_texel=lambda params: not params["quantize"],
    settle=lambda inputs, params: _settle_choices(inputs["stack"], params),
    device=True,
)
def sh_fit(ctx, stack, *, light_order, view_order, quantize, space, smoothness, energy_factor):
    """Fit double spherical harmonics ``f(l, v) = sum c[a, b] Y_a(v) Y_b(l)`` per texel and channel, on OpenCL.

    Order N means SH bands 0 .. N-1, i.e. N^2 coefficients: ``k_l = light_order^2`` over the light and
    ``k_v = view_order^2`` over the view (1 for a top-view RTI stack, giving plain SH over the light; the
    coefficients then carry the factor ``sqrt(4 pi)`` of the constant view harmonic).  Real SH are
    orthonormal without the Condon-Shortley phase; coefficient ``l^2 + l + m`` is band ``l``, index ``m``.

    Samples cover only the upper hemisphere, so plain least squares can make the function huge below the
    horizon, and at high orders it amplifies noise.  The fit is a constrained least squares (Leung et al.,
    Tileable BTF; Lam, Leung & Wong 2006): it minimises ``||A c - y||^2 + lambda ||c||^2`` with, per texel and
    channel, the smallest ``lambda >= 0`` (found by bisection) whose solution's full-sphere energy ``||c||^2``
    stays within ``energy_factor * (4 pi)^2 * mean(y^2)``.  ``2 pi mean(y^2)`` estimates the energy over a
    sampled hemisphere, and the bound allows twice that per sampled hemisphere (the energy of the mirror image
    about the horizon).  Texels whose least-squares fit is already within the bound get ``lambda = 0``.  The
estimate assumes lights (and views) spread roughly evenly in solid angle.  Because the basis is orthonormal,
the bound also caps the relit value in every direction, below the horizon included:
``|f| <= sqrt(energy_factor * k_l * k_v * mean(y^2))``.

    The design matrix is shared by all texels, so its SVD is computed once; each texel then costs a
    projection and a cheap bisection.  The stack is streamed over bands of rows.

    ``space: srgb`` fits the display values an 8-bit capture holds (its bytes / 255; a linear capture's
    radiance sRGB-encoded) and relighting decodes the evaluated values (clipped to [0, 1]) back to linear
    radiance; the energy bound then applies to the display values.  Held-out PSNR is judged on display values,
    where a display-space fit spends its accuracy evenly instead of on the bright samples.  ``auto`` fits a
    linear capture linearly and, for an 8-bit one, compares both spaces on held-out lights of a grid of up to
    4096 texels (as ``ptm.fit`` does).

    ``light_order: auto`` (the default) chooses the order the same way: orders 2 to 6 (those with no more
    coefficients than the lights each held-out fold keeps), in each space ``space`` allows, are fitted to a grid
    of up to 4096 texels with every light held out once (five folds), and the order and space whose fits predict
    the held-out samples with the lowest mean squared error (of display values for an 8-bit capture) are fitted
    to the whole stack; errors within 5 % of the lowest count as a tie, won by the higher order, because the
    whole stack has a quarter more lights than each fold.  Higher orders follow the fitted lights more closely but, with few lights, swing between
    them; held-out lights show where that starts.  With fewer than 10 lights no light is held out: the order is
    the largest up to 4 with two lights per coefficient.  The notes give the chosen ``light_order`` and the
    held-out errors compared.

    ``smoothness`` adds ``smoothness * (L / 4 pi) * sum_lm l (l + 1) c_lm^2`` to the least-squares objective
    (``L`` lights): the squared gradient of the fitted function over the sphere, in units of the fit to the
    samples (``L / 4 pi`` is the data term's weight per coefficient for lights spread evenly).  Higher bands
    cost more, so between and beyond the lights the function stays smooth instead of swinging; the constant
    band is free.  It is solved as least squares with extra rows of zero samples, so the per-texel solve and
    the energy bound are unchanged.  ``auto`` (the default) tries, after the order is chosen, that order and
    the higher ones at smoothness 0.003, 0.01 and 0.03 on the same held-out folds and keeps the best
    setting, no smoothing included: a smoothed higher order often predicts held-out lights better than a
    truncated lower one (the accuracy figures in the docs).

    With ``quantize`` each coefficient is stored as ``uint8`` with a scale and bias per coefficient index,
    covering its range over all texels and channels; coefficients are then within half a step of the fit.

    Fewer samples (lights x views) than coefficients is allowed - the constraint picks a bounded solution - but
    warns.

    Outputs
    -------
    model : SHModel
        ``coeffs [H, W, C, k_v, k_l]`` (float32, or uint8 with ``scale``/``bias``), evaluated by ``relight.images``.

    Notes
    -----
    ``compression_rate_percent`` (coefficients over samples per texel and channel: 25 x 25 coefficients of an
    81 x 81 BTF give 9.53 %), ``lambda_median``, ``lambda_max``, ``clamped`` (texel-channels with an active
    constraint) and ``clamped_fraction``, ``view_order`` (as used), ``rank`` of the design matrix.
    """
    if stack.n_view == 1 and view_order != 1:
        ctx.note("view_order_ignored", f"view_order {view_order} ignored: the stack has a single view (k_v = 1)")
    model, stats = fit_sh(stack, light_order, view_order, quantize, energy_factor=energy_factor, space=space,
                          smoothness=smoothness)
    k_l, k_v = model.k_l, model.k_v
    n_samples = stack.n_light * stack.n_view
    if n_samples < k_l * k_v:
        ctx.warn(f"fewer samples ({stack.n_light} lights x {stack.n_view} views = {n_samples}) than coefficients "
                 f"({k_v} x {k_l} = {k_v * k_l}): the fit is underdetermined and the energy constraint picks the "
                 "solution; lower the orders for a fit determined by the data")
    elif stats["underdetermined"]:
        ctx.warn(f"the light/view directions determine only {stats['rank']} of {k_v * k_l} coefficients "
                 f"({stack.n_light} lights for {k_l} light coefficients, {stack.n_view} views for {k_v} view "
                 "coefficients, or directions that are nearly coincident): the energy constraint picks the rest")
    ctx.note("compression_rate_percent", round(stats["compression_rate_percent"], 2))
    ctx.note("lambda_median", stats["lambda_median"])
    ctx.note("lambda_max", stats["lambda_max"])
    ctx.note("clamped", stats["clamped"])
    ctx.note("clamped_fraction", round(stats["clamped_fraction"], 4))
    ctx.note("view_order", stats["view_order"])
    ctx.note("rank", stats["rank"])
    ctx.note("space", stats["space"])
    ctx.note("light_order", stats["light_order"])
    ctx.note("smoothness", stats["smoothness"])
    if stats["held_out_errors"]:
        ctx.note("held_out_mse", {key: float(f"{value:.4g}") for key, value in stats["held_out_errors"].items()})
    return {"model": model}


def _settle_choices(stack, params):
    """``auto`` order, space and smoothness judged once on a grid of texels of the whole stack, so every band of
    a streamed or distributed fit uses the settings the whole-stack fit would choose."""
    from .model import resolve_choices
    if "auto" not in (params["light_order"], params["space"], params["smoothness"]):
        return params
    view_order = 1 if stack.n_view == 1 else params["view_order"]
    order, space, smoothness, _ = resolve_choices(stack, params["light_order"], view_order, params["space"],
                                                  params["smoothness"], "opencl", params["energy_factor"])
    return {**params, "light_order": order, "space": space, "smoothness": smoothness}


@hookimpl
def btforge_stages():
    return [sh_fit]


@hookimpl
def btforge_buffer_types():
    return [SHModel]
