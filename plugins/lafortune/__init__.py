"""Per-texel Lafortune lobes fitted by Levenberg-Marquardt on OpenCL (Bosserhoff & Nicoll; McAllister et al.)."""
from __future__ import annotations

from btforge import Param, declare_stage, hookimpl

from .model import DEFAULT_ITERATIONS, MAX_LOBES, LafortuneModel, fit_lafortune
from .normals import estimate_normals

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for

__all__ = ["LafortuneModel", "estimate_normals", "fit_lafortune"]

NOT_CONVERGED_WARN = 0.05  # warn when more than this fraction of texels ran out of iterations


@declare_stage(
    "lafortune.fit",
    role="fit",
    sweep=[{"lobes": k} for k in (1, 2, 3, 4)],
    inputs={"stack": "SampleStack"},
    outputs={"model": "LafortuneModel"},
    device=True,
    per_texel=True,          # each texel's normal, scale and lobes come from its own samples alone
    params=[
        Param("lobes", "int", 0, "lobes per fitted signal: on the luminance (variant lum, 1 to 7) or on each "
              "channel (variant rgb, 1 or 2); 0: 1 for lum, 2 per channel for rgb", low=0, high=MAX_LOBES),
        Param("variant", "choice", "lum", "lum: lobes on the channel mean times a per-texel colour; rgb: each channel "
              "its own diffuse term and lobes", choices=("lum", "rgb")),
        Param("iterations", "int", DEFAULT_ITERATIONS, "Levenberg-Marquardt steps allowed per added lobe and start",
              low=1, high=10000),
    ],
)
def lafortune_fit(ctx, stack, *, lobes, variant, iterations):
    """Fit per-texel Lafortune lobes to a stack (top view or multi-view BTF) by Levenberg-Marquardt, on OpenCL.

    Each texel gets its own frame: a normal from robust photometric stereo on its samples (least squares with
    the darkest and the brightest 30 % dropped, with any samples tied to them, then Tukey-reweighted least
    squares over every sample that is lit and not saturated, so shadows and highlights lose their pull while
    few lights keep all their clean samples; the order of the lights does not matter; ``(0, 0, 1)`` for black
    or constant texels or normals within 3 degrees of the surface plane)
    and the surface x-axis made orthogonal to it as tangent.  In that frame the model is::

        radiance = max(uz, 0) * (rho_d + sum_i max(Cx_i ux vx + Cy_i uy vy + Cz_i uz vz, 0) ^ n_i)

    with ``u``, ``v`` the light and view in the texel frame: a BRDF times the cosine foreshortening, so
    ``rho_d`` carries the Lambertian shading and every lobe is free for gloss.  ``lum`` multiplies the result by
    a per-texel colour (non-negative least squares per channel); ``rgb`` fits each channel on its own.

    One OpenCL work-item fits one texel (and channel, for rgb): lobes are added one at a time, each started
    from the best-scoring of a grid of mirror / retro / normal-aligned shapes at exponents 1 ... 768 (the
    first lobe races two starts), then all parameters are refined by Levenberg-Marquardt: Cholesky-solved
    damped normal equations, trust-region (gain-ratio) damping, steps kept inside the parameter bounds, and a
    Newton-decrement stop after which the texel's work-item retires.  A lobe is kept only if it lowers the
    texel's error, so more lobes never fit worse.  Exponents stay in [1, 1000], a negative lobe base counts as
    0 (no negative number is raised to a fractional power), and no lobe may peak above 10x (the first) or 2x
    (later lobes) the texel's brightest sample in any direction, which keeps relighting between the measured
    lights bounded.  Each texel is fitted scaled to a peak near 1 (by a power of two) and scaled back, so
    the fit does not depend on the data's overall brightness.  The stack is streamed in bands of rows.

    Inputs
    ------
    stack : SampleStack
        Any light (and view) set with at least 1 + 4 x lobes samples per texel; 8-bit stacks are fitted in
        linear radiance.

    Outputs
    -------
    model : LafortuneModel
        ``normals [H, W, 3]``, ``diffuse [H, W, 1 or C]``, ``lobes [H, W, K, 3]`` (Cx, Cy, Cz; for rgb ``K = 2C``,
        channel-major, the second of each channel switched off, ``C = 0``, for ``lobes`` 1), ``exponents [H, W, K]``,
        ``colour [H, W, C]`` (lum).  Relight it with ``relight.images``.

    Notes
    -----
    ``not_converged``: texels whose kept fit used up ``iterations`` (they keep their best iterate); ``rms``:
    root-mean-square error over all samples and channels, linear radiance; ``iterations``: mean steps per texel.
    """
    model, info = fit_lafortune(stack, lobes or None, variant, iterations=iterations)
    ctx.note("not_converged", info["not_converged"])
    ctx.note("rms", float(f"{info['rms']:.6g}"))
    ctx.note("iterations", round(info["iterations"], 2))
    if info["texels"] and info["not_converged"] > NOT_CONVERGED_WARN * info["texels"]:
        ctx.warn(f"{info['not_converged']} of {info['texels']} texels did not converge within {iterations} "
                 "iterations (they keep their best fit); raise 'iterations' for a closer fit")
    return {"model": model}


@hookimpl
def btforge_stages():
    return [lafortune_fit]


@hookimpl
def btforge_buffer_types():
    return [LafortuneModel]


@hookimpl
def btforge_bench_commands():
    from .bench import bench_lafortune
    return {"lafortune": bench_lafortune}
