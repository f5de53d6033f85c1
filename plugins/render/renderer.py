"""The renderer: plans passes from the scene's effects and content, casts rays with open3d, shades with the models.

Passes (each runs only when the scene calls for it, and reports its counts):

* ``primary``: camera rays, one per pixel, or ``camera.samples`` per pixel with ``antialias``;
* ``direct``: directional and point lights, model evaluations at each visible sample's light in its texel frame;
* ``shadows``: shadow rays toward each direct light, only with ``shadows``, geometry that can occlude (more
  than one mesh, or a mesh that can shadow itself: not a plane, sphere or cube alone) and a light that takes
  shadow rays (a direct light or an importance-sampled environment; the SH method takes none);
* ``environment``: with ``environment`` and an environment light: importance-sampled directional lights (with
  their own shadow rays when shadows run), or SH projection rotated into each texel's frame (no shadows, canonical
  view); reported per light, under ``lights[i]`` (its place in the scene's ``lights``);
* ``view_dependence``: per-sample view directions in the texel frame, only for view-dependent models with the
  ``view_dependence`` effect and a light shaded one direction at a time (otherwise models are evaluated at their
  canonical view).

An effect the scene asks for that does no work (or none for some lights) gets its reason in ``skipped``.  With the
``environment`` effect off, environment lights are not read at all, and a ``background: environment`` is black.

Shading of one sample under a directional light of intensity ``E`` toward ``l``: ``E * f(l_local, v_local)``
where ``f`` is the model (radiance under unit light, as relighting gives it) and ``l_local = (l.T, l.B, l.N)`` in
the sample's tangent frame; zero when ``l`` is below the horizon of the (interpolated) shading normal.  Point lights
give ``E / d^2``.  Meshes without a material are Lambertian in RTI units: ``f = colour * max(l_local.z, 0)``.
"""
from __future__ import annotations

import dataclasses
import math
import functools
from typing import Any, Mapping

import numpy as np

from btforge.buffers import CoordMap, ReflectanceModel
from btforge.errors import BtforgeInputError

from .envmap import (DirectionalSet, SHRotator, environment_pixels, hemisphere_quadrature, importance_sample,
                     lookup, project_sh, real_sh)
from .geometry import BuiltMesh, build_mesh, complete_frame
from .o3d import open3d
from .lookup import texel_corners
from .scene import LightSpec, Scene, SceneSpec

BATCH_ITEMS = 1 << 21  # (sample, light) pairs shaded per batch
BAND_SAMPLES = 1 << 19  # camera samples traced and shaded at once (a band of image rows)
SH_QUADRATURE = 256    # hemisphere directions used to project a model onto SH


