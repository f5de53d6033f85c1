"""Polynomial texture maps: fit on OpenCL, read and write HP ``.ptm`` files."""
from __future__ import annotations

import json
from pathlib import Path

from btforge import REQUIRED, Expect, Fact, Param, declare_stage, hookimpl
from btforge.errors import BtforgeInputError

from btforge.plugins.stackio import light_file_precheck

from .model import DEFAULT_RCOND, PTMModel, fit_ptm

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for

SELECT_ONE_VIEW = ("a PTM depends on the light only: insert `pick: {stage: stackio.select, params: {views: [0]}, "
                   "inputs: {stack: NODE.PORT}}` and wire this input to pick.stack (or pick a view by its angles, "
                   "views: ['tv0_pv0']), or fit a view-dependent representation such as sh.fit or lafortune.fit")
PTM_FILE_SPACE = ("a .ptm file holds display values: fit with `space: srgb`, or leave `space: auto` (the default), "
                  "which then fits srgb for this writer; save a linear model with models.write or web.export")
MODEL_SPACE = {"model": {"space": "space"}}  # the model's colour space is the fit's `space`: ptm.write checks it
POOR_CONDITION = 100.0  # above this the fit is still unique, but noticeably noise-sensitive

FIT_PARAMS = (
    Param("variant", "choice", "rgb", "rgb: 6 coefficients per channel; lrgb: 6 luminance coefficients + a colour",
          choices=("rgb", "lrgb")),
    Param("space", "choice", "auto", "what the polynomial fits: linear radiance, or sRGB display values as "
          ".ptm files hold; auto: for an 8-bit capture the one that predicts held-out lights of a sample of "
          "texels better, linear otherwise", choices=("auto", "linear", "srgb")),
    Param("basis", "choice", "raw", "raw: the PTM terms (lu^2, lv^2, lu*lv, lu, lv, 1); orthonormal: 2D Legendre "
          "functions over [-1, 1]^2, where coefficient distance equals function distance", choices=("raw", "orthonormal")),
    Param("rcond", "float", DEFAULT_RCOND, "singular values of the light design matrix below rcond x the largest are "
          "dropped (regularises ill-conditioned light sets)", low=1e-12, high=1.0),
    Param("ridge", "any", "auto", "weight of a ridge penalty lambda |c|^2 on the coefficients, lambda = ridge x the "
          "largest squared singular value of the light design matrix (a number in [0, 1]; 0: plain least squares); "
          "auto: the weight (0 or 1e-4 to 1e-2) whose fits best predict each light left out, judged in closed form "
          "on a grid of texels"),
)


@declare_stage(
    "ptm.fit",
    role="fit",
    version="2",
    sweep=[{"variant": v} for v in ("lrgb", "rgb")],
    inputs={"stack": "SampleStack"},
    outputs={"model": "PTMModel"},
    params=list(FIT_PARAMS),
    per_texel=True,
    settle=lambda inputs, params: _settle_space(inputs["stack"], params),
    device=True,
    expects={"stack": Expect("views", 1, SELECT_ONE_VIEW)},
    facts_from_params=MODEL_SPACE,
)
def ptm_fit(ctx, stack, *, variant, space, basis, rcond, ridge):
    """Fit a polynomial texture map to a single-view stack by least squares, on OpenCL.

    Each texel's samples are mapped to coefficients by one shared 6 x L pseudo-inverse of the light design
    matrix.  The kernel reads an 8-bit capture in place (bytes as numbers for display values, through a table
    for linear radiance) and writes straight into the result.  Fed by ``stackio.read`` with no other node reading
    the stack, the fit runs band by band of rows and the capture is never held whole (``space: auto`` is decided
    first, on a grid of texels of the whole capture).  A light set whose
    design matrix is ill-conditioned (clustered, one elevation, grazing) is regularised by dropping small
    singular values (the minimum-norm solution), with a warning naming the condition number.  ``ridge`` adds a
    penalty ``lambda |c|^2`` on the coefficients; ``auto`` (the default) weighs it by how well the fits predict each
    light left out of a grid of texels (closed-form leave-one-out, ``btforge.fitspace``), and is decided with the
    space, before the bands are fitted.  The notes give ``space`` and ``ridge``.

    Outputs
    -------
    model : PTMModel
        ``[H, W, K, 6]`` coefficients in the order (lu^2, lv^2, lu*lv, lu, lv, 1).
    """
    model, solver = fit_ptm(stack, variant, space, rcond=rcond, ridge=ridge, output_array=ctx.output_array)
    return {"model": _report_fit(ctx, model.with_basis(basis), solver, rcond)}


