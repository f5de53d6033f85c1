"""``btforge bench lafortune``: Lafortune fit time, convergence, held-out PSNR and normal error on glossy bumps.

The fit time is that of the whole ``lafortune.fit`` stage call - photometric-stereo normals, the host's layout
of samples and geometry, the OpenCL fit and the read-back of the model - with its kernels built beforehand: what
``btforge bench representations`` times for every fit.  ``--save DIR`` writes the capture (float EXR and
``lights.lp``) so that ``btforge bench representations --stack DIR/lights.lp --only lafortune`` measures the
same fits on the same 48 lights (both hold out every fifth light).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import time

import numpy as np


def glossy_bumps(size: int, n_lights: int, seed: int = 3):
    """A top-view capture of the procedural bumps (bump height 3 texels) with cast shadows: Lambert plus a
    Blinn-Phong lobe ``0.6 (n . h)^40`` - the material of ``demo.btf`` seen from above.  Returns the linear
    stack and the true normals ``[H, W, 3]``."""
    from btforge.buffers import SampleStack
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights
    material = make_material(size, size, bump_height=3.0, seed=seed)
    lights = hemisphere_lights(n_lights, min_elevation_deg=15.0)
    white = dataclasses.replace(material, albedo=np.ones_like(material.albedo))
    lit = render_lights(white, lights)[..., 0]                               # max(n . l, 0) x visibility
    half = lights + [0.0, 0.0, 1.0]
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    gloss = 0.6 * np.clip(np.einsum("hwc,lc->lhw", material.normals, half), 0.0, 1.0) ** 40
    radiance = lit[..., None] * (material.albedo[None] + gloss[..., None])
    stack = SampleStack(radiance[None].astype(np.float32), lights, np.array([[0.0, 0.0, 1.0]]))
    return stack, material.normals


def bench_lafortune(args: list[str]) -> int:
    """Lafortune fit on glossy bumps: seconds, texels at the iteration limit, held-out PSNR, normal error."""
    parser = argparse.ArgumentParser(prog="btforge bench lafortune", description=bench_lafortune.__doc__)
    parser.add_argument("--size", type=int, default=128, help="capture side in texels (default 128)")
    parser.add_argument("--lights", type=int, default=60, help="lights; every fifth is held out (default 60: 48 fit)")
    parser.add_argument("--lobes", type=int, nargs="+", default=[1, 2], help="lobe counts to fit (default 1 2)")
    parser.add_argument("--repeat", type=int, default=3, help="fits per lobe count; medians are reported")
    parser.add_argument("--uneven", action="store_true", help="sample half the dome (azimuth 180-360 degrees) 3x "
                        "more sparsely, and also fit with images interpolated between its neighbouring lights")
    parser.add_argument("--save", metavar="DIR", help="also write the capture (all lights, float EXR + lights.lp) "
                        "for `btforge bench representations --stack DIR/lights.lp`")
    opts = parser.parse_args(args)
    from btforge.buffers import SampleStack
    from btforge.plugins.relight import compare_stacks

    from .normals import estimate_normals
    stack, truth = glossy_bumps(opts.size, opts.lights)
    if opts.save:
        from btforge.plugins.stackio.images import write_stack
        write_stack(stack, opts.save)
    held = np.arange(stack.n_light) % 5 == 0
    keep = ~held
    if opts.uneven:
        azimuth = np.degrees(np.arctan2(stack.lights[:, 1], stack.lights[:, 0])) % 360
        keep &= (azimuth < 180) | (np.arange(stack.n_light) % 3 == 0)

    def part(mask):
        return SampleStack(np.ascontiguousarray(stack.samples[:, mask]), stack.lights[mask], stack.views)
    fit, test = part(keep), part(held)
    fits = {"measured": fit}
    if opts.uneven:
        fits["+ interpolated"] = with_interpolated_images(fit, azimuth[keep] >= 180)
    print(f"glossy bumps {opts.size} x {opts.size}, {fit.n_light} fitting / {test.n_light} held-out lights; "
          f"load average {os.getloadavg()[0]:.1f}; fit = the whole lafortune.fit stage call (normals included, kernel "
          "builds not), wall and CPU (this process and its OpenCL threads)")
    start = time.perf_counter()
    normals = estimate_normals(fit)
    error = np.degrees(np.arccos(np.clip((normals * truth).sum(-1), -1.0, 1.0)))
    lum = fit.linear()[0].mean(axis=-1).reshape(fit.n_light, -1)
    plain = np.linalg.lstsq(fit.lights, lum, rcond=None)[0].T.reshape(truth.shape)
    plain /= np.linalg.norm(plain, axis=-1, keepdims=True)
    plain_error = np.degrees(np.arccos(np.clip((plain * truth).sum(-1), -1.0, 1.0)))
    print(f"  normals (robust photometric stereo): {time.perf_counter() - start:.3f} s, "
          f"error mean {error.mean():.2f} deg, 95th percentile {np.percentile(error, 95):.2f} deg "
          f"(plain least squares: mean {plain_error.mean():.2f} deg)")
    for lobes in opts.lobes:
        fit_stage(SampleStack(fit.samples[:, :, :4, :4], fit.lights, fit.views), lobes)   # kernel builds, untimed
        for name, stack_fit in fits.items():
            walls, cpus = [], []
            for _ in range(max(1, opts.repeat)):
                start, cpu = time.perf_counter(), time.process_time()
                model, notes = fit_stage(stack_fit, lobes)
                walls.append(time.perf_counter() - start)
                cpus.append(time.process_time() - cpu)
            relit = SampleStack(model.evaluate(test.lights), test.lights, test.views, model.channels)
            texels = model.height * model.width
            print(f"  {lobes} lobe(s), {name} ({stack_fit.n_light} lights): fit {statistics.median(walls):.3f} s "
                  f"wall, {statistics.median(cpus):.3f} s CPU (medians of {len(walls)}), "
                  f"{100 * notes['not_converged'] / texels:.2f} % at the iteration limit, "
                  f"{notes['iterations']:.1f} steps per texel, "
                  f"held-out PSNR {compare_stacks(relit, test)['psnr_db']:.2f} dB")
    return 0


def fit_stage(stack, lobes: int):
    """Call the ``lafortune.fit`` stage as a graph node would: ``(model, notes)``."""
    import warnings

    from btforge.context import StageContext

    from . import lafortune_fit
    ctx = StageContext(node="lafortune.fit")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # the not-converged warning: its count is printed
        model = lafortune_fit(ctx, stack=stack, lobes=lobes)["model"]
    return model, ctx.notes


def with_interpolated_images(stack, sparse: np.ndarray):
    """``stack`` plus, for each light flagged ``sparse``, a virtual image at the normalised mid-direction to
    its nearest light: the mean of the two images (Bosserhoff & Nicoll's remedy for uneven sampling)."""
    from btforge.buffers import SampleStack
    closeness = stack.lights @ stack.lights.T
    np.fill_diagonal(closeness, -2.0)
    nearest = closeness.argmax(axis=1)[sparse]
    chosen = np.flatnonzero(sparse)
    mid = stack.lights[chosen] + stack.lights[nearest]
    images = 0.5 * (stack.samples[:, chosen] + stack.samples[:, nearest])
    return SampleStack(np.ascontiguousarray(np.concatenate([stack.samples, images], axis=1), np.float32),
                       np.vstack([stack.lights, mid / np.linalg.norm(mid, axis=1, keepdims=True)]), stack.views)
