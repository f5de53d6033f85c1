"""Scene files: parsing and validating a scene (YAML or a mapping) into plain specs, and the ``Scene`` buffer.

Everything a user can get wrong in a scene is reported here, with the key path at fault (``meshes.ground.material``),
before anything renders: :func:`parse_scene` checks the structure and values; :func:`btforge.plugins.render.loader.load_scene`
also reads the files it names (meshes, environment maps).  The format is documented in docs/guide/rendering.md.
"""
from __future__ import annotations

import dataclasses
import math
import os
import re
from pathlib import Path
from typing import Any, ClassVar, Mapping

import numpy as np
import yaml

from btforge.buffers import Buffer, freeze_fields
from btforge.errors import BtforgeInputError
from btforge.registry import did_you_mean

EFFECTS = ("shadows", "environment", "view_dependence", "tonemap", "antialias")
PRIMITIVES = ("plane", "sphere", "torus", "cube")
CLOSED_PRIMITIVES = ("sphere", "torus", "cube")
CONVEX_PRIMITIVES = ("plane", "sphere", "cube")  # cannot shadow themselves (a torus can)
MESH_EXTENSIONS = (".ply", ".obj")
WRAPS = ("repeat", "clamp", "mirror")
ENV_METHODS = ("importance", "sh")
MAX_SH_ORDER = 6
RESERVED_PORTS = ("scene", "scene_data", "materials")
PORT_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")

TOP_KEYS = ("description", "camera", "meshes", "lights", "effects", "exposure", "background", "animation")
CAMERA_KEYS = ("type", "width", "height", "position", "look_at", "up", "fov", "extent", "samples")
MESH_KEYS = ("primitive", "file", "size", "radius", "major_radius", "minor_radius", "segments", "position", "rotate",
             "scale", "material", "uv_scale", "uv_offset", "wrap", "coord_map", "color", "tiles")
LIGHT_KEYS = {
    "directional": ("type", "direction", "intensity"),
    "point": ("type", "position", "intensity"),
    "environment": ("type", "file", "sky", "intensity", "method", "samples", "order", "rotate", "up", "forward"),
}
MIN_SEGMENTS = {"plane": (1, 1), "sphere": (3, 2), "torus": (3, 3)}  # fewer cannot enclose (or span) the shape
SKY_KEYS = ("zenith", "horizon", "ground", "sun", "sun_intensity", "sun_size", "width")
ANIMATION_KEYS = ("type", "frames", "degrees", "light", "axis", "fps")
ANIMATIONS = ("light_sweep", "turntable")


# ----------------------------------------------------------------------------------------------- specs


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    kind: str
    width: int
    height: int
    position: tuple[float, float, float]
    look_at: tuple[float, float, float]
    up: tuple[float, float, float]
    fov: float          # perspective: vertical field of view, degrees
    extent: float       # orthographic: height of the view in world units
    samples: int        # samples per pixel when the antialias effect is on


@dataclasses.dataclass(frozen=True)
class MeshSpec:
    name: str
    primitive: str | None
    file: str | None          # absolute path
    size: tuple[float, float]
    radius: float
    major_radius: float
    minor_radius: float
    segments: tuple[int, int] | None
    position: tuple[float, float, float]
    rotate: tuple[float, float, float]
    scale: tuple[float, float, float]
    material: str | None
    uv_scale: tuple[float, float]
    uv_offset: tuple[float, float]
    wrap: str
    coord_map: bool
    color: tuple[float, float, float]
    tiles: bool = False       # the material is looked up through a Wang TileSet (port NAME_tiles)

    @property
    def closed(self) -> bool:
        return self.primitive in CLOSED_PRIMITIVES

    @property
    def convex(self) -> bool:
        return self.primitive in CONVEX_PRIMITIVES


