"""Relighting: evaluate any reflectance model at new lights."""
from __future__ import annotations

import numpy as np

from btforge import Param, SampleStack, declare_stage, hookimpl
from btforge.buffers import Scores
from btforge.errors import BtforgeInputError
from btforge.plugins.stackio.compare import compare_stacks

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


def resolve_lights(value, paths, param: str = "lights", role: str = "light") -> tuple[np.ndarray, tuple[str, ...]]:
    """Directions from a list of [x, y, z] or a ``.lp`` file: unit ``[L, 3]`` float32 and per-row names.

    ``param`` names the parameter in messages (``"views"`` for view directions, with ``role="view"``).
    """
    from btforge.plugins.stackio.lightfile import parse_light_list, read_light_file
    if isinstance(value, str):
        entries = read_light_file(paths.input(value), require_images=False)
        return np.array([e.light for e in entries], np.float32), tuple(e.filename for e in entries)
    return parse_light_list(value, name=f"param '{param}'", role=role), ()


@declare_stage(
    "relight.images", deprecated_names=("relight",),
    inputs={"model": "ReflectanceModel", "at": "SampleStack"},
    optional_inputs=("at",),
    outputs={"stack": "SampleStack"},
    params=[Param("lights", "lights", None, "light directions (toward the light, z up) as [[x, y, z], ...] or a .lp "
                  "file; leave out to relight at the lights of the stack wired to 'at'"),
            Param("views", "lights", None, "view directions (toward the camera) as [[x, y, z], ...] for view-dependent "
                  "models; default: the stack wired to 'at', else straight above [0, 0, 1]")],
)
def relight(ctx, model, at=None, *, lights, views):
    """Evaluate a reflectance model (PTM, and any other representation) at the given lights.

    Inputs
    ------
    model : ReflectanceModel
        Any fitted representation.
    at : SampleStack, optional
        Relight at this stack's lights (e.g. held-out lights of a capture) instead of the ``lights`` param.

    Outputs
    -------
    stack : SampleStack
        Linear radiance ``[views, lights, H, W, C]``, named after the light file's entries when there is one.
    """
    if lights is None and at is None:
        raise BtforgeInputError("relight.images", "expected the 'lights' param or a stack wired to input 'at', found neither",
                                "add `params: {lights: [[0, 0, 1]]}` or `inputs: {at: NODE.stack}`")
    if lights is not None:
        directions, names = resolve_lights(lights, ctx.paths)
    else:
        directions, names = at.lights, at.names
    if views is not None:
        view_dirs, _ = resolve_lights(views, ctx.paths, "views", "view")
    elif at is not None:
        view_dirs = at.views
    else:
        view_dirs = np.array([[0.0, 0.0, 1.0]], np.float32)
    values = model.evaluate(directions, view_dirs)
    if values.shape[0] != len(view_dirs):  # a model of the light only looks the same from every view
        values = np.broadcast_to(values, (len(view_dirs),) + values.shape[1:])
    return {"stack": SampleStack(np.ascontiguousarray(values), directions, view_dirs, model.channels, names=names)}


@declare_stage("relight.compare", deprecated_names=("stack.compare",), inputs={"stack": "SampleStack", "reference": "SampleStack"},
               outputs={"scores": "Scores"},
               params=[Param("peak", "float", 1.0, "the signal peak for PSNR (1.0 for images in [0, 1])", low=1e-9)])
def stack_compare(ctx, stack, reference, *, peak):
    """Compare a predicted stack with a measured one at the same lights: PSNR (dB) overall, of the worst and the
    median light, RMSE and max error.

    Errors are computed on display values (sRGB-encoded, clipped to [0, 1]) when the reference is an 8-bit
    capture, so the figures match what RTI tools report; on linear values otherwise.
    """
    if stack.samples.shape[:2] != reference.samples.shape[:2] or stack.samples.shape[2:] != reference.samples.shape[2:]:
        raise BtforgeInputError("relight.compare", f"expected stacks of equal shape, found {stack.samples.shape} and "
                                f"{reference.samples.shape}", "relight at the reference's lights (wire it to relight's 'at')")
    if not np.allclose(stack.lights, reference.lights, atol=1e-4):
        raise BtforgeInputError("relight.compare", "expected the same light directions in both stacks",
                                "relight at the reference's lights (wire it to relight's 'at')")
    scores = compare_stacks(stack, reference, peak)
    for key, value in scores.items():
        ctx.note(key, value)
    return {"scores": Scores(scores)}


@hookimpl
def btforge_stages():
    return [relight, stack_compare]


@hookimpl
def btforge_bench_commands():
    from .bench import bench_representations_command
    return {"representations": bench_representations_command}
