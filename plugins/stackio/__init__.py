"""Reading and writing multi-light captures (``.lp`` / ``.lvp`` light files with PNG, JPEG, TIFF or EXR images)."""
from __future__ import annotations

import numpy as np

from btforge import REQUIRED, Fact, Param, SampleStack, declare_stage, hookimpl
from btforge.atomic import atomic_write
from btforge.buffers import linear_to_srgb8
from btforge.errors import BtforgeInputError

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


def light_file_precheck(params, paths):
    """The files a capture's reader reads, and the number of views of the stack it gives (a :class:`Fact`, so the
    graph check can tell a single-view stage it will get a BTF)."""
    from btforge.store import is_store, open_store

    from .images import group_views
    from .lightfile import image_path, is_btf_zip, is_dfmf_path, read_capture_index
    path = paths.input(params["path"])
    if is_store(path):  # the cache keys the folder by its contents
        return [path, Fact("stack", "views", open_store(path)[0].shape[0], str(path))]
    if is_dfmf_path(path):
        from .ubo2014 import read_dfmf
        # header, directions and matrix sizes checked before anything runs
        return [path, Fact("stack", "views", read_dfmf(path).n_view, str(path))]
    entries = read_capture_index(path, require_images=True)
    views = 1 if entries[0].view is None else len(group_views(entries, str(path))[1])
    files = [path] if is_btf_zip(path) else [path] + [image_path(path, e.filename) for e in entries]
    return files + [Fact("stack", "views", views, str(path))]


@declare_stage(
    "stackio.read", deprecated_names=("stack.read",),
    outputs={"stack": "SampleStack"},
    params=[
        Param("path", "path", REQUIRED, "the capture: a .lp light file (filename x y z per line after the count), "
              "a .lvp light-and-view file (filename lx ly lz vx vy vz), a UBO-style BTF folder or UBO2003 zip whose "
              "image names carry the angles (tl{theta}_pl{phi}_tv{theta}_pv{phi}), or a store made by stackio.import"),
        Param("transfer", "choice", "auto", "how pixel values map to radiance: auto (8-bit images are sRGB, "
              "16-bit and float are linear), srgb or linear", choices=("auto", "srgb", "linear")),
    ],
    precheck=light_file_precheck,
    cache_outputs=False,
    streams=("stack",),
)
def stack_read(ctx, *, path, transfer):
    """Read a multi-light (and multi-view) capture: a light file and the images it lists, or a BTF folder.

    Light directions are normalised; one a hair below the horizon (within 1 degree) is clamped with a warning;
    a bad count, a missing image, or images of different sizes are reported by line.  8-bit captures stay
    8-bit in memory (decoded to linear on use), a quarter of the float size.  A store made by ``stackio.import``
    is opened lazily: its samples are read band by band as stages need them.

    When every node reading the stack runs per texel (``ptm.fit``, ``sh.fit``, ``lafortune.fit`` ...), the
    images are decoded into a spilled file instead of memory and those nodes fit it band by band of rows, so
    the process never holds the capture (the run report notes ``streamed``; a capture under 64 MB is held all
    the same, which costs less); a node that needs the stack whole (``stackio.split``, ``relight.compare``, a
    relight) gets it in memory.
    """
    from btforge.store import is_store, open_stored_stack

    from .images import load_stack
    from .lightfile import is_dfmf_path
    source = ctx.paths.input(path)
    if is_store(source):
        stack = open_stored_stack(source)
    elif is_dfmf_path(source):
        from .importer import load_dfmf_stack
        stack = load_dfmf_stack(source)
    elif "stack" in ctx.streamed:  # every reader runs per texel: decoded into a file, fitted band by band
        from .images import load_stack_spilled
        stack = load_stack_spilled(source, transfer=transfer)
        ctx.note("streamed", stack.chunked)  # a small capture is read into memory all the same
    else:
        stack = load_stack(source, transfer=transfer)
    ctx.note("lights", stack.n_light)
    ctx.note("size", [stack.height, stack.width])
    return {"stack": stack}


@declare_stage(
    "stackio.write", deprecated_names=("stack.write",),
    inputs={"stack": "SampleStack"},
    params=[
        Param("dir", "outpath", REQUIRED, "folder for the images and their light file (relative to --out)"),
        Param("format", "choice", "exr", "exr: linear float images; png: 8-bit sRGB", choices=("exr", "png")),
        Param("half", "bool", False, "write EXR as 16-bit half floats"),
    ],
    side_effects=True,
)
def stack_write(ctx, stack, *, dir, format, half):
    """Write a stack as one image per light plus a light file listing them in light order.

    Every file is written atomically.
    """
    from .images import write_stack
    written = write_stack(stack, ctx.paths.output(dir), fmt=format, half=half)
    ctx.note("files", len(written))
    return {}


