"""Saved models: any reflectance model written to and read from one documented, lossless file format (``.btfm``)."""
from __future__ import annotations

from btforge import REQUIRED, Param, declare_stage, hookimpl

from .modelfile import SUFFIX, describe_model, read_manifest, read_model, write_model

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for

__all__ = ["read_model", "write_model", "describe_model"]


@declare_stage(
    "models.write", deprecated_names=("model.write",),
    inputs={"model": "ReflectanceModel"},
    params=[Param("path", "outpath", REQUIRED, f"the model file to write, conventionally {SUFFIX} (relative paths "
                  "land under --out)")],
    side_effects=True,
)
def model_write(ctx, model, *, path):
    """Save any reflectance model (PTM, SH, Lafortune, ...) losslessly in the btforge model file format.

    The file is a ZIP of a JSON manifest - the representation's name, its parameters, the format version and a
    checksum per array - and one ``.npy`` per array, bit for bit as fitted (quantized SH keeps its 8-bit planes
    with their scale and bias).  The format is documented in ``plugins/models/modelfile.py`` and the README;
    ``btforge info FILE`` shows a saved model.  The file is written atomically.
    """
    target = ctx.paths.output(path)
    manifest = write_model(target, model)
    ctx.note("written", str(target))
    ctx.note("representation", manifest["representation"])
    return {}


def _model_file_precheck(params, paths):
    path = paths.input(params["path"])
    read_manifest(path)
    return [path]


@declare_stage(
    "models.read", deprecated_names=("model.read",),
    outputs={"model": "ReflectanceModel"},
    params=[Param("path", "path", REQUIRED, f"a model file written by models.write ({SUFFIX})")],
    precheck=_model_file_precheck,
)
def model_read(ctx, *, path):
    """Read a model saved by ``models.write``: the same representation, parameters and arrays, exactly.

    A file of a format version this btforge does not read, of a representation no installed plugin defines, or
    whose arrays fail their checksums is refused with the reason.  The output port is typed
    ``ReflectanceModel``: wire it into stages that take any model (relight, render, synthesis).
    """
    from btforge.registry import default_registry
    model = read_model(ctx.paths.input(path), default_registry().types)
    ctx.note("representation", model.type_name)
    return {"model": model}


@hookimpl
def btforge_stages():
    return [model_write, model_read]


@hookimpl
def btforge_info_readers():
    return {SUFFIX: describe_model}