@dataclasses.dataclass(frozen=True)
class LightSpec:
    index: int
    kind: str
    intensity: tuple[float, float, float]
    direction: tuple[float, float, float] | None = None  # unit, toward the light
    position: tuple[float, float, float] | None = None
    file: str | None = None                                 # environment: absolute path of a lat-long EXR
    sky: Mapping[str, Any] | None = None                    # environment: procedural sky instead of a file
    method: str = "importance"
    samples: int = 64
    order: int = 3
    rotate: float = 0.0
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)        # environment: the map's top row (zenith)
    forward: tuple[float, float, float] = (1.0, 0.0, 0.0)   # environment: where the map's left edge faces


@dataclasses.dataclass(frozen=True)
class AnimationSpec:
    kind: str
    frames: int
    degrees: float
    light: int
    axis: tuple[float, float, float]
    fps: float


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    source: str
    camera: CameraSpec
    meshes: tuple[MeshSpec, ...]
    lights: tuple[LightSpec, ...]
    effects: frozenset[str]
    exposure: float
    background: tuple[float, float, float] | str
    animation: AnimationSpec | None

    @property
    def materials(self) -> list[str]:
        """Material names (graph input ports), in order of first use."""
        names: list[str] = []
        for m in self.meshes:
            if m.material and m.material not in names:
                names.append(m.material)
        return names

    @property
    def coord_mapped(self) -> list[str]:
        return [name for name in self.materials if any(m.material == name and m.coord_map for m in self.meshes)]

    @property
    def tiled(self) -> list[str]:
        return [name for name in self.materials if any(m.material == name and m.tiles for m in self.meshes)]

    def ports(self) -> dict[str, str]:
        """Input ports of a ``render.image`` node for this scene: one per material, plus ``NAME_map`` for coordinate maps
        and ``NAME_tiles`` for Wang tile sets."""
        ports = {name: "ReflectanceModel" for name in self.materials}
        ports.update({f"{name}_map": "CoordMap" for name in self.coord_mapped})
        ports.update({f"{name}_tiles": "TileSet" for name in self.tiled})
        return ports

    def files(self) -> list[Path]:
        out = [Path(m.file) for m in self.meshes if m.file]
        out += [Path(l.file) for l in self.lights if l.file]
        return out


# ----------------------------------------------------------------------------------------------- value checks


INLINE = "<inline>"   # the source name of a scene given as a mapping in the graph


