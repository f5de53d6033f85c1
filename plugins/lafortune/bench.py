"""``btforge bench lafortune``: Lafortune fit time, convergence, held-out PSNR and normal error on glossy bumps."""
from __future__ import annotations

import argparse
import dataclasses
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
    opts = parser.parse_args(args)
    from btforge.buffers import SampleStack
    from btforge.plugins.relight import compare_stacks

    from .model import estimate_normals, fit_lafortune
    stack, truth = glossy_bumps(opts.size, opts.lights)
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
    fit_lafortune(SampleStack(fit.samples[:, :, :4, :4], fit.lights, fit.views), 1)   # kernel builds, untimed
    print(f"glossy bumps {opts.size} x {opts.size}, {fit.n_light} fitting / {test.n_light} held-out lights")
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
        fit_lafortune(SampleStack(fit.samples[:, :, :4, :4], fit.lights, fit.views), lobes)
        for name, stack_fit in fits.items():
            times = []
            for _ in range(max(1, opts.repeat)):
                start = time.perf_counter()
                model, info = fit_lafortune(stack_fit, lobes)
                times.append(time.perf_counter() - start)
            relit = SampleStack(model.evaluate(test.lights), test.lights, test.views, model.channels)
            print(f"  {lobes} lobe(s), {name} ({stack_fit.n_light} lights): fit {statistics.median(times):.3f} s "
                  f"(median of {len(times)}), {100 * info['not_converged'] / info['texels']:.2f} % at the "
                  f"iteration limit ({info['iteration_limit']}), {info['iterations']:.1f} steps per texel, "
                  f"held-out PSNR {compare_stacks(relit, test)['psnr_db']:.2f} dB")
    return 0


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