# ----------------------------------------------------------------------------------------------- utilities


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(n > 1e-30, n, 1.0)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def rotate_about(v: np.ndarray, axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rodrigues rotation of vectors ``v [..., 3]`` about the unit ``axis``."""
    a = math.radians(degrees)
    k = np.asarray(axis, np.float64)
    v = np.asarray(v, np.float64)
    return v * math.cos(a) + np.cross(k, v) * math.sin(a) + np.outer(v @ k, k).reshape(v.shape) * (1 - math.cos(a))


def sample_offsets(spp: int) -> np.ndarray:
    """Sub-pixel positions in [0, 1)^2: the centre for one sample, else a rank-1 lattice (stratified in x)."""
    if spp == 1:
        return np.array([[0.5, 0.5]])
    i = np.arange(spp)
    golden = (math.sqrt(5) - 1) / 2
    return np.stack([(i + 0.5) / spp, (0.5 + i * golden) % 1.0], 1)


# ----------------------------------------------------------------------------------------------- counters


class Counters:
    """Work done per pass; only passes that did something are reported.

    An entry is named by a pass (``"direct"``) or a path into one (``("environment", "lights[2]")``).
    """

    def __init__(self):
        self.passes: dict[str, dict[str, Any]] = {}
        self.skipped: dict[str, str] = {}

    def _entry(self, path: str | tuple[str, ...]) -> dict[str, Any]:
        entry = self.passes
        for part in (path,) if isinstance(path, str) else path:
            entry = entry.setdefault(part, {})
        return entry

    def add(self, path: str | tuple[str, ...], key: str, n: int | float) -> None:
        entry = self._entry(path)
        entry[key] = entry.get(key, 0) + n

    def set(self, path: str | tuple[str, ...], key: str, value: Any) -> None:
        self._entry(path)[key] = value


# ----------------------------------------------------------------------------------------------- planning


@dataclasses.dataclass
class Plan:
    spp: int
    direct: list[LightSpec]
    shadows: bool
    environment: list[LightSpec]
    view: bool
    background: LightSpec | None   # the environment light drawn where camera rays miss, if any


def make_plan(spec: SceneSpec, meshes: list[BuiltMesh], materials: Mapping[str, Any], counters: Counters) -> Plan:
    eff = spec.effects
    skipped = counters.skipped
    occluders = len(meshes) > 1 or any(not m.convex for m in meshes)
    direct = [l for l in spec.lights if l.kind in ("directional", "point")]
    env = [l for l in spec.lights if l.kind == "environment"]
    environment = env if "environment" in eff else []
    if "environment" in eff and not env:
        skipped["environment"] = "the scene has no environment light"
    if env and "environment" not in eff:
        skipped["environment"] = "effect off: environment lights are ignored" + (
            ", and the background is black" if spec.background == "environment" else "")
    # Only lights shaded one direction at a time cast shadow rays and see the view; the SH method integrates a
    # whole environment against a transfer table taken at the canonical view, with no visibility.
    sampled = direct + [l for l in environment if l.method == "importance"]
    sh_lights = ", ".join(f"lights[{l.index}]" for l in environment if l.method == "sh")
    unlit = ("the scene has no direct light, and its environment lights are off without the environment effect"
             if env and not environment else "the scene has no light")

    def through_sampled_lights(effect: str, unavailable: str | None, sh_method: str) -> bool:
        """Plan an effect that acts per light direction (direct lights, importance-sampled environments): off,
        with the reason, when it cannot apply or no such light exists; the sh method never gets it."""
        if effect not in eff:
            return False
        if unavailable:
            skipped[effect] = unavailable
        elif not sampled:
            skipped[effect] = f"the sh method ({sh_lights}) {sh_method}" if sh_lights else unlit
        else:
            if sh_lights:
                skipped[effect] = f"not for {sh_lights}: the sh method {sh_method}"
            return True
        return False

    shadows = through_sampled_lights(
        "shadows", None if occluders else "nothing can occlude: a single convex mesh casts no shadow on itself",
        "ignores shadows")
    view = through_sampled_lights(
        "view_dependence",
        None if any(getattr(materials.get(name), "view_dependent", False) for name in spec.materials)
        else "no material's model depends on the view (a PTM depends on the light only)",
        "evaluates models at their canonical view")

    background = None
    if spec.background == "environment" and environment:
        background = env[0]
    spp = spec.camera.samples if "antialias" in eff else 1
    return Plan(spp=spp, direct=direct, shadows=shadows, environment=environment, view=view, background=background)


class ColourShader:
    """A mesh without a material: Lambertian in RTI units, ``colour * max(l_local.z, 0)``."""

    view_dependent = False

    def __init__(self, colour):
        self.colour = np.asarray(colour, np.float64)

    def evaluate(self, sel, lights, views):
        return np.maximum(lights[:, 2:3], 0.0) * self.colour.astype(lights.dtype)

    def transfer(self, order: int, sel: np.ndarray, cache: dict) -> np.ndarray:
        """The SH transfer vectors ``[n, 3, order^2]`` of the Lambertian lobe at the samples ``sel``."""
        key = ("cosine", order)
        if key not in cache:
            dirs, wq = hemisphere_quadrature(SH_QUADRATURE)
            cache[key] = (dirs[:, 2:3] * real_sh(order, dirs)).sum(0) * wq           # [n^2]
        t = cache[key]
        return np.broadcast_to(self.colour[None, :, None] * t[None, None, :], (len(sel), 3, order * order))


def _to_rgb(values: np.ndarray, model) -> np.ndarray:
    c = values.shape[-1]
    if c == 3:
        return values
    if c == 1:
        return np.repeat(values, 3, axis=-1)
    raise BtforgeInputError(f"render, model {type(model).__name__}", f"expected 1 or 3 colour channels, found {c} "
                            f"({', '.join(model.channels)})", "render an RGB or grey model")


def _mixing(model: ReflectanceModel) -> ReflectanceModel:
    """The model a blend layer reads: itself where its records mix, else its ``mixing_form`` where it has one (as
    ``synth.materialize`` replays the layer), else itself (each texel's heavier source)."""
    return model if model.mixes_records else (model.mixing_form() or model)


class ModelShader:
    """A reflectance model looked up at the samples of one mesh (through a coordinate map if any).

    Linear models whose per-texel records are floats (``blendable``) are looked up by interpolating the records
    of the 4 texels around each sample (8 with a blending coordinate map) into a one-record-per-sample model,
    evaluated with nearest lookups; other models are evaluated at each corner texel and the values weighted.  A
    blend layer on a model whose records mix only as display values (an sRGB PTM) mixes each corner's record with
    its partner's first, as ``synth.materialize`` replays the map, and weighs the corners' radiance as without one.
    """

    def __init__(self, name: str, model: ReflectanceModel, coord_map: CoordMap | None, uv: np.ndarray, wrap: str,
                 texels: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None):
        if coord_map is not None and coord_map.blend_weight.size:
            model = _mixing(model)
        self.name, self.model = name, model
        grid = (coord_map.height, coord_map.width) if coord_map is not None else (model.height, model.width)
        # ``texels``: the model's (rows, cols, weights) around each sample, found by the caller (a tile set)
        rows, cols, weights = texels if texels is not None else texel_corners(uv, grid[0], grid[1], wrap)
        if coord_map is not None:
            if coord_map.source_size != (model.height, model.width):
                raise BtforgeInputError(f"render, material '{name}'", f"the coordinate map indexes a "
                                        f"{coord_map.source_size[0]} x {coord_map.source_size[1]} exemplar, but the "
                                        f"model is {model.height} x {model.width}",
                                        "wire the map synthesized from this model's exemplar")
            coords = coord_map.coords[rows, cols]
            if coord_map.blend_weight.size:
                bw = coord_map.blend_weight[rows, cols].astype(np.float64)
                other = coord_map.blend_coords[rows, cols]
                if model.mixes_records:
                    rows = np.concatenate([coords[..., 0], other[..., 0]])
                    cols = np.concatenate([coords[..., 1], other[..., 1]])
                    weights = np.concatenate([weights * (1 - bw), weights * bw])
                else:
                    pick = (bw > 0.5)[..., None]
                    chosen = np.where(pick, other, coords)
                    rows, cols = chosen[..., 0], chosen[..., 1]
            else:
                rows, cols = coords[..., 0], coords[..., 1]
        self.rows, self.cols, self.weights = rows, cols, weights
        self.view_dependent = bool(model.view_dependent)
        self.interpolates_records = model.evaluates_texels and model.blendable and all(
            getattr(model, f).dtype.kind == "f" for f in model.texel_fields)
        # 8 corners are the 4 bilinear ones and their blend partners (a blend layer, from a map or a tile set)
        self.mixes_pairs = len(weights) == 8 and not self.interpolates_records and model.mixes_records

    @functools.cached_property
    def corners(self) -> list:
        """``(model, rows, cols, weights)`` per corner, each over every sample, for evaluating the corners one by
        one: the model's own texels, or where pairs mix as display values one mixed record per sample."""
        if not self.mixes_pairs:
            return [(self.model, self.rows[k], self.cols[k], self.weights[k]) for k in range(len(self.weights))]
        n = self.rows.shape[1]
        return [(flat, np.arange(n), np.zeros(n, np.int64), weight) for flat, weight in self.mixed_corners()]

    def mixed_corners(self) -> list:
        """(one record per sample, its corner's weight) for each bilinear corner: the corner's record mixed with its
        blend partner's through :meth:`~PerTexel.remap`, the record ``synth.materialize`` replays there."""
        corners = []
        for k in range(4):
            total = self.weights[k] + self.weights[k + 4]
            share = np.divide(self.weights[k + 4], total, out=np.zeros_like(total), where=total > 0)
            column = (slice(None), None)    # the samples as an [N, 1] grid of texels
            mixed = self.model.remap(self.rows[k][column], self.cols[k][column], self.rows[k + 4][column],
                                     self.cols[k + 4][column], share[column].astype(np.float32))
            corners.append((mixed.evaluation_form(), total))
        return corners

    @functools.cached_property
    def flat(self) -> ReflectanceModel:
        """One interpolated record per sample, gathered on first evaluation: the SH environment path reads the
        per-texel transfer table instead and never needs it."""
        return self._gather_model()

    def _gather_model(self):
        model = self.model
        ax = model.texel_axis
        lead = (slice(None),) * ax
        changes = {}
        w = self.weights.astype(np.float32)
        for field in model.texel_fields:
            array = getattr(model, field)
            acc = None
            for k in range(len(w)):
                if not w[k].any():
                    continue
                part = array[lead + (self.rows[k], self.cols[k])]
                wk = w[k].reshape((1,) * ax + w[k].shape + (1,) * (array.ndim - ax - 2))
                acc = part * wk if acc is None else acc + part * wk
            if acc is None:
                acc = np.zeros(array.shape[:ax] + (self.rows.shape[1],) + array.shape[ax + 2:], array.dtype)
            changes[field] = np.expand_dims(acc.astype(array.dtype), ax + 1)
        return dataclasses.replace(model, **changes).evaluation_form()  # converted once, evaluated many times

    def evaluate(self, sel: np.ndarray, lights: np.ndarray, views: np.ndarray | None) -> np.ndarray:
        lights32 = np.ascontiguousarray(lights, np.float32)
        views32 = None if views is None else np.ascontiguousarray(views, np.float32)
        if self.interpolates_records:
            values = self.flat.evaluate_texels(sel, np.zeros_like(sel), lights32, views32)
            return _to_rgb(np.asarray(values), self.model)
        total = np.zeros((len(sel), 3))
        for model, rows, cols, weights in self.corners:
            wk = weights[sel]
            use = wk > 0
            if not use.any():
                continue
            values = model.evaluate_texels(rows[sel][use], cols[sel][use], lights32[use],
                                           None if views32 is None else views32[use])
            total[use] += wk[use, None] * _to_rgb(np.asarray(values), self.model)
        return total

    def transfer(self, order: int, sel: np.ndarray, cache: dict) -> np.ndarray:
        """The model's SH transfer vectors ``[n, 3, order^2]`` at the samples ``sel`` (canonical view)."""
        key = (id(self.model), order)
        if key not in cache:
            cache[key] = model_transfer(self.model, order)
        table = cache[key]                                                  # [H, W, 3, n^2]
        # A blend layer's partners are weighed as radiance here, the transfer being a projection of radiance: for
        # records that mix as display values (mixes_pairs) it differs from the direct lights' mix inside the band.
        out = np.zeros((len(sel), 3, order * order))
        for k in range(len(self.weights)):
            out += self.weights[k][sel, None, None] * table[self.rows[k][sel], self.cols[k][sel]]
        return out


def model_transfer(model: ReflectanceModel, order: int) -> np.ndarray:
    """Per-texel SH projection ``[H, W, 3, order^2]`` of ``l -> f(l)`` over the upper hemisphere (zero below).

    Uses only the generic :meth:`ReflectanceModel.evaluate` (all texels at a list of lights), so any model works.
    """
    dirs, wq = hemisphere_quadrature(SH_QUADRATURE)
    basis = real_sh(order, dirs) * wq                                       # [Q, n^2]
    out = np.zeros((model.height, model.width, 3, order * order))
    for start in range(0, len(dirs), 16):
        values = model.evaluate(dirs[start:start + 16].astype(np.float32))[0]   # [q, H, W, C]
        values = _to_rgb(values, model).astype(np.float64)
        out += np.einsum("qhwc,qj->hwcj", values, basis[start:start + 16])
    return out


# ----------------------------------------------------------------------------------------------- the scene


class BuiltScene:
    """Meshes in world space with an open3d ray-casting scene, and the environment maps the plan uses."""

    def __init__(self, scene: Scene, spec: SceneSpec):
        o3d = open3d()

        self.scene, self.spec = scene, spec
        self.meshes = [build_mesh(m, scene) for m in spec.meshes]
        self.rc = o3d.t.geometry.RaycastingScene()
        self.geometry_to_mesh = {}
        for i, mesh in enumerate(self.meshes):
            gid = self.rc.add_triangles(o3d.core.Tensor(np.ascontiguousarray(mesh.positions, np.float32)),
                                        o3d.core.Tensor(np.ascontiguousarray(mesh.triangles, np.uint32)))
            self.geometry_to_mesh[gid] = i
        allpos = np.concatenate([m.positions for m in self.meshes])
        self.diagonal = float(np.linalg.norm(allpos.max(0) - allpos.min(0))) or 1.0
        self._env_pixels: dict[int, np.ndarray] = {}
        self.tilings: dict = {}  # Wang tilings of meshes dressed with tile sets, made on first use

    def env_pixels(self, light: LightSpec) -> np.ndarray:
        """The lat-long map of an environment light, made (sky) or taken from the scene the first time a pass asks,
        so an environment the plan leaves out costs nothing."""
        if light.index not in self._env_pixels:
            self._env_pixels[light.index] = environment_pixels(light, self.scene)
        return self._env_pixels[light.index]

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        o3d = open3d()
        rays = np.concatenate([origins, dirs], 1).astype(np.float32)
        return {k: v.numpy() for k, v in self.rc.cast_rays(o3d.core.Tensor(rays)).items()}

    def occluded_rays(self, rays: np.ndarray, tfar: float) -> np.ndarray:
        """Whether each ray ``[N, 6]`` float32 (origin, direction) hits anything with ``0 <= t < tfar``."""
        o3d = open3d()
        return self.rc.test_occlusions(o3d.core.Tensor.from_numpy(rays), tnear=0.0, tfar=tfar).numpy().astype(bool)


@dataclasses.dataclass
class Surface:
    """What the camera sees: per sample, whether it hit, and for hits the shading data."""

    n_samples: int
    hit: np.ndarray          # [S] bool
    miss_dirs: np.ndarray    # [S - n, 3] ray directions of the misses
    P: np.ndarray            # [n, 3] world positions
    Ng: np.ndarray           # [n, 3] geometric normals (facing the camera)
    N: np.ndarray            # [n, 3] shading frame: normal, tangent, bitangent
    T: np.ndarray
    B: np.ndarray
    V: np.ndarray            # [n, 3] toward the camera
    groups: list             # (indices into the n hits, shader)


def camera_rays(cam, spp: int, position=None, up=None, rows: slice = slice(None)) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins and unit directions ``[h * W * spp, 3]`` of a band of rows, pixel-major (row, column, sample)."""
    position = np.asarray(cam.position if position is None else position, np.float64)
    up = np.asarray(cam.up if up is None else up, np.float64)
    forward = _unit(np.asarray(cam.look_at, np.float64) - position)
    right = _unit(np.cross(forward, up))
    true_up = np.cross(right, forward)
    w, h = cam.width, cam.height
    offsets = sample_offsets(spp)
    first, last, _ = rows.indices(h)
    rows, cols = np.mgrid[first:last, 0:w]
    px = (cols[..., None] + offsets[:, 0]).reshape(-1)
    py = (rows[..., None] + offsets[:, 1]).reshape(-1)
    ndc_x = px / w * 2 - 1
    ndc_y = 1 - py / h * 2
    aspect = w / h
    if cam.kind == "orthographic":
        half_h = cam.extent / 2
        origins = position + (ndc_x * half_h * aspect)[:, None] * right + (ndc_y * half_h)[:, None] * true_up
        dirs = np.broadcast_to(forward, origins.shape).copy()
    else:
        t = math.tan(math.radians(cam.fov) / 2)
        dirs = _unit(forward + (ndc_x * t * aspect)[:, None] * right + (ndc_y * t)[:, None] * true_up)
        origins = np.broadcast_to(position, dirs.shape).copy()
    return origins, dirs


def trace(built: BuiltScene, materials: Mapping[str, Any], plan: Plan, counters: Counters,
          position=None, up=None, rows: slice = slice(None)) -> Surface:
    origins, dirs = camera_rays(built.spec.camera, plan.spp, position, up, rows)
    counters.add("primary", "rays", len(dirs))
    if plan.spp > 1:
        counters.set("antialias", "samples_per_pixel", plan.spp)
        counters.add("antialias", "extra_rays", len(dirs) - len(dirs) // plan.spp)
    res = built.cast(origins, dirs)
    hit = np.isfinite(res["t_hit"])
    idx = np.nonzero(hit)[0]
    t = res["t_hit"][idx].astype(np.float64)
    d = dirs[idx]
    P = origins[idx] + t[:, None] * d
    prim = res["primitive_ids"][idx].astype(np.int64)
    gid = res["geometry_ids"][idx]
    bary_uv = res["primitive_uvs"][idx].astype(np.float64)
    bary = np.stack([1 - bary_uv[:, 0] - bary_uv[:, 1], bary_uv[:, 0], bary_uv[:, 1]], 1)
    mesh_of = np.vectorize(built.geometry_to_mesh.get, otypes=[np.int64])(gid) if len(gid) else gid.astype(np.int64)
    n = len(idx)
    Ng, N, T, B, uv = (np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 2)))
    groups = []
    for mi, mesh in enumerate(built.meshes):
        sel = np.nonzero(mesh_of == mi)[0]
        if not len(sel):
            continue
        p, w = prim[sel], bary[sel][:, :, None]
        tri = mesh.positions[mesh.triangles[p]].astype(np.float64)
        Ng[sel] = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
        N[sel] = (w * mesh.corner_n[p]).sum(1)
        T[sel] = (w * mesh.corner_t[p]).sum(1)
        B[sel] = (w * mesh.corner_b[p]).sum(1)
        uv[sel] = (w * mesh.corner_uv[p]).sum(1)
        groups.append((mi, sel))
    # two-sided: a back face is seen from behind (the texture mirrored)
    back = _dot(Ng, d) > 0
    Ng[back] *= -1
    N[back] *= -1
    N = _unit(N)
    T, B = complete_frame(N, T, B)   # interpolated frames drift from orthonormal between corners

    shader_groups = _shader_groups(built, materials, groups, prim, uv, T, B)
    return Surface(len(dirs), hit, dirs[~hit], P, Ng, N, T, B, -d, shader_groups)


def _shader_groups(built: BuiltScene, materials: Mapping[str, Any], groups, prim, uv, T, B) -> list:
    """(samples, shader) per mesh hit: its plain colour, or its model looked up at its texture coordinates (through
    a coordinate map or a Wang tile set where the mesh says so).  Flips ``T`` / ``B`` in place where the texture
    is mirrored (negative UV scale, ``wrap: mirror``), so the frame follows the texture."""
    shader_groups = []
    for mi, sel in groups:
        mesh = built.meshes[mi]
        spec = mesh.spec
        if spec.material is None:
            shader_groups.append((sel, ColourShader(spec.color)))
            continue
        model = materials[spec.material]
        if spec.tiles:  # a Wang tile set: each UV cell shows a tile, looked up through its BTFel table
            from .tiles import tiled_texels
            tiles = materials[f"{spec.material}_tiles"]
            if tiles.blends:
                model = _mixing(model)
            texels = tiled_texels(built, mi, tiles, prim[sel], uv[sel], blend=model.mixes_records)
            shader_groups.append((sel, ModelShader(spec.material, model, None, uv[sel], spec.wrap, texels)))
            continue
        coord_map = materials.get(f"{spec.material}_map") if spec.coord_map else None
        su, sv = spec.uv_scale
        ou, ov = spec.uv_offset
        tex_uv = np.stack([uv[sel, 0] * su + ou, uv[sel, 1] * sv + ov], 1)
        flip_t = np.full(len(sel), su < 0)
        flip_b = np.full(len(sel), sv < 0)
        if spec.wrap == "mirror":  # odd tiles are mirrored: so is the texture's frame
            flip_t ^= np.floor(tex_uv[:, 0]).astype(np.int64) % 2 == 1
            flip_b ^= np.floor(tex_uv[:, 1]).astype(np.int64) % 2 == 1
        T[sel[flip_t]] *= -1
        B[sel[flip_b]] *= -1
        shader_groups.append((sel, ModelShader(spec.material, model, coord_map, tex_uv, spec.wrap)))
    return shader_groups


# ----------------------------------------------------------------------------------------------- shading


def _local(surface: Surface, omega: np.ndarray) -> np.ndarray:
    return np.stack([_dot(omega, surface.T), _dot(omega, surface.B), _dot(omega, surface.N)], -1)


def _views(surface: Surface, plan: Plan, counters: Counters) -> dict[int, np.ndarray | None]:
    """Per shader group: view directions in the texel frame, or None (canonical view) when not needed."""
    out, local = {}, None
    for gi, (sel, shader) in enumerate(surface.groups):
        if plan.view and shader.view_dependent:
            local = _local(surface, surface.V) if local is None else local
            out[gi] = local[sel]
            counters.add("view_dependence", "views", len(sel))
        else:
            out[gi] = None
    return out


def shade_lights(surface: Surface, built: BuiltScene, lights: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
                 shadows: bool, views: dict, counters: Counters, report: str | tuple[str, ...],
                 radiance: np.ndarray) -> None:
    """Add the contribution of ``lights`` = [(direction or None, intensity RGB, position or None)] to ``radiance``,
    counting the work under ``report`` (shadow rays of the ``direct`` pass under ``shadows``).

    Lights are shaded in batches: the (sample, light) pairs above both horizons are found for the whole batch at
    once, shadow rays for them are cast in one call, and each shader group is evaluated once per batch.
    """
    n = len(surface.P)
    if n == 0 or not lights:
        return
    eps = 1e-4 * built.diagonal
    origins = (surface.P + surface.Ng * eps).astype(np.float32)
    frames = np.stack([surface.T, surface.B, surface.N], 1)                 # [n, 3, 3] rows T, B, N
    frames32 = frames.astype(np.float32)
    group_of = np.full(n, -1, dtype=np.int64)
    position_in_group = np.zeros(n, dtype=np.int64)
    for gi, (sel, _) in enumerate(surface.groups):
        group_of[sel] = gi
        position_in_group[sel] = np.arange(len(sel))
    directional = [(d, i) for d, i, p in lights if p is None]
    points = [(i, p) for d, i, p in lights if p is not None]
    per_batch = max(1, BATCH_ITEMS // n)
    batches = []
    for start in range(0, len(directional), per_batch):
        batches.append(("directional", directional[start:start + per_batch]))
    batches += [("point", [light]) for light in points]
    for kind, batch in batches:
        if kind == "directional":
            s_idx, local, scale, n_rays = _lit_by_directional(batch, frames32, origins, built, shadows)
        else:
            s_idx, local, scale, n_rays = _lit_by_point(batch[0], surface, frames, origins, built, shadows)
        if n_rays:
            if report == "direct":
                counters.add("shadows", "rays", n_rays)
            else:
                counters.add(report, "shadow_rays", n_rays)
        _accumulate(surface, views, counters, report, group_of[s_idx], position_in_group, s_idx, local, scale,
                    radiance)


def _lit_by_directional(batch, frames32, origins, built: BuiltScene, shadows: bool):
    """The (sample, light) pairs a batch of directional lights reaches: sample indices, light directions in the
    sample frames, the light's intensity, and the shadow rays cast (light-major, so the rays are coherent)."""
    dirs = np.array([d for d, _ in batch])                              # [L, 3]
    intensity = np.array([i for _, i in batch], np.float64)            # [L, 3]
    d32 = dirs.astype(np.float32)
    local_all = (frames32[:, :, 0:1] * d32[:, 0] + frames32[:, :, 1:2] * d32[:, 1]
                 + frames32[:, :, 2:3] * d32[:, 2])                     # [n, 3, L]: (l.T, l.B, l.N)
    visible = local_all[:, 2, :] > 0                                     # [n, L] above the horizon
    l_idx, s_idx = np.nonzero(visible.T)       # light-major: coherent shadow rays
    local = local_all[s_idx, :, l_idx]
    scale = intensity.astype(np.float32)[l_idx]
    n_rays = 0
    if shadows and len(s_idx):
        rays = np.empty((len(s_idx), 6), np.float32)
        rays[:, :3] = origins[s_idx]
        bounds = np.searchsorted(l_idx, np.arange(len(dirs) + 1))   # light-major: one block per light
        for l in range(len(dirs)):
            rays[bounds[l]:bounds[l + 1], 3:] = d32[l]
        keep = ~built.occluded_rays(rays, np.inf)
        s_idx, local, scale, n_rays = s_idx[keep], local[keep], scale[keep], len(keep)
    return s_idx, local, scale, n_rays


def _lit_by_point(light, surface: Surface, frames, origins, built: BuiltScene, shadows: bool):
    """The samples a point light reaches, with its direction in their frames and its inverse-square intensity."""
    intensity, position = light
    vec = position - surface.P
    d2 = _dot(vec, vec)
    omega = vec / np.sqrt(d2)[:, None]
    local = np.einsum("nij,nj->ni", frames, omega)
    s_idx = np.nonzero(local[:, 2] > 0)[0]
    local = local[s_idx].astype(np.float32)
    scale = (intensity[None, :] / np.maximum(d2[s_idx], 1e-30)[:, None]).astype(np.float32)
    n_rays = 0
    if shadows and len(s_idx):  # to the light, not beyond: direction scaled to the distance, t in [0, 1)
        rays = np.concatenate([origins[s_idx], vec[s_idx].astype(np.float32)], 1)
        keep = ~built.occluded_rays(rays, 1.0 - 1e-4)
        s_idx, local, scale, n_rays = s_idx[keep], local[keep], scale[keep], len(keep)
    return s_idx, local, scale, n_rays


def _accumulate(surface: Surface, views: dict, counters: Counters, report, groups, position_in_group, s_idx, local,
                scale, radiance: np.ndarray) -> None:
    """Evaluate each shader group once at its lit samples and add the light's share to ``radiance``."""
    n = len(surface.P)
    for gi, (sel, shader) in enumerate(surface.groups):
        mine = np.nonzero(groups == gi)[0]
        if not len(mine):
            continue
        items = position_in_group[s_idx[mine]]
        view = views[gi]
        values = shader.evaluate(items, local[mine], None if view is None else view[items])
        counters.add(report, "evaluations", len(items))
        contrib = values.astype(np.float32, copy=False) * scale[mine]
        targets = s_idx[mine]
        for c in range(3):
            radiance[:, c] += np.bincount(targets, weights=contrib[:, c], minlength=n)


def shade_environment_sh(surface: Surface, built: BuiltScene, light: LightSpec, counters: Counters,
                         report: tuple[str, ...], radiance: np.ndarray, cache: dict) -> None:
    order = light.order
    key = ("sh", light.index)
    if key not in cache:
        cache[key] = project_sh(built.env_pixels(light), light, order)
    coeffs = cache[key]
    rotator = cache.setdefault(("rotator", order), SHRotator(order))
    for sel, shader in surface.groups:
        for start in range(0, len(sel), 1 << 15):
            part = sel[start:start + (1 << 15)]
            local = rotator.local_values(surface.T[part], surface.B[part], surface.N[part], coeffs)   # [m, n^2, 3]
            transfer = shader.transfer(order, np.arange(start, start + len(part)), cache)
            radiance[part] += np.einsum("mcj,mjc->mc", transfer, local)
        counters.add(report, "sh_rotations", len(sel))


def shade_frame(surface: Surface, built: BuiltScene, plan: Plan, counters: Counters, cache: dict,
                lights: list[LightSpec]) -> np.ndarray:
    """Linear radiance per sample ``[S, 3]`` (float64) of one frame."""
    radiance = np.zeros((len(surface.P), 3))
    views = _views(surface, plan, counters)
    direct = []
    for light in lights:
        if light.kind == "directional":
            direct.append((np.asarray(light.direction, np.float64), np.asarray(light.intensity), None))
        elif light.kind == "point":
            direct.append((None, np.asarray(light.intensity), np.asarray(light.position, np.float64)))
    if direct:
        counters.set("direct", "lights", len(direct))
    shade_lights(surface, built, direct, plan.shadows, views, counters, "direct", radiance)
    for light in plan.environment:
        report = ("environment", f"lights[{light.index}]")
        counters.set(report, "method", light.method)
        if light.method == "sh":
            counters.set(report, "order", light.order)
            shade_environment_sh(surface, built, light, counters, report, radiance, cache)
            continue
        key = ("samples", light.index)
        if key not in cache:
            cache[key] = importance_sample(built.env_pixels(light), light, light.samples)
        dset: DirectionalSet = cache[key]
        counters.set(report, "lights", len(dset.directions))
        env_lights = [(d, i, None) for d, i in zip(dset.directions, dset.intensities)]
        shade_lights(surface, built, env_lights, plan.shadows, views, counters, report, radiance)

    out = np.zeros((surface.n_samples, 3))
    out[surface.hit] = radiance
    if plan.background is not None:
        out[~surface.hit] = lookup(built.env_pixels(plan.background), surface.miss_dirs, plan.background)
    elif built.spec.background != "environment":   # 'environment' with the effect off stays black
        out[~surface.hit] = built.spec.background
    return out


def check_materials(spec: SceneSpec, materials: Mapping[str, Any], plan: Plan) -> None:
    """Every material bound to a model that the planned passes can evaluate; coordinate maps where declared."""
    for name in spec.materials:
        model = materials.get(name)
        if model is None:
            raise BtforgeInputError(f"render, material '{name}'", "is bound to no model",
                                    f"wire a reflectance model to the render node's input '{name}'")
        if not isinstance(model, ReflectanceModel):
            raise BtforgeInputError(f"render, material '{name}'", f"expected a ReflectanceModel, found "
                                    f"{type(model).__name__}")
        needs_texels = bool(plan.direct) or any(l.method == "importance" for l in plan.environment)
        if needs_texels and not model.evaluates_texels:
            raise BtforgeInputError(f"render, material '{name}'", f"model {type(model).__name__} cannot be rendered "
                                    "yet: it has no evaluate_texels(rows, cols, lights_local, views_local) method",
                                    "light the scene only with an environment light of method 'sh' (which needs "
                                    "just evaluate), or add evaluate_texels to the model class")
    if spec.tiled:
        from .tiles import check_tiles
        for name in spec.tiled:
            check_tiles(name, materials[name], materials.get(f"{name}_tiles"))
    for name in spec.coord_mapped:
        cmap = materials.get(f"{name}_map")
        if not isinstance(cmap, CoordMap):
            raise BtforgeInputError(f"render, material '{name}'", "declares coord_map: true but no coordinate map is "
                                    f"wired to '{name}_map'", f"wire a CoordMap (e.g. a synthesizer's map) to "
                                    f"'{name}_map'")


def render(scene: Scene, materials: Mapping[str, Any], counters: Counters | None = None) -> np.ndarray:
    """Render ``scene`` with ``materials`` ({name: model, name_map: CoordMap}); ``[H, W, 3]`` or ``[F, H, W, 3]``."""
    counters = counters or Counters()
    spec = scene.spec
    built = BuiltScene(scene, spec)
    plan = make_plan(spec, built.meshes, materials, counters)
    check_materials(spec, materials, plan)
    cam = spec.camera
    cache: dict = {}
    anim = spec.animation

    n_frames = anim.frames if anim else 1
    poses = [(None, None)] * n_frames
    frame_lights = [list(spec.lights)] * n_frames
    if anim is not None:
        counters.set("animation", "frames", anim.frames)
        centre = np.asarray(cam.look_at, np.float64)
        axis = np.asarray(anim.axis)
        for f in range(n_frames):
            angle = anim.degrees * f / anim.frames
            if anim.kind == "turntable":
                poses[f] = (centre + rotate_about(np.asarray(cam.position) - centre, axis, angle),
                            rotate_about(np.asarray(cam.up), axis, angle))
                continue
            lights = []
            for light in spec.lights:
                if light.index == anim.light and light.kind == "directional":
                    light = dataclasses.replace(light, direction=tuple(rotate_about(
                        np.asarray(light.direction), axis, angle)))
                elif light.index == anim.light:
                    light = dataclasses.replace(light, position=tuple(centre + rotate_about(
                        np.asarray(light.position) - centre, axis, angle)))
                lights.append(light)
            frame_lights[f] = lights

    # Bands of rows bound memory; a camera that does not move is traced once per band for all frames.
    band = max(1, BAND_SAMPLES // (cam.width * plan.spp))
    out = np.zeros((n_frames, cam.height, cam.width, 3), np.float32)
    moving = anim is not None and anim.kind == "turntable"
    for start in range(0, cam.height, band):
        rows = slice(start, min(cam.height, start + band))
        surface = None
        for f in range(n_frames):
            if surface is None or moving:
                surface = trace(built, materials, plan, counters, poses[f][0], poses[f][1], rows)
            samples = shade_frame(surface, built, plan, counters, cache, frame_lights[f])
            out[f, rows] = samples.reshape(rows.stop - rows.start, cam.width, plan.spp, 3).mean(axis=2)
    return out if anim is not None else out[0]
