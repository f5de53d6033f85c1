"""Models on the web: relight's layout (info.json + coefficient planes, as OpenLIME reads it), HSH ``.rti``
files, and ``btforge view``, a relighting page of our own."""
from __future__ import annotations

from pathlib import Path

from btforge import REQUIRED, Param, declare_stage, hookimpl
from btforge.errors import BtforgeInputError

from .hsh import HSHModel, read_rti
from .layout import describe_web, read_info, read_web, write_web

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


@declare_stage(
    "web.export", deprecated_names=("model.export_web",),
    inputs={"model": "ReflectanceModel"},
    params=[
        Param("dir", "outpath", REQUIRED, "folder for info.json and the plane images (relative to --out)"),
        Param("format", "choice", "png", "png: exact up to 8 bits; jpg: smaller, lossy (as relight's default; "
              "OpenLIME loads only jpg)",
              choices=("png", "jpg")),
        Param("quality", "int", 95, "JPEG quality", low=1, high=100),
    ],
    side_effects=True,
)
def export_web(ctx, model, *, dir, format, quality):
    """Write a PTM (rgb, lrgb), an SH model (light order <= 3), an HSH model, an ``hsh.fit`` / ``rbf.fit`` /
    ``bilinear.fit`` model or a ``neural.fit`` model in relight's web layout.

    ``info.json`` with the basis, colour space and a scale and bias per coefficient plane, and the planes packed
    three to a PNG or JPEG, as ``btforge view`` reads them (OpenLIME's ``image`` layout loads only JPEG planes:
    use ``format: jpg`` for it, and an rgb PTM, since its lrgb shader darkens the colour); ``rbf`` and
    ``bilinear`` add their light table (``basis``, 8 bits) and its lights or grid resolution.  Every plane's
    scale and bias cover its whole range, so with PNG the export is exact up to 8-bit rounding (relight's
    exporter clips at a quantile).
    Models of linear radiance (fitted in ``space: linear``, or ``auto`` choosing it) are marked ``"btforge":
    {"transfer": "linear"}``; models of display values are written as they are, as relight writes them.

    A ``neural.fit`` model is written as OpenLIME's neural layer reads it (``"type": "neural"``): its latent
    codes as 8-bit images ``plane_1 ..`` (three codes each, ``min`` / ``max`` per image covering the whole range)
    and the decoder's weights in info.json.  OpenLIME opens those of NeuralRTI's network (``decoder: light``,
    ``light_order: 0``, ``latent: 9``, ``layers: 2``) exported as ``format: jpg``; ``btforge view`` and
    ``web.read`` open every neural export, the harmonics decoder's too.
    """
    written = write_web(model, ctx.paths.output(dir), format, quality)
    ctx.note("files", len(written))
    ctx.note("written", str(ctx.paths.output(dir)))
    return {}


def _model_precheck(params, paths):
    path = paths.input(params["path"])
    if path.suffix.lower() == ".rti":
        if not path.is_file():
            raise BtforgeInputError(str(path), "file not found")
        return [path]
    info = read_info(path)
    folder = Path(info["_folder"])
    return [folder / "info.json"] + sorted(folder.glob(f"plane_*.{info.get('format', 'jpg')}"))


@declare_stage("web.read", outputs={"model": "ReflectanceModel"},
               params=[Param("path", "path", REQUIRED, "a web layout (its folder or info.json: ptm, hsh, sh, rbf, "
                             "bilinear or neural) "
                             "or an HSH .rti file")],
               precheck=_model_precheck)
def web_read(ctx, *, path):
    """Read a model saved for viewers: relight's web layout (PTM, HSH, SH, RBF, bilinear, neural) or an RTIBuilder
    HSH ``.rti`` file.

    Outputs
    -------
    model : ReflectanceModel
        A PTMModel, HSHModel, SHModel, LightTableModel (rbf, bilinear) or NeuralModel; PTM, HSH, RBF, bilinear
        and neural layouts hold display values (``space: srgb``).
    """
    target = ctx.paths.input(path)
    model = read_rti(target) if target.suffix.lower() == ".rti" else read_web(target)
    ctx.note("type", model.type_name)
    ctx.note("size", [model.height, model.width])
    return {"model": model}


def _describe_rti(path):
    model = read_rti(path)
    return {"kind": "HSH .rti file", "size": [model.width, model.height], "terms": model.coeffs.shape[3],
            "bands": model.coeffs.shape[2]}


@hookimpl
def btforge_stages():
    return [export_web, web_read]


@hookimpl
def btforge_buffer_types():
    return [HSHModel]


@hookimpl
def btforge_cli_commands():
    from .server import view_arguments, view_run
    return {"view": (view_arguments, view_run)}


@hookimpl
def btforge_bench_commands():
    from .bench import bench_web
    return {"web": bench_web}


@hookimpl
def btforge_info_readers():
    return {".rti": _describe_rti, ".json": describe_web}
