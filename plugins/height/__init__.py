"""Height fields: the ``HeightField`` buffer, height from shading (Liu, Yu & Shum 2001) and its files.

Stages: ``height.from_shading`` (a stack -> a HeightField and the robust sample weights), ``height.write_normals``
(PNG / EXR normal map) and ``height.write`` (EXR height image, PLY mesh with UVs).  ``btforge info`` describes
the PLY meshes (the EXR images are described by stackio's reader).
"""
from __future__ import annotations

import numpy as np

from btforge import REQUIRED, Param, SampleStack, declare_stage, hookimpl
from btforge.errors import BtforgeInputError

from . import io as height_io
from .field import HeightField

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


@declare_stage(
    "height.from_shading",
    inputs={"stack": "SampleStack"},
    outputs={"height": "HeightField", "weights": "SampleStack"},
    params=[
        Param("iterations", "int", 100, "at most this many conjugate-gradient iterations per round (a round "
              "stops earlier once the energy fell by less than 1e-4 of itself over 10 iterations)", low=1,
              high=100000),
        Param("smoothness", "float", 0.01, "lambda: weight of the edge-weighted second-difference smoothness "
              "of the heights, relative to the mean data term", low=0.0),
        Param("albedo_smoothness", "float", 0.01, "gamma: weight of the second-difference smoothness of the "
              "albedo", low=0.0),
        Param("robust", "bool", True, "weight samples by Tukey's biweight of their Lambertian residual, so "
              "shadows and highlights drop out; false: weight 1 wherever the surface faces the light"),
        Param("init", "choice", "photometric_stereo", "start from heights integrated out of robust photometric "
              "stereo, or from a flat field", choices=("photometric_stereo", "flat")),
        Param("rounds", "int", 2, "solves, each followed by re-estimating the robust weights", low=1, high=20),
    ],
)
def from_shading(ctx, stack, *, iterations, smoothness, albedo_smoothness, robust, init, rounds):
    """Recover a height field and its albedo from a stack by the modified Leclerc-Bobick method.

    Minimises, over per-texel heights and grey albedo, the energy of Liu, Yu & Shum (2001, eq. 5): the squared
    Lambertian residual ``rho (n . l_k) - I_k`` of every sample, times its robust weight, plus ``smoothness`` x
    the squared second differences of the heights (weaker at strong intensity edges of the inputs) plus
    ``albedo_smoothness`` x those of the albedo.  Conjugate gradients on OpenCL; the start is robust photometric
    stereo (Tukey-reweighted least squares) integrated to heights.  Every view and light of the stack is one
    sample (the stack's images are in the texture frame, as a rectified BTF's are).  The colour albedo is fitted
    per channel at the end.

    Outputs
    -------
    height : HeightField
        Heights in texel widths (mean 0), albedo, normals of the heights and the final sample weights.
    weights : SampleStack
        The weights in [0, 1] as a one-channel stack on the input's views and lights (0 = shadow or highlight).
    """
    from .sfs import recover_height
    if stack.height < 3 or stack.width < 3:
        raise BtforgeInputError("height.from_shading 'stack'", f"expected at least 3 x 3 texels, found "
                                f"{stack.height} x {stack.width}", "crop a larger region")
    if stack.n_view * stack.n_light < 3:
        raise BtforgeInputError("height.from_shading 'stack'", f"expected at least 3 images, found "
                                f"{stack.n_view * stack.n_light}", "capture under more lights")
    linear = stack.linear()
    images = linear.reshape((-1,) + linear.shape[2:])
    lights = np.tile(stack.lights, (stack.n_view, 1))
    rec = recover_height(images, lights, iterations=iterations, smoothness=smoothness,
                         albedo_smoothness=albedo_smoothness, robust=robust, init=init, rounds=rounds)
    weights_hwk = np.ascontiguousarray(np.moveaxis(rec.weights, 0, -1))
    field = HeightField.from_height(rec.height, rec.albedo, weights=weights_hwk, channels=stack.channels)
    per_sample = rec.weights.reshape(stack.n_view, stack.n_light, stack.height, stack.width, 1)
    ctx.note("rounds", rec.notes["rounds"])
    ctx.note("outlier_fraction", round(float((rec.weights < 0.5).mean()), 4))
    ctx.note("height_range", [round(float(rec.height.min()), 3), round(float(rec.height.max()), 3)])
    weights = SampleStack(np.ascontiguousarray(per_sample, np.float32), stack.lights, stack.views, channels=("W",),
                          names=stack.names)
    return {"height": field, "weights": weights}


@declare_stage("height.write_normals", deprecated_names=("normals.write",), inputs={"height": "HeightField"},
               params=[Param("path", "outpath", REQUIRED, "the .png (8-bit) or .exr (float) file to write")],
               side_effects=True)
def normals_write(ctx, height, *, path):
    """Write a height field's normal map.

    ``.png``: 8-bit RGB ``(n + 1) / 2``, +y up the image (the OpenGL convention: green = up).  ``.exr``: float32
    channels R, G, B = x, y, z of the unit normal in the texture frame (x along columns, y up, z out).
    """
    height_io.suffix_of(path, height_io.NORMAL_FORMATS, "height.write_normals 'path'")
    height_io.write_normals(height, ctx.paths.output(path))
    return {}


@declare_stage("height.write", inputs={"height": "HeightField"},
               params=[Param("path", "outpath", REQUIRED, "the .exr image or .ply mesh to write")],
               side_effects=True)
def height_write(ctx, height, *, path):
    """Write a height field: ``.exr`` = channel Y, the height in texel widths; ``.ply`` = a triangle mesh.

    The mesh has one vertex per texel centre at ``(col - (W-1)/2, (H-1)/2 - row, height)`` (texel widths) with
    UVs ``u`` along the columns and ``v`` up the rows, so ``render.image`` can load it (scale it in the scene).
    """
    height_io.suffix_of(path, height_io.HEIGHT_FORMATS, "height.write 'path'")
    height_io.write_height(height, ctx.paths.output(path))
    return {}


@hookimpl
def btforge_buffer_types():
    return [HeightField]


@hookimpl
def btforge_stages():
    return [from_shading, normals_write, height_write]


@hookimpl
def btforge_info_readers():
    return {".ply": height_io.describe_ply}