@declare_stage(
    "stackio.contact_sheet", deprecated_names=("stack.contact_sheet",),
    inputs={"stack": "SampleStack", "beside": "SampleStack"},
    optional_inputs=("beside",),
    params=[
        Param("path", "outpath", REQUIRED, "the PNG to write (relative to --out)"),
        Param("columns", "int", 8, "images per row", low=1),
        Param("exposure", "float", 1.0, "multiplier applied to linear radiance before sRGB encoding", low=0.0),
        Param("sides", "str", "fit,truth", "what the two sides of a tile are, left and right (with 'beside')"),
    ],
    side_effects=True,
)
def contact_sheet(ctx, stack, beside=None, *, path, columns, exposure, sides):
    """Write every light's image of a stack in one sRGB PNG grid, for a quick look.

    Each tile is labelled with its light (elevation and azimuth in degrees).  With a second stack wired to
    ``beside`` (e.g. the measured images at the same lights), each tile shows the two side by side: ``stack``
    left, ``beside`` right, as the header says (``sides`` names them), and each label adds the tile's PSNR
    (display values for 8-bit captures, as ``relight.compare`` measures).
    """
    from btforge.plot import labelled_grid, light_label
    from .compare import compare_stacks
    if beside is not None and beside.samples.shape[:4] != stack.samples.shape[:4]:
        raise BtforgeInputError("stackio.contact_sheet 'beside'", f"expected the shape of 'stack' {stack.samples.shape[:4]}, "
                                f"found {beside.samples.shape[:4]}")
    n = stack.n_view * stack.n_light
    tiles, labels = [], []
    scores = compare_stacks(stack, beside, per_light=True)["psnr_db_per_light"] if beside is not None else None
    for i in range(n):
        v, l = divmod(i, stack.n_light)
        parts = [stack.image(v, l)] + ([beside.image(v, l)] if beside is not None else [])
        tile = np.concatenate([p if p.shape[2] == 3 else np.repeat(p[..., :1], 3, axis=2) for p in parts], axis=1)
        tiles.append(linear_to_srgb8(tile * exposure))
        label = f"{l + 1} {light_label(stack.lights[l])}"
        labels.append(label + (f" {scores[l]:.1f} dB" if scores is not None else ""))
    names = [s.strip() for s in sides.split(",")] + ["beside"]
    header = f"left: {names[0]}, right: {names[1]}; per tile: light, elevation, azimuth, PSNR" if beside is not None \
        else ""
    sheet = labelled_grid(tiles, labels, min(columns, n), header)
    target = ctx.paths.output(path)
    with atomic_write(target) as handle:
        sheet.save(handle, format="PNG", compress_level=1)  # large sheets: speed over size
    ctx.note("written", str(target))
    return {}


@declare_stage(
    "stackio.split", deprecated_names=("stack.split",),
    inputs={"stack": "SampleStack"},
    outputs={"fit": "SampleStack", "test": "SampleStack"},
    params=[Param("every", "int", 5, "hold out every N-th light (the 1st, (N+1)-th, ...) as the test set", low=2)],
)
def stack_split(ctx, stack, *, every):
    """Split a stack's lights into a fitting set and a held-out test set (every N-th light)."""
    held = np.zeros(stack.n_light, bool)
    held[::every] = True
    if held.sum() == 0 or (~held).sum() == 0:
        raise BtforgeInputError("stackio.split", f"expected lights on both sides of the split, found {stack.n_light} lights",
                                "use a smaller 'every'")

    def part(mask):
        idx = np.flatnonzero(mask)
        names = tuple(stack.names[i] for i in idx) if stack.names else ()
        return SampleStack(stack.take(range(stack.n_view), idx), stack.lights[idx], stack.views, stack.channels,
                           stack.encoding, names)

    ctx.note("fit_lights", int((~held).sum()))
    ctx.note("test_lights", int(held.sum()))
    return {"fit": part(~held), "test": part(held)}