def _settle_space(stack, params):
    """``space: auto`` and ``ridge: auto`` judged once on a grid of texels of the whole stack, so every band of a
    streamed or distributed fit fits as the whole-stack fit would."""
    from .model import check_ridge, ptm_settings
    if "auto" not in (params["space"], params["ridge"]) or stack.n_view != 1:  # multi-view: refused by the fit
        return params
    check_ridge(params["ridge"])
    space, ridge = ptm_settings(stack, params["variant"], params["space"], params["ridge"], rcond=params["rcond"])
    return {**params, "space": space, "ridge": ridge}


def _report_fit(ctx, model, solver, rcond):
    ctx.note("condition_number", round(solver.condition_number, 3))
    ctx.note("space", model.space)
    ctx.note("ridge", solver.ridge)
    if solver.clamped:
        ctx.warn(f"light directions are ill-conditioned for a PTM (condition number {solver.condition_number:.3g}); "
                 f"{solver.clamped} singular value(s) below {rcond:g} x the largest were clamped to zero weight "
                 "(the coefficient combination they govern is left at zero)")
    elif solver.condition_number > POOR_CONDITION:
        ctx.warn(f"light directions are poorly conditioned for a PTM (condition number {solver.condition_number:.3g}): "
                 "noise in the samples is amplified up to that factor; lights at more elevations would help")
    return model


def _capture_precheck(params, paths):
    from btforge.store import is_store
    if is_store(paths.input(params["path"])):
        raise BtforgeInputError(f"param 'path' ({params['path']})", "is a chunked store, not a light file",
                                "read a store with stackio.read and fit it with ptm.fit")
    found = light_file_precheck(params, paths)
    for fact in (f for f in found if isinstance(f, Fact) and f.name == "views" and f.value != 1):
        raise BtforgeInputError(f"param 'path' ({params['path']})", f"expected a single-view capture (a PTM depends "
                                f"on the light only), found {fact.value} views", "read it with stackio.read and pick one "
                                "view with stackio.select before ptm.fit")
    return found


@declare_stage(
    "ptm.fit_capture",
    version="2",
    outputs={"model": "PTMModel"},
    params=[Param("path", "path", REQUIRED, "the capture's .lp light file (a single view)"),
            Param("transfer", "choice", "auto", "how pixel values map to radiance, as in stackio.read",
                  choices=("auto", "srgb", "linear")),
            *FIT_PARAMS],
    precheck=_capture_precheck,
    device=True,
    facts_from_params=MODEL_SPACE,
)
def ptm_fit_capture(ctx, *, path, transfer, variant, space, basis, rcond, ridge):
    """Fit a PTM to a capture while its images decode, never holding the capture or a file of it.

    ``stackio.read`` -> ``ptm.fit`` streams too (band by band of a file the images are decoded into), and is what
    to use; this stage skips the file, for captures larger than the disk space a decoded copy needs.

    The fit is linear in the samples, so images are decoded into two 8 MB batches in turn: while one decodes,
    the other is projected onto the light set's pseudo-inverse on OpenCL and added onto the sums of the lights
    before it, in light order.  Images decode two at a time (simplejpeg for JPEG where installed, else Pillow).  The
    model equals ``ptm.fit`` of ``stackio.read`` with the same parameters (the same regularised estimator; for
    rgb the same float operations in the same order).  For a 1024 x 1024, 49-light JPEG capture the whole
    process peaks near the size of the coefficients plus the interpreter (README, Benchmarks).
    """
    from .model import fit_ptm_capture
    model, solver = fit_ptm_capture(ctx.paths.input(path), variant, space, transfer=transfer, rcond=rcond,
                                    ridge=ridge)
    ctx.note("lights", int(solver.solve.shape[1]))
    return {"model": _report_fit(ctx, model.with_basis(basis), solver, rcond)}


@declare_stage("ptm.basis", inputs={"model": "PTMModel"}, outputs={"model": "PTMModel"},
               keeps_facts={"model": "model"},  # the same functions in other coordinates: the same space
               params=[Param("basis", "choice", "orthonormal", "the basis to express the coefficients in",
                             choices=("raw", "orthonormal"))])
def ptm_basis(ctx, model, *, basis):
    """Re-express PTM coefficients in the raw PTM terms or the orthonormal 2D Legendre basis, and back.

    The reflectance functions do not change (relighting gives the same images); only the coordinates do.  In
    the orthonormal basis (Hel-Or, Malzbender & Gelb 2003) the Euclidean distance between two texels'
    coefficient vectors equals the L2 distance between their functions over [-1, 1]^2, so synthesis can
    compare and blend texels directly.  The colour of an ``lrgb`` model stays as it is.
    """
    return {"model": model.with_basis(basis)}