class _Where:
    """Builds messages that name the scene and the key path at fault."""

    def __init__(self, source: str):
        self.source = source

    def error(self, key: str, problem: str, hint: str | None = None) -> BtforgeInputError:
        return BtforgeInputError(f"scene {self.source}" + (f", {key}" if key else ""), problem, hint)

    def mapping(self, value: Any, key: str, allowed: tuple[str, ...]) -> Mapping[str, Any]:
        if not isinstance(value, Mapping):
            raise self.error(key, f"expected a mapping, found {type(value).__name__}")
        for k in value:
            if k not in allowed:
                raise self.error(f"{key}.{k}" if key else str(k), "unknown key", did_you_mean(str(k), allowed))
        return value

    def file(self, value: Any, key: str, base_dir: Path, check_files: bool, suffixes: tuple[str, ...],
             expected: str, noun: str) -> str:
        """A file the scene names: its absolute path, resolved and checked to exist when ``check_files``.

        Relative paths resolve against ``base_dir``: the scene file's folder, or the graph's for an inline scene.
        """
        if not isinstance(value, str) or not value:
            raise self.error(key, f"expected a file path, found {value!r}")
        path = Path(os.path.expanduser(value))
        path = path if path.is_absolute() else base_dir / path
        if path.suffix.lower() not in suffixes:
            raise self.error(key, f"expected {expected}, found '{path.name}'")
        if not check_files:
            return str(path)
        if not path.is_file():
            raise self.error(key, f"{noun} not found: {path}",
                             "paths in an inline scene are relative to the graph file's folder"
                             if self.source == INLINE else
                             "paths in a scene file are relative to the scene file's folder")
        return str(path.resolve())

    def number(self, value: Any, key: str, *, low: float | None = None, high: float | None = None,
               low_open: bool = False) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.error(key, f"expected a finite number, found {value!r}")
        if low is not None and (value < low or (low_open and value == low)):
            raise self.error(key, f"expected a number {'>' if low_open else '>='} {low:g}, found {value!r}")
        if high is not None and value > high:
            raise self.error(key, f"expected a number <= {high:g}, found {value!r}")
        return float(value)

    def integer(self, value: Any, key: str, *, low: int = 1, high: int | None = None) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, found {value!r}")
        if value < low or (high is not None and value > high):
            bound = f"in [{low}, {high}]" if high is not None else f">= {low}"
            raise self.error(key, f"expected an integer {bound}, found {value!r}")
        return value

    def vector(self, value: Any, key: str, n: int = 3, *, low: float | None = None) -> tuple[float, ...]:
        if (isinstance(value, (list, tuple)) and len(value) == n
                and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            if not all(math.isfinite(v) for v in value):
                raise self.error(key, f"expected finite values, found {list(value)!r}", "NaN and Inf are not directions")
            if low is not None and any(v < low for v in value):
                raise self.error(key, f"expected values >= {low:g}, found {list(value)!r}")
            return tuple(float(v) for v in value)
        raise self.error(key, f"expected a list of {n} numbers, found {value!r}")

    def direction(self, value: Any, key: str) -> tuple[float, float, float]:
        v = np.array(self.vector(value, key), dtype=np.float64)
        norm = float(np.linalg.norm(v))
        if norm < 1e-9:
            raise self.error(key, f"expected a non-zero direction, found {list(value)!r}",
                             "give the direction toward the light, e.g. [0, 0, 1]")
        return tuple(float(x) for x in v / norm)

    def colour(self, value: Any, key: str) -> tuple[float, float, float]:
        """A non-negative intensity or colour: a number (grey) or [r, g, b]."""
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            v = self.number(value, key)
            if v < 0:
                raise self.error(key, f"expected a non-negative intensity, found {value!r}",
                                 "a light cannot take energy away; use 0 to switch it off")
            return (v, v, v)
        rgb = self.vector(value, key)
        if any(c < 0 for c in rgb):
            raise self.error(key, f"expected non-negative values, found {list(value)!r}",
                             "a light cannot take energy away; use 0 to switch it off")
        return rgb

    def pair(self, value: Any, key: str, *, positive: bool = False, default=None) -> tuple[float, float]:
        if value is None:
            return default
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value, value]
        out = self.vector(value, key, 2)
        if positive and min(out) <= 0:
            raise self.error(key, f"expected positive values, found {list(out)!r}")
        return out

    def choice(self, value: Any, key: str, choices: tuple[str, ...]) -> str:
        if value not in choices:
            raise self.error(key, f"expected one of {', '.join(choices)}, found {value!r}",
                             did_you_mean(str(value), choices))
        return value


# ----------------------------------------------------------------------------------------------- parsing