@declare_stage(
    "stackio.import", deprecated_names=("stack.import",),
    outputs={"stack": "SampleStack"},
    params=[
        Param("path", "path", REQUIRED, "the capture: a .lp/.lvp light file, a Bonn UBO2003 BTF as a zip archive "
              "or unpacked folder (image names carry the angles, tl15_pl0_tv30_pv120.jpg), or a Bonn UBO2014 .btf "
              "file (DFMF: per-channel SVD factors, decoded to linear float32 radiance)"),
        Param("store", "outpath", REQUIRED, "the zarr v3 store to write, conventionally NAME.zarr (relative paths "
              "land under --out); an existing store there is replaced"),
        Param("block", "ints", (32, 32), "texels per chunk [rows, columns]: each chunk holds all samples of one "
              "block", length=2, low=1, high=4096),
        Param("transfer", "choice", "auto", "how pixel values map to radiance, as in stackio.read",
              choices=("auto", "srgb", "linear")),
    ],
    precheck=light_file_precheck,
    side_effects=True,
)
def stack_import(ctx, *, path, store, block, transfer):
    """Convert a capture once into a chunked, compressed store (zarr v3) that stackio.read opens later.

    Every chunk holds all samples (views x lights x channels) of a block of texels, as per-texel fits need
    them, Zstandard-compressed.  Images decode in parallel a batch at a time into a temporary file beside the
    store, which is then rewritten band by band into chunks: memory stays at a batch plus a band.  A UBO2014
    ``.btf`` (DFMF) is decoded chunk by chunk from its memory-mapped factors into linear float32 radiance (a
    chunk is views x lights x block x 3 floats: 151 x 151 directions and [16, 16] texels make 70 MB).  The output
    is the stack read lazily from the store (as ``stackio.read`` of the store gives it).  ``btforge info
    NAME.zarr`` describes a store.
    """
    from btforge.store import open_stored_stack

    from .importer import import_capture
    target = ctx.paths.output(store)
    array = import_capture(ctx.paths.input(path), target, transfer=transfer, block=tuple(block))
    ctx.note("written", str(target))
    ctx.note("chunk", list(array.chunks))
    return {"stack": open_stored_stack(target)}


def _selection_precheck(params, paths):
    from .select import check_selection
    for name in ("views", "lights"):
        check_selection(params[name], f"param '{name}'")
    views = params["views"]
    return [Fact("stack", "views", len(views), "param 'views'")] if views else []


@declare_stage(
    "stackio.select", deprecated_names=("stack.select",),
    inputs={"stack": "SampleStack"},
    outputs={"stack": "SampleStack"},
    params=[
        Param("views", "any", (), "views to keep, in this order: 0-based indices or angle names like 'tv30_pv90' "
              "(degrees from the zenith, azimuth); [] keeps all"),
        Param("lights", "any", (), "lights to keep, in this order: 0-based indices, image names ('light_003.jpg') "
              "or angle names like 'tl45_pl120'; [] keeps all"),
    ],
    precheck=_selection_precheck,
    keeps_facts={"stack": "stack"},  # views: [] keeps every view: the input's count still holds
)
def stack_select(ctx, stack, *, views, lights):
    """Keep some views and lights of a stack, by index or by name, in the order given.

    Use it to fit a single-view representation (a PTM) to one view of a BTF, or to hold lights out.  A name
    is matched exactly against the image names, or as angles (``tl45_pl120``, ``tv30_pv90``, in degrees) to the
    direction within 0.75 degrees (names round to whole degrees); unknown or ambiguous names and out-of-range
    indices are all reported at once.
    """
    from .select import check_selection, select
    for name, value in (("views", views), ("lights", lights)):
        check_selection(value, f"stackio.select '{name}'")
    picked = select(stack, views, lights)
    ctx.note("views", picked.n_view)
    ctx.note("lights", picked.n_light)
    return {"stack": picked}


def _describe_light_file(path):
    from .lightfile import read_light_file
    entries = read_light_file(path, require_images=True)  # a missing image is reported here, not at run time
    lights = np.array([e.light for e in entries])
    elevation = np.degrees(np.arcsin(np.clip(lights[:, 2], -1, 1)))
    return {"kind": "light file", "images": len(entries), "lights": len({e.light for e in entries}),
            "views": len({e.view for e in entries}),
            "elevation_deg": [round(float(elevation.min()), 2), round(float(elevation.max()), 2)],
            "first": entries[0].filename if entries else None}


def _describe_dfmf(path):
    from .ubo2014 import read_dfmf
    return read_dfmf(path).summary()


def _describe_exr(path):
    from .images import read_exr
    pixels = read_exr(path)
    return {"kind": "OpenEXR image", "shape": list(pixels.shape), "dtype": str(pixels.dtype),
            "min": float(np.min(pixels)), "max": float(np.max(pixels))}


@hookimpl
def btforge_stages():
    return [stack_read, stack_import, stack_write, contact_sheet, stack_split, stack_select]


@hookimpl
def btforge_buffer_types():
    from btforge.store import StoredSampleStack
    return [StoredSampleStack]


@hookimpl
def btforge_info_readers():
    from btforge.store import store_summary
    return {".lp": _describe_light_file, ".lvp": _describe_light_file, ".exr": _describe_exr, ".zarr": store_summary,
            ".btf": _describe_dfmf}


@hookimpl
def btforge_bench_commands():
    from .bench import bench_btf_store
    return {"btf-store": bench_btf_store}