def _ptm_file_precheck(params, paths):
    from .ptmfile import describe_ptm
    path = paths.input(params["path"])
    if _is_web_layout(path):
        files = _web_reader().precheck(params, paths)  # checks the layout; its info.json comes first
        kind = json.loads(Path(files[0]).read_text(encoding="utf-8"))["type"]
        if kind != "ptm":
            raise BtforgeInputError(str(path), f"holds a {kind} model, not a PTM", "read it with stage web.read")
        return files
    describe_ptm(path)
    return [path]


def _web_reader():
    """The installed ``web.read`` stage, which reads relight's web layout; found through the registry, as the web
    family builds on this one (it exports and views PTMs)."""
    from btforge.registry import default_registry
    return default_registry().stage("web.read")


def _is_web_layout(path) -> bool:
    """relight's web layout: its info.json, or the folder holding one."""
    return path.suffix.lower() == ".json" or (path.is_dir() and (path / "info.json").is_file())


@declare_stage("ptm.read", outputs={"model": "PTMModel"},
               params=[Param("path", "path", REQUIRED, "the .ptm file (PTM_1.2: LRGB, RGB or JPEG_LRGB), or a "
                             "PTM in relight's web layout (its info.json or folder)")],
               precheck=_ptm_file_precheck)
def ptm_read(ctx, *, path):
    """Read an HP ``.ptm`` file (PTM_FORMAT_LRGB, PTM_FORMAT_RGB, or PTM_FORMAT_JPEG_LRGB with plane prediction),
    or a PTM in relight's web layout (``info.json`` with its coefficient planes, as OpenLIME reads it).

    The model's ``space`` is ``srgb``: PTM files hold display values, decoded to linear when relit.
    """
    from .ptmfile import read_ptm
    if _is_web_layout(ctx.paths.input(path)):
        ctx.note("file_format", "relight web layout")
        return {"model": _web_reader()(ctx=ctx, path=path)["model"]}
    content = read_ptm(ctx.paths.input(path))
    ctx.note("file_format", content.file_format)
    albedo = content.albedo if content.albedo is not None else content.coeffs[..., :0, 0]
    return {"model": PTMModel(content.coeffs, albedo.astype("float32"), content.variant, "srgb")}


@declare_stage("ptm.write", inputs={"model": "PTMModel"},
               params=[Param("path", "outpath", REQUIRED, "the .ptm file to write (relative paths land under --out)")],
               side_effects=True, expects={"model": Expect("space", "srgb", PTM_FILE_SPACE)})
def ptm_write(ctx, model, *, path):
    """Write a PTM as an HP ``.ptm`` file (raw PTM_FORMAT_LRGB or PTM_FORMAT_RGB, 8 bits per coefficient).

    Each coefficient gets the scale and bias that make its whole range representable, and values are rounded,
    so a write/read round trip changes no relit pixel by more than one 8-bit step.  Only ``srgb``-space models
    can be written: the file format has no colour space and viewers show the values as display values.  A
    ``ptm.fit`` left at ``space: auto`` that feeds this stage fits ``srgb`` (the graph check narrows its choice and
    the run report says so); one given ``space: linear`` is refused by the check, before anything runs.
    """
    from .ptmfile import write_ptm
    if model.space != "srgb":
        raise BtforgeInputError("ptm.write 'model'", "expected a PTM of sRGB display values (space: srgb), found a "
                                "linear one", PTM_FILE_SPACE)
    if len(model.channel_names) != 3:
        raise BtforgeInputError("ptm.write 'model'", f"expected 3 colour channels, found {len(model.channel_names)}")
    target = ctx.paths.output(path)
    model = model.with_basis("raw")
    write_ptm(target, model.variant, model.coeffs, model.albedo if model.variant == "lrgb" else None)
    ctx.note("written", str(target))
    return {}


def _describe_ptm(path):
    from .ptmfile import describe_ptm
    info = describe_ptm(path)
    expected, found = info.get("expected_size_bytes"), info.get("size_bytes")
    if expected is not None and found is not None and expected != found:
        raise BtforgeInputError(str(path), f"the header promises {expected} bytes, the file has {found}",
                                "the file is truncated or has trailing data; export it again")
    return info


@hookimpl
def btforge_stages():
    return [ptm_fit, ptm_fit_capture, ptm_basis, ptm_read, ptm_write]


@hookimpl
def btforge_buffer_types():
    return [PTMModel]


@hookimpl
def btforge_info_readers():
    return {".ptm": _describe_ptm}


@hookimpl
def btforge_bench_commands():
    from .bench import bench_ptm
    from .bench_stream import bench_ptm_stream
    return {"ptm": bench_ptm, "ptm-stream": bench_ptm_stream}