def read_scene_source(value: Any, paths) -> tuple[Mapping[str, Any], str, Path]:
    """The raw scene mapping, a name for messages, and the folder its relative paths resolve against."""
    if isinstance(value, Mapping):
        return value, INLINE, Path(paths.graph_dir)
    if not isinstance(value, (str, os.PathLike)) or str(value) == "":
        raise BtforgeInputError("render 'scene'", f"expected a scene file path or a mapping, found {value!r}")
    path = paths.input(str(value))
    if not path.is_file():
        raise BtforgeInputError(f"scene {path}", "scene file not found", "paths are relative to the graph file's folder")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise BtforgeInputError(f"scene {path}", f"is not UTF-8 text (byte {exc.start} cannot be decoded)",
                                "save the scene as UTF-8 YAML") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"scene {path}" + (f", line {mark.line + 1}" if mark else "")
        raise BtforgeInputError(where, f"is not valid YAML: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(data, Mapping):
        raise BtforgeInputError(f"scene {path}", f"expected a mapping at the top, found {type(data).__name__}",
                                "see the Scene format section of README.md")
    return data, str(path), path.parent


def parse_scene(data: Mapping[str, Any], source: str, base_dir: Path, check_files: bool = True) -> SceneSpec:
    """Check a raw scene mapping and return its spec; relative file paths resolve against ``base_dir``.

    ``check_files=False`` skips checking that named files exist (a :class:`Scene` holds their contents).
    """
    w = _Where(source)
    w.mapping(data, "", TOP_KEYS)
    if "camera" not in data:
        raise w.error("camera", "is missing", "add e.g. camera: {type: perspective, width: 640, height: 480, "
                      "position: [0, 0, 5], look_at: [0, 0, 0]}")
    camera = _parse_camera(w, data["camera"])
    meshes_raw = data.get("meshes")
    if not isinstance(meshes_raw, Mapping) or not meshes_raw:
        raise w.error("meshes", f"expected a non-empty mapping of named meshes, found {meshes_raw!r}",
                      "add e.g. meshes: {ground: {primitive: plane, size: 2.0, material: stone}}")
    meshes = tuple(_parse_mesh(w, str(name), body, base_dir, check_files) for name, body in meshes_raw.items())
    lights_raw = data.get("lights", [])
    if not isinstance(lights_raw, list):
        raise w.error("lights", f"expected a list of lights, found {type(lights_raw).__name__}")
    lights = tuple(_parse_light(w, i, body, base_dir, check_files) for i, body in enumerate(lights_raw))

    effects_raw = data.get("effects", list(EFFECTS))
    if not isinstance(effects_raw, list) or not all(isinstance(e, str) for e in effects_raw):
        raise w.error("effects", f"expected a list of effect names, found {effects_raw!r}",
                      f"known effects: {', '.join(EFFECTS)}")
    for e in effects_raw:
        if e not in EFFECTS:
            raise w.error("effects", f"unknown effect '{e}'", did_you_mean(e, EFFECTS))
    exposure = w.number(data.get("exposure", 0.0), "exposure", low=-30, high=30)

    background = data.get("background", [0.0, 0.0, 0.0])
    if background == "environment":
        if not any(l.kind == "environment" for l in lights):
            raise w.error("background", "is 'environment' but the scene has no environment light",
                          "add a light of type environment, or give a colour [r, g, b]")
    else:
        background = w.colour(background, "background")

    animation = None
    if data.get("animation") is not None:
        animation = _parse_animation(w, data["animation"], lights)
    return SceneSpec(source, camera, meshes, lights, frozenset(effects_raw), exposure, background, animation)


def _parse_camera(w: _Where, raw: Any) -> CameraSpec:
    c = w.mapping(raw, "camera", CAMERA_KEYS)
    kind = w.choice(c.get("type", "perspective"), "camera.type", ("perspective", "orthographic"))
    width = w.integer(c.get("width", 640), "camera.width", high=16384)
    height = w.integer(c.get("height", 480), "camera.height", high=16384)
    position = w.vector(c.get("position", [0.0, 0.0, 5.0]), "camera.position")
    look_at = w.vector(c.get("look_at", [0.0, 0.0, 0.0]), "camera.look_at")
    up = w.vector(c.get("up", [0.0, 1.0, 0.0]), "camera.up")
    forward = np.subtract(look_at, position)
    if np.linalg.norm(forward) < 1e-9:
        raise w.error("camera.look_at", "equals the camera position", "look at a point away from the camera")
    if np.linalg.norm(np.cross(forward / np.linalg.norm(forward), up)) < 1e-6:
        raise w.error("camera.up", f"is parallel to the viewing direction (or zero): {list(up)!r}",
                      "give an up vector across the view, e.g. [0, 1, 0] when looking along z")
    fov = w.number(c.get("fov", 40.0), "camera.fov", low=0.0, high=179.0, low_open=True)
    extent = w.number(c.get("extent", 2.0), "camera.extent", low=0.0, low_open=True)
    samples = w.integer(c.get("samples", 4), "camera.samples", high=256)
    return CameraSpec(kind, width, height, position, look_at, up, fov, extent, samples)


def _parse_mesh(w: _Where, name: str, raw: Any, base_dir: Path, check_files: bool = True) -> MeshSpec:
    key = f"meshes.{name}"
    m = w.mapping(raw, key, MESH_KEYS)
    if ("primitive" in m) == ("file" in m):
        raise w.error(key, "expected exactly one of 'primitive' or 'file'",
                      f"primitive: one of {', '.join(PRIMITIVES)}; file: a .ply or .obj path")
    primitive, file = None, None
    if "primitive" in m:
        primitive = w.choice(m["primitive"], f"{key}.primitive", PRIMITIVES)
    else:
        file = w.file(m["file"], f"{key}.file", base_dir, check_files, MESH_EXTENSIONS, "a .ply or .obj mesh",
                      "mesh file")
    size, radius, major, minor, segments = _parse_shape(w, key, m, primitive)
    position, rotate, scale = _parse_transform(w, key, m)
    material, uv_scale, uv_offset, wrap, coord_map, color = _parse_binding(w, key, m)
    tiles = _parse_tiles(w, key, m, uv_scale, coord_map)
    return MeshSpec(name, primitive, file, size, radius, major, minor, segments, position, rotate, scale, material,
                    uv_scale, uv_offset, wrap, coord_map, color, tiles)


def _parse_shape(w: _Where, key: str, m: Mapping[str, Any], primitive: str | None):
    """A primitive's size, radii and tessellation (a mesh file takes none of them)."""
    if primitive is None:
        for k in ("size", "radius", "major_radius", "minor_radius", "segments"):
            if k in m:
                raise w.error(f"{key}.{k}", "only applies to primitives", "scale a mesh file with 'scale'")
    size = w.pair(m.get("size"), f"{key}.size", positive=True, default=(2.0, 2.0))
    if primitive == "cube" and size[0] != size[1]:
        raise w.error(f"{key}.size", "a cube takes one edge length", "use scale: [x, y, z] for a box")
    radius = w.number(m.get("radius", 1.0), f"{key}.radius", low=0.0, low_open=True)
    major = w.number(m.get("major_radius", 1.0), f"{key}.major_radius", low=0.0, low_open=True)
    minor = w.number(m.get("minor_radius", 0.3), f"{key}.minor_radius", low=0.0, low_open=True)
    if primitive == "torus" and minor >= major:
        raise w.error(f"{key}.minor_radius", f"expected less than major_radius ({major:g}), found {minor:g}",
                      "a self-intersecting torus has no consistent inside")
    return size, radius, major, minor, _parse_segments(w, key, m, primitive)


def _parse_segments(w: _Where, key: str, m: Mapping[str, Any], primitive: str | None):
    if "segments" not in m:
        return None
    if primitive == "cube":
        raise w.error(f"{key}.segments", "does not apply to a cube",
                      "a cube is six flat faces of one quad each; remove 'segments'")
    seg = m["segments"]
    seg = [seg, seg] if isinstance(seg, int) and not isinstance(seg, bool) else seg
    if not (isinstance(seg, list) and len(seg) == 2):
        raise w.error(f"{key}.segments", f"expected [n_u, n_v], found {m['segments']!r}")
    segments = (w.integer(seg[0], f"{key}.segments", high=4096), w.integer(seg[1], f"{key}.segments", high=4096))
    least = MIN_SEGMENTS[primitive]
    if segments[0] < least[0] or segments[1] < least[1]:
        raise w.error(f"{key}.segments", f"expected at least {list(least)} for a {primitive}, found "
                      f"{list(segments)}", f"fewer segments cannot make a closed {primitive}")
    return segments


def _parse_transform(w: _Where, key: str, m: Mapping[str, Any]):
    """Position, rotation (degrees) and non-zero scale factors."""
    position = w.vector(m.get("position", [0, 0, 0]), f"{key}.position")
    rotate = w.vector(m.get("rotate", [0, 0, 0]), f"{key}.rotate")
    scale_raw = m.get("scale", 1.0)
    scale = (w.number(scale_raw, f"{key}.scale"),) * 3 if isinstance(scale_raw, (int, float)) and not isinstance(
        scale_raw, bool) else w.vector(scale_raw, f"{key}.scale")
    if min(abs(s) for s in scale) < 1e-12:
        raise w.error(f"{key}.scale", f"expected non-zero scale factors, found {scale_raw!r}")
    return position, rotate, scale


def _parse_binding(w: _Where, key: str, m: Mapping[str, Any]):
    """The material the mesh binds (a port name) with its texture coordinates, or the plain colour of none."""
    material = m.get("material")
    if material is not None:
        if not isinstance(material, str) or not PORT_NAME.match(material):
            raise w.error(f"{key}.material", f"expected a material name (letters, digits, _), found {material!r}",
                          "the name becomes an input port of the render node")
        if material in RESERVED_PORTS or material.endswith(("_map", "_tiles")):
            raise w.error(f"{key}.material", f"'{material}' cannot name a material",
                          f"{', '.join(RESERVED_PORTS)} and names ending in _map or _tiles are taken by the render node")
    for k in ("uv_scale", "uv_offset", "wrap", "coord_map", "tiles"):
        if k in m and material is None:
            raise w.error(f"{key}.{k}", "applies to a bound material, but the mesh has none", "add 'material: NAME'")
    uv_scale = w.pair(m.get("uv_scale"), f"{key}.uv_scale", default=(1.0, 1.0))
    if min(abs(s) for s in uv_scale) < 1e-12:
        raise w.error(f"{key}.uv_scale", f"expected non-zero factors, found {m.get('uv_scale')!r}")
    uv_offset = w.pair(m.get("uv_offset"), f"{key}.uv_offset", default=(0.0, 0.0))
    wrap = w.choice(m.get("wrap", "repeat"), f"{key}.wrap", WRAPS)
    coord_map = m.get("coord_map", False)
    if not isinstance(coord_map, bool):
        raise w.error(f"{key}.coord_map", f"expected true or false, found {coord_map!r}")
    if "color" in m and material is not None:
        raise w.error(f"{key}.color", "a mesh has either a material or a plain colour, not both")
    color = w.colour(m.get("color", [0.6, 0.6, 0.6]), f"{key}.color")
    return material, uv_scale, uv_offset, wrap, coord_map, color


def _parse_tiles(w: _Where, key: str, m: Mapping[str, Any], uv_scale: tuple[float, float], coord_map: bool) -> bool:
    """``tiles: true``: whole tiles per unit of UV (``uv_scale`` a pair of integers), no offset, no coordinate map."""
    tiles = m.get("tiles", False)
    if not isinstance(tiles, bool):
        raise w.error(f"{key}.tiles", f"expected true or false, found {tiles!r}")
    if tiles and coord_map:
        raise w.error(f"{key}.tiles", "a mesh takes either a coordinate map or a tile set, not both")
    if tiles and (any(s < 1 or s != int(s) for s in uv_scale) or "uv_offset" in m):
        raise w.error(f"{key}.uv_scale", f"with tiles, expected whole tiles per unit of UV (integers >= 1) and no "
                      f"uv_offset, found uv_scale {list(uv_scale)}", "e.g. uv_scale: [4, 4] for 4 x 4 tiles per face")
    return tiles


def _a(noun: str) -> str:
    return f"{'an' if noun[0] in 'aeiou' else 'a'} {noun}"


def _parse_light(w: _Where, index: int, raw: Any, base_dir: Path, check_files: bool = True) -> LightSpec:
    key = f"lights[{index}]"
    if not isinstance(raw, Mapping):
        raise w.error(key, f"expected a mapping, found {type(raw).__name__}")
    kind = w.choice(raw.get("type"), f"{key}.type", tuple(LIGHT_KEYS))
    allowed = LIGHT_KEYS[kind]
    for k in raw:
        if k not in allowed:  # often a key of another light type: say so, and list what this type takes
            owners = [_a(f"{t} light") for t, keys in LIGHT_KEYS.items() if k in keys]
            near = did_you_mean(str(k), allowed)
            lead = (f"'{k}' belongs to {' or '.join(owners)}; " if owners
                    else f"{near} " if near.startswith("did you mean") else "")
            raise w.error(f"{key}.{k}", f"unknown key for {_a(kind + ' light')}",
                          f"{lead}{_a(kind + ' light')} takes {', '.join(allowed)}")
    intensity = w.colour(raw.get("intensity", 1.0), f"{key}.intensity")
    if kind == "directional":
        if "direction" not in raw:
            raise w.error(f"{key}.direction", "is missing", "give the direction toward the light, e.g. [0, 0, 1]")
        return LightSpec(index, kind, intensity, direction=w.direction(raw["direction"], f"{key}.direction"))
    if kind == "point":
        if "position" not in raw:
            raise w.error(f"{key}.position", "is missing")
        return LightSpec(index, kind, intensity, position=w.vector(raw["position"], f"{key}.position"))
    if ("file" in raw) == ("sky" in raw):
        raise w.error(key, "an environment light needs exactly one of 'file' (a lat-long EXR) or 'sky'")
    file, sky = None, None
    if "file" in raw:
        file = w.file(raw["file"], f"{key}.file", base_dir, check_files, (".exr",),
                      "a lat-long OpenEXR map (.exr)", "environment map")
    else:
        s = w.mapping(raw["sky"] or {}, f"{key}.sky", SKY_KEYS)
        sky = {
            "zenith": w.colour(s.get("zenith", [0.25, 0.35, 0.6]), f"{key}.sky.zenith"),
            "horizon": w.colour(s.get("horizon", [0.8, 0.8, 0.85]), f"{key}.sky.horizon"),
            "ground": w.colour(s.get("ground", [0.15, 0.13, 0.1]), f"{key}.sky.ground"),
            "sun": w.direction(s.get("sun", [0.5, 0.3, 0.8]), f"{key}.sky.sun"),
            "sun_intensity": w.number(s.get("sun_intensity", 40.0), f"{key}.sky.sun_intensity", low=0.0),
            "sun_size": w.number(s.get("sun_size", 4.0), f"{key}.sky.sun_size", low=0.0, high=90.0, low_open=True),
            "width": w.integer(s.get("width", 256), f"{key}.sky.width", low=8, high=8192),
        }
    method = w.choice(raw.get("method", "importance"), f"{key}.method", ENV_METHODS)
    samples = w.integer(raw.get("samples", 64), f"{key}.samples", high=4096)
    order = w.integer(raw.get("order", 3), f"{key}.order", high=MAX_SH_ORDER)
    rotate = w.number(raw.get("rotate", 0.0), f"{key}.rotate")
    up = w.direction(raw.get("up", [0, 0, 1]), f"{key}.up")
    forward = np.array(w.vector(raw.get("forward", [1, 0, 0]), f"{key}.forward"))
    forward = forward - np.dot(forward, up) * np.asarray(up)
    if np.linalg.norm(forward) < 1e-6:
        raise w.error(f"{key}.forward", f"is parallel to 'up' (or zero): {list(raw.get('forward', [1, 0, 0]))!r}",
                      "give the horizontal direction the map's left edge (column 0) faces, across 'up'")
    forward = tuple(float(x) for x in forward / np.linalg.norm(forward))
    return LightSpec(index, kind, intensity, file=file, sky=sky, method=method, samples=samples, order=order,
                     rotate=rotate, up=up, forward=forward)


def _parse_animation(w: _Where, raw: Any, lights: tuple[LightSpec, ...]) -> AnimationSpec:
    a = w.mapping(raw, "animation", ANIMATION_KEYS)
    kind = w.choice(a.get("type"), "animation.type", ANIMATIONS)
    frames = w.integer(a.get("frames", 24), "animation.frames", high=10000)
    degrees = w.number(a.get("degrees", 360.0), "animation.degrees")
    light = w.integer(a.get("light", 0), "animation.light", low=0)
    axis = w.direction(a.get("axis", [0, 0, 1]), "animation.axis")
    fps = w.number(a.get("fps", 12.0), "animation.fps", low=0.0, low_open=True, high=240.0)
    if kind == "light_sweep":
        if light >= len(lights):
            raise w.error("animation.light", f"expected the index of a light (0..{len(lights) - 1}), found {light}",
                          "a light sweep moves one of the scene's lights")
        if lights[light].kind == "environment":
            raise w.error("animation.light", "names an environment light",
                          "sweep a directional or point light; rotate an environment with its 'rotate' key")
    return AnimationSpec(kind, frames, degrees, light, axis, fps)


def scene_ports(value: Any, paths) -> dict[str, str]:
    """Input ports a ``render.image`` node gets from its ``scene`` param (used by the engine at validation)."""
    data, source, base = read_scene_source(value, paths)
    return parse_scene(data, source, base).ports()


# ----------------------------------------------------------------------------------------------- the Scene buffer


def _absolute(data: Mapping[str, Any], spec: SceneSpec) -> dict[str, Any]:
    """A copy of the raw scene with the file paths ``spec`` resolved (absolute), so it can move between folders."""
    out = dict(data)
    if any(m.file for m in spec.meshes):
        out["meshes"] = {str(name): dict(body) for name, body in data["meshes"].items()}
        for mesh in spec.meshes:
            if mesh.file:
                out["meshes"][mesh.name]["file"] = mesh.file
    if any(l.file for l in spec.lights):
        out["lights"] = [dict(body) for body in data["lights"]]
        for light in spec.lights:
            if light.file:
                out["lights"][light.index]["file"] = light.file
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class Scene(Buffer):
    """A checked scene with the contents of the files it names (meshes, environment maps), so it is self-contained.

    ``raw`` is the scene mapping with absolute file paths; ``arrays`` maps ``"<file>|<field>"`` to arrays
    (mesh ``positions``, ``triangles``, ``corner_uv``; environment ``pixels``).
    """

    type_name: ClassVar[str] = "Scene"

    raw: dict
    source: str
    arrays: dict

    def __post_init__(self):
        freeze_fields(self, arrays={k: np.asarray(v) for k, v in self.arrays.items()})

    def payload(self):
        names = sorted(self.arrays)
        return ({"raw": self.raw, "source": self.source, "names": names},
                {f"a{i}": self.arrays[n] for i, n in enumerate(names)})

    @classmethod
    def from_payload(cls, meta, arrays):
        return cls(meta["raw"], meta["source"], {n: arrays[f"a{i}"] for i, n in enumerate(meta["names"])})

    @property
    def spec(self) -> SceneSpec:
        return parse_scene(self.raw, self.source, Path("/"), check_files=False)

    def file_arrays(self, path: str) -> dict[str, np.ndarray]:
        prefix = f"{path}|"
        return {k[len(prefix):]: v for k, v in self.arrays.items() if k.startswith(prefix)}
