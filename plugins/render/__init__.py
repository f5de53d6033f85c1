"""Rendering reflectance textures on meshes: scenes, ray casting with open3d, models evaluated on OpenCL.

Stages: ``render.image`` (a scene with one input port per material it names -> a linear RGB ``Image``), ``render.read_scene``
(a scene file with the meshes and maps it names -> a ``Scene``), ``render.write_image`` (EXR, PNG, GIF, MP4).
The scene format is described in README.md, section "Scene format".
"""
from __future__ import annotations

from btforge import REQUIRED, Param, declare_stage, hookimpl
from btforge.errors import BtforgeInputError

from .image import FORMATS, Image, check_writable, format_of
from .scene import RESERVED_PORTS, PORT_NAME, Scene

BTFORGE_PLUGIN_API = 1  # the btforge plugin API this plugin is written for


def _render_ports(params, paths) -> dict[str, str]:
    """One ``ReflectanceModel`` port per material the scene names (plus ``NAME_map`` CoordMap ports)."""
    from .scene import scene_ports
    if params.get("scene") is not None:
        if params.get("materials") is not None:
            raise BtforgeInputError("render 'materials'", "only applies when the scene comes through the "
                                    "'scene_data' port; with the 'scene' param the ports come from the scene",
                                    "remove 'materials'")
        return scene_ports(params["scene"], paths)
    names = params.get("materials") or []
    if not isinstance(names, list) or not all(isinstance(n, str) and PORT_NAME.match(n) for n in names):
        raise BtforgeInputError("render 'materials'", f"expected a list of material names, found {names!r}")
    bad = [n for n in names if n in RESERVED_PORTS]
    if bad:
        raise BtforgeInputError("render 'materials'", f"'{bad[0]}' cannot name a material")
    return {n: ("CoordMap" if n.endswith("_map") else "TileSet" if n.endswith("_tiles") else "ReflectanceModel")
            for n in names}


def _render_precheck(params, paths):
    from .loader import load_scene
    value = params.get("scene")
    if value is None:
        return []
    scene = load_scene(value, paths)
    files = [] if not isinstance(value, str) else [paths.input(value)]
    return files + scene.spec.files()


@declare_stage(
    "render.image", deprecated_names=("render",),
    inputs={"scene_data": "Scene"},
    optional_inputs=("scene_data",),
    outputs={"image": "Image"},
    params=[
        Param("scene", "any", None, "the scene: a YAML file path (relative to the graph) or the same as a mapping; "
              "each material it names becomes an input port taking a reflectance model"),
        Param("materials", "any", None, "only with a scene wired to 'scene_data' (from render.read_scene): the material "
              "names to take as input ports (NAME_map for coordinate maps)"),
    ],
    precheck=_render_precheck,
    dynamic_inputs=_render_ports,
    version="1",
)
def render(ctx, scene_data=None, *, scene, materials, **models):
    """Render reflectance models on meshes: ray casting with open3d, model evaluation on OpenCL.

    The renderer plans its passes from the scene's effects and content and runs nothing else (no shadow rays
    when nothing can occlude, no environment pass without an environment light, no view directions for models
    of light only).  Light and view are expressed in each texel's frame, built from the mesh's UV
    parameterization, as the model was fitted.  The report lists the passes that ran with their ray and
    evaluation counts (``passes``) and why planned effects were skipped (``skipped``).

    Inputs
    ------
    scene_data : Scene, optional
        A scene from ``render.read_scene`` instead of the ``scene`` param (then list the material ports in ``materials``).
    <material> : ReflectanceModel
        One port per material named in the scene; ``<material>_map`` (CoordMap) where a mesh sets ``coord_map``,
        ``<material>_tiles`` (TileSet) where it sets ``tiles``.

    Outputs
    -------
    image : Image
        Linear RGB ``[H, W, 3]`` float32, or ``[F, H, W, 3]`` for a light sweep or turntable.
    """
    from .renderer import Counters, render as render_scene
    from .loader import load_scene
    if (scene is None) == (scene_data is None):
        raise BtforgeInputError("render.image", "expected exactly one scene: the 'scene' param or a Scene wired to "
                                "'scene_data'", "add `params: {scene: scenes/NAME.yaml}`")
    if scene_data is None:
        scene_data = load_scene(scene, ctx.paths)
    spec = scene_data.spec
    missing = [n for n in spec.ports() if n not in models]
    if scene is None and missing:
        raise BtforgeInputError("render 'materials'", f"the scene names {', '.join(repr(m) for m in missing)}, which "
                                "the node does not take", f"add `materials: {list(spec.ports())}` to the params")
    counters = Counters()
    pixels = render_scene(scene_data, models, counters)
    ctx.note("passes", counters.passes)
    if counters.skipped:
        ctx.note("skipped", counters.skipped)
    ctx.note("size", [spec.camera.height, spec.camera.width])
    return {"image": Image(pixels, exposure=spec.exposure, tonemap="tonemap" in spec.effects,
                           fps=spec.animation.fps if spec.animation else 12.0)}


def _scene_read_precheck(params, paths):
    from .loader import load_scene
    scene = load_scene(params["path"], paths)
    return [paths.input(params["path"])] + scene.spec.files()


@declare_stage("render.read_scene", deprecated_names=("scene.read",), outputs={"scene": "Scene"},
               params=[Param("path", "path", REQUIRED, "the scene YAML file (format: README, Scene format)")],
               precheck=_scene_read_precheck)
def scene_read(ctx, *, path):
    """Read and check a scene file with the meshes and environment maps it names, into one self-contained Scene.

    Wire it to ``render.image``'s ``scene_data`` port (and list the material names in that node's ``materials``) to
    share one scene between several renders.
    """
    from .loader import load_scene
    scene = load_scene(path, ctx.paths)
    ctx.note("meshes", len(scene.spec.meshes))
    ctx.note("materials", scene.spec.materials)
    return {"scene": scene}


def _write_precheck(params, paths):
    check_writable(format_of(params["path"], params["format"]))
    return []


@declare_stage(
    "render.write_image", deprecated_names=("image.write",),
    inputs={"image": "Image"},
    params=[
        Param("path", "outpath", REQUIRED, "the file to write (relative paths land under --out); frames of an "
              "animation written as EXR or PNG get _000, _001, ... suffixes"),
        Param("format", "choice", "auto", "exr: linear float; png: 8-bit (tonemapped: exposure then sRGB, when the "
              "scene has the tonemap effect); gif / mp4: animation (mp4 needs imageio-ffmpeg or PyAV); auto: from "
              "the extension", choices=("auto",) + FORMATS),
    ],
    side_effects=True,
    precheck=_write_precheck,
)
def image_write(ctx, image, *, path, format):
    """Write a rendered image: linear EXR, tonemapped PNG, or an animated GIF / MP4 of a sweep or turntable."""
    from .image import write_image
    fmt = format_of(path, format)
    written = write_image(image, ctx.paths.output(path), fmt)
    if fmt != "exr" and image.tonemap:
        ctx.note("tonemap", {"exposure": image.exposure, "pixels": int(image.frames[..., 0].size)})
    ctx.note("written", [str(p) for p in written])
    return {}


@hookimpl
def btforge_stages():
    return [render, scene_read, image_write]


@hookimpl
def btforge_buffer_types():
    return [Image, Scene]


@hookimpl
def btforge_bench_commands():
    from .bench import bench_render
    return {"render": bench_render}
