"""BTF synthesis on a height field (Liu, Yu & Shum 2001, sec. 6): for every target (view, light), a template is
rendered from the height field, the nearest reference images are warped to the target and block-copied under the
template's guidance, and the results are blended with eq. 8's weights.

Images are written one at a time into preallocated output arrays, so the working set beyond the output is that
of one target setting (the references it uses, their block indexes and one template).
"""
from __future__ import annotations

import concurrent.futures
import dataclasses
import os
import time

import numpy as np

from . import blockcopy, settings, template

_WORKERS = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


@dataclasses.dataclass(frozen=True)
class Choice:
    """The references of one target: indices into the flattened references, eq. 8 weights, warps."""

    indices: np.ndarray
    distances: np.ndarray
    weights: np.ndarray
    rotations: np.ndarray
    mirrored: np.ndarray


def choose_references(view, light, ref_views, ref_lights, count: int, isotropic: bool) -> Choice:
    """The ``count`` references nearest to the target by eq. 7 (``isotropic``) or eq. 6, with their warps."""
    if isotropic:
        d, r, m = settings.isotropic_match(view, light, ref_views, ref_lights)
    else:
        d = settings.distance(view, light, ref_views, ref_lights)
        r, m = np.zeros_like(d), np.zeros(d.shape, bool)
    order = np.argsort(d, kind="stable")[:count]
    return Choice(order, d[order], settings.blend_weights(d[order]), r[order], m[order])


def grey_albedo(field) -> np.ndarray:
    """The height field's albedo as grey, scaled to mean 1 (the template only needs relative shading)."""
    grey = field.albedo.mean(axis=2)
    return (grey / max(float(grey.mean()), 1e-6)).astype(np.float32)


def reference_table(references):
    """Flattened ``(views [N, 3], lights [N, 3], (v, l) pairs [N, 2])`` of a reference stack."""
    pairs = np.array([(v, l) for v in range(references.n_view) for l in range(references.n_light)])
    return references.views[pairs[:, 0]], references.lights[pairs[:, 1]], pairs


def synthesize_image(template_image, references, choice: Choice, pairs, block_sizes, seed, engine="fast",
                     feather=blockcopy.FEATHER, relax=blockcopy.RELAX, colour=blockcopy.COLOUR):
    """One target image ``[H, W, C]``: block copy from each chosen reference, blended with eq. 8's weights.

    The references' block copies are independent (each has its own seed) and, with the ``fast`` engine, run on
    a thread each, up to the number of cores (with one reference, its block indexes are built on threads): the
    k-d tree builds and searches and the large array operations release the GIL.
    """
    def copy(i):
        v, l = pairs[choice.indices[i]]
        warped, valid = blockcopy.warp(references.image(v, l), float(choice.rotations[i]), bool(choice.mirrored[i]),
                                       template_image.shape)
        return blockcopy.block_copy(template_image, warped, valid, block_sizes, seed=seed + 7919 * i, engine=engine,
                                    threads=_WORKERS if count == 1 else 1, feather=feather,
                                    relax=relax, colour=colour)
    count = len(choice.indices)
    if count > 1 and _WORKERS > 1 and engine == "fast":   # (the exact engine's OpenCL kernels are not shared)
        with concurrent.futures.ThreadPoolExecutor(min(count, _WORKERS)) as pool:
            results = list(pool.map(copy, range(count)))
    else:
        results = [copy(i) for i in range(count)]
    out = np.zeros(template_image.shape + (references.n_channel,), np.float64)
    for weight, result in zip(choice.weights, results):
        out += weight * result.image
    return out.astype(np.float32), [(r.blocks, r.hole_pixels) for r in results]


def first_equal(directions: np.ndarray, tolerance: float = 1e-6) -> np.ndarray:
    """For each row, the index of the first row equal to it (itself when it is the first)."""
    d = np.asarray(directions, np.float64)
    close = np.abs(d[:, None] - d[None]).max(-1) <= tolerance
    return close.argmax(1)


def synthesize(field, references, views, lights, *, isotropic=True, count=3, block_sizes=(3, 5, 9), seed=0,
               out=None, templates_out=None, progress=None, feather=blockcopy.FEATHER, relax=blockcopy.RELAX,
               colour=blockcopy.COLOUR):
    """The BTF ``[V, L, H, W, C]`` and templates ``[V, L, H, W, 1]`` of ``field`` on the grid ``views x lights``.

    ``out`` / ``templates_out`` may be given (e.g. memory-mapped arrays) to receive the images.
    """
    V, L, (H, W) = len(views), len(lights), field.heights.shape
    C = references.n_channel
    out = np.empty((V, L, H, W, C), np.float32) if out is None else out
    templates_out = np.empty((V, L, H, W, 1), np.float32) if templates_out is None else templates_out
    ref_views, ref_lights, pairs = reference_table(references)
    count = min(count, len(pairs))
    albedo = grey_albedo(field)
    seconds = {"templates": 0.0, "synthesis": 0.0}
    blocks = holes = 0
    first_view, first_light = first_equal(views), first_equal(lights)
    for v in range(V):
        if first_view[v] != v:  # the same direction again (a tilt-0 row of a tilt x azimuth grid): same images
            out[v], templates_out[v] = out[first_view[v]], templates_out[first_view[v]]
            continue
        start = time.perf_counter()
        distinct = np.flatnonzero(first_light == np.arange(L))     # a repeated light's template is rendered once
        images, _ = template.render(field.heights, albedo, field.normals, np.repeat(views[v:v + 1], len(distinct), 0),
                                    lights[distinct])
        images = images[np.searchsorted(distinct, first_light)]
        seconds["templates"] += time.perf_counter() - start
        templates_out[v, ..., 0] = images
        for l in range(L):
            if first_light[l] != l:
                out[v, l] = out[v, first_light[l]]
                continue
            start = time.perf_counter()
            choice = choose_references(views[v], lights[l], ref_views, ref_lights, count, isotropic)
            out[v, l], stats = synthesize_image(images[l], references, choice, pairs, block_sizes,
                                                seed + 104729 * (v * L + l), feather=feather, relax=relax,
                                                colour=colour)
            seconds["synthesis"] += time.perf_counter() - start
            blocks += sum(s[0] for s in stats)
            holes += sum(s[1] for s in stats)
            if progress is not None:
                progress(v, l)
    return out, templates_out, {"seconds": seconds, "blocks": blocks, "hole_pixels": holes}
