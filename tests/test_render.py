"""Renderer: consistency with relight, tangent frames from UVs, lookups, and that each effect runs only when asked."""
import dataclasses
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
import yaml

import btforge
from btforge.buffers import CoordMap, ReflectanceModel
from btforge.context import StageContext
from btforge.errors import BtforgeInputError
from btforge.plugins.ptm.model import PTMModel, fit_ptm
from btforge.plugins.render.renderer import Counters, render
from btforge.plugins.render.loader import load_scene
from btforge.stages import RunPaths

PLANE_SCENE = """\
camera: {type: orthographic, width: 128, height: 128, position: [0, 0, 5], look_at: [0, 0, 0], up: [0, 1, 0], extent: 2.0}
meshes:
  ground: {primitive: plane, size: 2.0, material: stone}      # UV (0,0)-(1,1) across the plane, u along +x, v along +y
lights:
  - {type: directional, direction: [0.3, 0.2, 0.93], intensity: 1.0}   # toward the light
effects: [shadows]
"""


def paths(folder=None) -> RunPaths:
    folder = Path(folder or Path.cwd())
    return RunPaths(folder, folder)


def draw(scene: dict, materials: dict, folder=None) -> tuple[np.ndarray, Counters]:
    counters = Counters()
    return render(load_scene(scene, paths(folder)), materials, counters), counters


def random_ptm(h=16, w=24, seed=0, variant="rgb", space="linear") -> PTMModel:
    rng = np.random.default_rng(seed)
    k = 3 if variant == "rgb" else 1
    coeffs = rng.normal(0.0, 0.15, (h, w, k, 6)).astype(np.float32)
    coeffs[..., 5] += 0.5
    albedo = rng.uniform(0.2, 1.0, (h, w, 3 if variant == "lrgb" else 0)).astype(np.float32)
    return PTMModel(coeffs, albedo, variant, space)


def constant_ptm(value=0.1, h=4, w=4) -> PTMModel:
    coeffs = np.zeros((h, w, 3, 6), np.float32)
    coeffs[..., 5] = value
    return PTMModel(coeffs, np.zeros((h, w, 0), np.float32))


def plane_scene(w=24, h=16, **extra) -> dict:
    scene = yaml.safe_load(PLANE_SCENE)
    scene["camera"].update(width=w, height=h)
    scene["meshes"]["ground"]["size"] = [2.0 * w / h, 2.0]
    scene.update(extra)
    return scene


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A PTM fitted to the procedural demo material through the engine (128 x 128, 36 lights)."""
    from btforge.plugins.demo.procedural import hemisphere_lights, make_material, render_lights
    from btforge.buffers import SampleStack
    material = make_material(128, 128, bumps=40, seed=3)
    lights = hemisphere_lights(36, min_elevation_deg=15.0)
    stack = SampleStack(render_lights(material, lights)[None], lights, np.array([[0.0, 0.0, 1.0]]))
    return fit_ptm(stack, "rgb")[0]


# ----------------------------------------------------------------------------------------------- consistency


def test_plane_scene_equals_relight_texel_for_texel_through_the_engine(tmp_path):
    (tmp_path / "plane.yaml").write_text(PLANE_SCENE)
    graph = {"nodes": {
        "material": {"stage": "demo.material", "params": {"size": [128, 128], "lights": 36, "seed": 3}},
        "fit": {"stage": "ptm.fit", "inputs": {"stack": "material.stack"}},
        "relit": {"stage": "relight.images", "params": {"lights": [[0.3, 0.2, 0.93]]}, "inputs": {"model": "fit.model"}},
        "img": {"stage": "render.image", "params": {"scene": "plane.yaml"}, "inputs": {"stone": "fit.model"}},
    }}
    (tmp_path / "g.yaml").write_text(yaml.safe_dump(graph))
    result = btforge.run(tmp_path / "g.yaml", only=["relit", "img"], cache_dir=tmp_path / "cache")
    relit = result["relit"]["stack"].samples[0, 0]
    image = result["img"]["image"].pixels
    assert image.shape == (128, 128, 3) and image.dtype == np.float32
    np.testing.assert_array_equal(image, relit)          # texel (r, c) lands on pixel (r, c), same radiance
    notes = next(r for r in result.report if r.node == "img").notes
    assert notes["passes"] == {"primary": {"rays": 128 * 128}, "direct": {"lights": 1, "evaluations": 128 * 128}}
    assert "shadows" in notes["skipped"]                   # a plane alone cannot shadow itself: no shadow rays


@pytest.mark.parametrize("variant, space", [("lrgb", "srgb"), ("rgb", "srgb")])
def test_plane_equals_relight_for_other_variants_and_intensity_scales(variant, space):
    model = random_ptm(16, 24, seed=1, variant=variant, space=space)
    light = np.array([[-0.4, 0.5, 0.7]])
    image, _ = draw(plane_scene(lights=[{"type": "directional", "direction": light[0].tolist(), "intensity": 2.5}]),
                    {"stone": model})
    relit = model.evaluate(light)[0, 0]
    np.testing.assert_allclose(image, 2.5 * relit, rtol=1e-6, atol=1e-7)


def test_tangent_frame_follows_the_parameterization_not_the_world():
    """Rotating plane and light together (about the normal) gives the same image: light is taken in the texel frame."""
    model = random_ptm(16, 16, seed=2)
    base = plane_scene(16, 16)
    base["camera"]["extent"] = 2.0
    image, _ = draw(base, {"stone": model})
    turned = plane_scene(16, 16)
    turned["camera"].update(up=[-1, 0, 0])                   # the camera turns with the plane
    turned["meshes"]["ground"]["rotate"] = [0, 0, 90]
    d = np.array([0.3, 0.2, 0.93])
    turned["lights"][0]["direction"] = [-d[1], d[0], d[2]]     # the light rotated by 90 degrees about z
    turned_image, _ = draw(turned, {"stone": model})
    np.testing.assert_allclose(turned_image, image, atol=2e-6)


def test_mirrored_mesh_mirrors_the_texture_frame():
    """scale x -1 shows the texture mirrored, and the light is taken in the mirrored frame (x toward increasing u)."""
    model = random_ptm(16, 24, seed=3)
    scene = plane_scene()
    scene["meshes"]["ground"]["scale"] = [-1, 1, 1]
    mirrored, _ = draw(scene, {"stone": model})
    expected = model.evaluate(np.array([[-0.3, 0.2, 0.93]]))[0, 0][:, ::-1]
    np.testing.assert_array_equal(mirrored, expected)


def test_sphere_frame_at_the_front_and_a_uv_gradient():
    """On a sphere the UV-derived frame at the point facing +z is (x, y, z): a light from +x brightens u-slopes."""
    from btforge.plugins.render.geometry import build_mesh
    spec = load_scene({"camera": {}, "meshes": {"s": {"primitive": "sphere", "material": "m"}}}, paths()).spec
    mesh = build_mesh(spec.meshes[0])
    front = np.argmax(mesh.positions[mesh.triangles].mean(1)[:, 2])
    np.testing.assert_allclose(mesh.corner_t[front].mean(0), [1, 0, 0], atol=0.05)
    np.testing.assert_allclose(mesh.corner_b[front].mean(0), [0, 1, 0], atol=0.05)
    np.testing.assert_allclose(np.cross(mesh.corner_t, mesh.corner_b), mesh.corner_n, atol=1e-5)


def test_obj_file_with_uvs_renders_like_the_primitive(tmp_path):
    obj = "v -1.5 -1 0\nv 1.5 -1 0\nv 1.5 1 0\nv -1.5 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n"
    (tmp_path / "quad.obj").write_text(obj)
    model = random_ptm(16, 24, seed=4)
    primitive, _ = draw(plane_scene(), {"stone": model})
    scene = plane_scene()
    scene["meshes"]["ground"] = {"file": "quad.obj", "material": "stone"}
    from_file, _ = draw(scene, {"stone": model}, tmp_path)
    np.testing.assert_allclose(from_file, primitive, atol=1e-6)


def test_bilinear_lookup_repeat_wrap_and_uv_scale():
    """Twice the UV scale with repeat shows the texture twice; half-texel offsets interpolate neighbours."""
    model = constant_ptm(0.0, 4, 4)
    coeffs = np.array(model.coeffs)
    coeffs[:, :, :, 5] = np.arange(4, dtype=np.float32)[None, :, None]          # columns 0..3
    model = dataclasses.replace(model, coeffs=coeffs)
    scene = plane_scene(8, 4)
    scene["camera"]["extent"] = 2.0
    scene["meshes"]["ground"].update(size=[4.0, 2.0], uv_scale=[2, 1])
    scene["lights"] = [{"type": "directional", "direction": [0, 0, 1]}]
    image, _ = draw(scene, {"stone": model})
    np.testing.assert_allclose(image[0, :, 0], [0, 1, 2, 3, 0, 1, 2, 3], atol=1e-6)
    scene["meshes"]["ground"]["uv_offset"] = [0.125, 0]                        # half a texel
    image, _ = draw(scene, {"stone": model})
    np.testing.assert_allclose(image[0, :, 0], [0.5, 1.5, 2.5, 1.5, 0.5, 1.5, 2.5, 1.5], atol=1e-5)  # wraps 3 -> 0


def test_coordinate_map_is_replayed_at_lookup():
    model = random_ptm(16, 24, seed=5)
    rows, cols = np.mgrid[0:16, 0:24]
    shifted = CoordMap(np.stack([rows, (cols + 5) % 24], -1).astype(np.int32), (16, 24))
    scene = plane_scene()
    scene["meshes"]["ground"]["coord_map"] = True
    image, _ = draw(scene, {"stone": model, "stone_map": shifted})
    direct, _ = draw(plane_scene(), {"stone": model})
    np.testing.assert_array_equal(image, np.roll(direct, -5, axis=1))
    with pytest.raises(BtforgeInputError, match="no coordinate map is wired to 'stone_map'"):
        draw(scene, {"stone": model})


@pytest.mark.parametrize("space", ["linear", "srgb"])
def test_a_blended_map_renders_as_materialize_replays_it(space):
    """An lrgb PTM blends through its rgb form at lookup, as synth.materialize replays the map: a linear one's
    records interpolated with the corners', an srgb one's mixed per corner (display values) before evaluation."""
    model = random_ptm(16, 24, seed=6, variant="lrgb", space=space)
    rng = np.random.default_rng(6)
    rows, cols = np.mgrid[0:16, 0:24]
    coords = np.stack([rows, (cols + 5) % 24], -1).astype(np.int32)
    partner = np.stack([(rows + 7) % 16, cols], -1).astype(np.int32)
    weight = rng.choice([0.0, 1 / 3, 0.7], (16, 24)).astype(np.float32)
    blended = CoordMap(coords, (16, 24), blend_coords=partner, blend_weight=weight)
    scene = plane_scene()
    scene["meshes"]["ground"]["coord_map"] = True
    image, _ = draw(scene, {"stone": model, "stone_map": blended})
    replayed = blended.apply(model)
    assert replayed.variant == "rgb" and replayed.space == space
    direct, _ = draw(plane_scene(), {"stone": replayed})
    np.testing.assert_allclose(image, direct, rtol=1e-5, atol=1e-6)  # the same sums in another order (float32)
    unblended, _ = draw(scene, {"stone": model, "stone_map": CoordMap(coords, (16, 24))})
    assert np.abs(image - unblended).max() > 0.01


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2 ** 16), scale=st.sampled_from([1e-4, 0.3, 40.0]),
       weights=st.sampled_from([(0.0, 1.0), (1e-7, 1 - 1e-7), (0.0, 1 / 3, 0.5, 0.7)]),
       variant=st.sampled_from(["rgb", "lrgb"]))
def test_a_blended_map_on_hard_srgb_records_renders_as_materialize_replays_it(seed, scale, weights, variant):
    """sRGB records mixed per corner before evaluation, as materialize mixes them: tiny, ordinary and huge
    coefficients (most display values then clipped at 0 or 1), blend weights at and next to 0 and 1."""
    rng = np.random.default_rng(seed)
    k = 3 if variant == "rgb" else 1
    coeffs = rng.normal(0.0, scale, (16, 24, k, 6)).astype(np.float32)
    albedo = rng.uniform(0.0, 1.0, (16, 24, 3 if variant == "lrgb" else 0)).astype(np.float32)
    model = PTMModel(coeffs, albedo, variant, "srgb")
    rows, cols = np.mgrid[0:16, 0:24]
    coords = np.stack([rows, (cols + 5) % 24], -1).astype(np.int32)
    partner = rng.integers(0, [16, 24], (16, 24, 2)).astype(np.int32)
    blended = CoordMap(coords, (16, 24), partner, rng.choice(weights, (16, 24)).astype(np.float32))
    scene = plane_scene()
    scene["meshes"]["ground"]["coord_map"] = True
    image, _ = draw(scene, {"stone": model, "stone_map": blended})
    direct, _ = draw(plane_scene(), {"stone": blended.apply(model)})
    assert np.isfinite(image).all() and image.min() >= 0 and image.max() <= 1 + 1e-6  # decoded values lie in [0, 1]
    # the same float32 sums in another order, then the clip and the decode (slope below 2.3 on [0, 1]): a few 1e-6
    np.testing.assert_allclose(image, direct, rtol=1e-5, atol=1e-5)


# ----------------------------------------------------------------------------------------------- models


@dataclasses.dataclass(frozen=True, eq=False)
class ToyViewModel(ReflectanceModel):
    """Albedo x cos(light) x a view lobe that equals 1 at the canonical view (0, 0, 1)."""

    type_name: ClassVar[str] = "ToyViewModel"
    texel_fields: ClassVar[tuple] = ("albedo",)
    view_dependent: ClassVar[bool] = True
    albedo: np.ndarray

    @property
    def channels(self):
        return ("R", "G", "B")

    def evaluate(self, lights, views=None):
        lights = np.asarray(lights, np.float32)
        vz = np.ones(1, np.float32) if views is None else np.asarray(views, np.float32)[:, 2]
        lobe = 0.3 + 0.7 * np.clip(vz, 0, 1) ** 8                                   # [V]
        shade = np.maximum(lights[:, 2], 0)                                          # [L]
        return (lobe[:, None, None, None, None] * shade[None, :, None, None, None] * self.albedo[None, None]
                ).astype(np.float32)

    def evaluate_texels(self, rows, cols, lights, views=None):
        vz = np.ones(len(rows), np.float32) if views is None else np.asarray(views)[:, 2]
        lobe = 0.3 + 0.7 * np.clip(vz, 0, 1) ** 8
        return (self.albedo[rows, cols] * np.maximum(lights[:, 2:3], 0) * lobe[:, None]).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class NoTexelsModel(ToyViewModel):
    type_name: ClassVar[str] = "NoTexelsModel"
    evaluates_texels: ClassVar[bool] = False  # declares that it has no per-texel evaluation


def test_model_without_scattered_evaluation_fails_naming_its_type():
    model = NoTexelsModel(np.ones((4, 4, 3), np.float32))
    with pytest.raises(BtforgeInputError, match="model NoTexelsModel cannot be rendered yet"):
        draw(plane_scene(), {"stone": model})
    with pytest.raises(BtforgeInputError, match="material 'stone'.*bound to no model"):
        draw(plane_scene(), {})


def test_one_channel_models_render_grey():
    coeffs = np.zeros((4, 4, 1, 6), np.float32)
    coeffs[..., 5] = 0.25
    model = PTMModel(coeffs, np.zeros((4, 4, 0), np.float32), channel_names=("Y",))
    image, _ = draw(plane_scene(8, 8), {"stone": model})
    np.testing.assert_allclose(image, 0.25, rtol=1e-6)


# ----------------------------------------------------------------------------------------------- effects


def shadow_scene(effects) -> dict:
    return {
        "camera": {"type": "orthographic", "width": 48, "height": 48, "position": [0, 0, 5], "look_at": [0, 0, 0],
                   "extent": 4.0},
        "meshes": {"ground": {"primitive": "plane", "size": 4.0, "material": "stone"},
                   "ring": {"primitive": "torus", "major_radius": 0.6, "minor_radius": 0.2, "position": [0, 0, 1.0],
                            "segments": [32, 16]}},
        "lights": [{"type": "directional", "direction": [0.5, 0.3, 0.8]}],
        "effects": effects,
    }


def test_shadows_off_removes_shadow_rays_and_changes_only_shadowed_pixels():
    model = constant_ptm(0.5)
    on, c_on = draw(shadow_scene(["shadows"]), {"stone": model})
    off, c_off = draw(shadow_scene([]), {"stone": model})
    assert c_on.passes["shadows"]["rays"] > 0
    assert "shadows" not in c_off.passes and "shadows" not in c_off.skipped
    changed = np.any(on != off, axis=-1)
    assert 20 < changed.sum() < 48 * 48 // 2
    assert np.all(on[changed] == 0) and np.all(off[changed] > 0)   # only where the torus hides the light
    # the same scene without the torus: nothing can occlude, so no shadow rays even with the effect on
    lone = shadow_scene(["shadows"])
    del lone["meshes"]["ring"]
    _, c_lone = draw(lone, {"stone": model})
    assert "shadows" not in c_lone.passes and "nothing can occlude" in c_lone.skipped["shadows"]


def env_scene(effects, method="importance", env=True, **light) -> dict:
    scene = shadow_scene(effects)
    scene["lights"][0]["intensity"] = 0.5
    if env:
        scene["lights"].append({"type": "environment", "sky": {"sun": [-0.3, 0.2, 0.9], "sun_intensity": 20.0},
                                "method": method, "samples": 16, "order": 3, **light})
    return scene


@pytest.mark.parametrize("method", ["importance", "sh"])
def test_environment_off_removes_its_pass_and_only_adds_light(method):
    model = constant_ptm(0.3)
    on, c_on = draw(env_scene(["environment", "shadows"], method), {"stone": model})
    off, c_off = draw(env_scene(["shadows"], method), {"stone": model})
    without, _ = draw(env_scene(["shadows"], env=False), {"stone": model})
    entry = c_on.passes["environment"]["lights[1]"]          # reported under the light's place in the scene
    assert entry["method"] == method
    if method == "importance":
        assert entry["evaluations"] > 0 and entry["shadow_rays"] > 0
    else:
        assert entry["sh_rotations"] > 0
    assert "environment" not in c_off.passes
    np.testing.assert_array_equal(off, without)          # an environment light with the effect off does nothing
    assert np.all(on >= off) and (on > off).mean() > 0.9
    # effect on but no environment light: no environment pass
    _, c_none = draw(env_scene(["environment"], env=False), {"stone": model})
    assert "environment" not in c_none.passes and "no environment light" in c_none.skipped["environment"]


def test_environment_methods_integrate_a_uniform_environment(tmp_path):
    """A constant PTM c under a uniform environment of radiance 1 reflects 2 pi c with both methods."""
    from btforge.plugins.stackio.images import write_exr
    write_exr(tmp_path / "white.exr", np.ones((32, 64, 3), np.float32))
    scene = plane_scene(8, 8, effects=["environment"])
    values = {}
    for method, n in (("importance", 512), ("sh", 64)):
        scene["lights"] = [{"type": "environment", "file": "white.exr", "method": method, "samples": n, "order": 2}]
        image, counters = draw(scene, {"stone": constant_ptm(0.1)}, tmp_path)
        values[method] = image
    np.testing.assert_allclose(values["sh"], 2 * np.pi * 0.1, rtol=1e-3)
    np.testing.assert_allclose(values["importance"], 2 * np.pi * 0.1, rtol=0.03)


def test_view_dependence_only_for_view_dependent_models():
    scene = plane_scene(24, 16)
    scene["camera"].update(type="perspective", position=[0.5, -1.5, 2.0], look_at=[0, 0, 0], fov=60)
    toy = ToyViewModel(np.full((8, 8, 3), 0.8, np.float32))
    on, c_on = draw({**scene, "effects": ["view_dependence"]}, {"stone": toy})
    off, c_off = draw({**scene, "effects": []}, {"stone": toy})
    assert c_on.passes["view_dependence"]["views"] > 0 and "view_dependence" not in c_off.passes
    # where each pixel's ray meets the plane (z = 0; u along +x, v along +y, so the texel frame is the world's)
    from btforge.plugins.render.renderer import camera_rays
    origins, dirs = camera_rays(load_scene(scene, paths()).spec.camera, 1)
    points = origins - (origins[:, 2] / dirs[:, 2])[:, None] * dirs
    margin = np.maximum(np.abs(points[:, 0]) - 1.5, np.abs(points[:, 1]) - 1.0).reshape(16, 24)
    inside, outside = margin < -1e-3, margin > 1e-3
    lit = 0.8 * 0.93 / np.linalg.norm([0.3, 0.2, 0.93])             # albedo x the light's local z
    lobe = (0.3 + 0.7 * np.clip(-dirs[:, 2], 0, 1) ** 8).reshape(16, 24)   # at the true view (V.N = -d_z)
    assert inside.sum() > 100 and outside.sum() > 20
    np.testing.assert_allclose(off[inside], lit, rtol=1e-5)         # off: every texel at its canonical view
    np.testing.assert_allclose(on[inside], np.repeat(lit * lobe[inside][:, None], 3, 1), rtol=1e-5)
    assert lobe[inside].max() - lobe[inside].min() > 0.05           # the views really differ across the plane
    assert np.all(on[outside] == 0) and np.all(off[outside] == 0)   # the background has no view to depend on
    ptm = random_ptm(8, 8, seed=6)                    # a PTM depends on the light only: no view pass, same image
    p_on, cp_on = draw({**scene, "effects": ["view_dependence"]}, {"stone": ptm})
    p_off, _ = draw({**scene, "effects": []}, {"stone": ptm})
    assert "view_dependence" not in cp_on.passes
    np.testing.assert_array_equal(p_on, p_off)


def sphere_scene(effects, samples=4) -> dict:
    return {"camera": {"type": "orthographic", "width": 40, "height": 40, "position": [0, 0, 5], "extent": 2.4,
                       "samples": samples},
            "meshes": {"ball": {"primitive": "sphere", "radius": 1.0, "material": "stone", "segments": [48, 24]}},
            "lights": [{"type": "directional", "direction": [0, 0, 1]}], "effects": effects}


def test_antialias_off_casts_one_ray_per_pixel_and_changes_mostly_the_silhouette():
    model = constant_ptm(0.8)
    on, c_on = draw(sphere_scene(["antialias"]), {"stone": model})
    off, c_off = draw(sphere_scene([]), {"stone": model})
    assert c_on.passes["primary"]["rays"] == 4 * 40 * 40 and c_on.passes["antialias"]["samples_per_pixel"] == 4
    assert c_off.passes["primary"]["rays"] == 40 * 40 and "antialias" not in c_off.passes
    diff = np.abs(on - off).max(-1)
    hit = off.max(-1) > 0
    inner = hit.copy()
    for axis in (0, 1):
        for shift in (1, -1):
            inner &= np.roll(hit, shift, axis)
    assert diff[~inner & (diff > 0.05)].size > 10 and np.all(diff[inner] < 0.05)


def test_tonemap_changes_only_the_display_encoding(tmp_path):
    model = constant_ptm(0.2)
    stage = btforge.stage("render.image")
    write = btforge.stage("render.write_image")
    images, notes = {}, {}
    for flag, effects in (("on", ["tonemap"]), ("off", [])):
        scene = plane_scene(8, 8, effects=effects, exposure=1.0)
        image = stage(scene=scene, stone=model)["image"]
        ctx = StageContext("w", paths=paths(tmp_path))
        write(ctx=ctx, image=image, path=f"{flag}.png")
        images[flag], notes[flag] = image, ctx.notes
    np.testing.assert_array_equal(images["on"].pixels, images["off"].pixels)
    assert images["on"].tonemap and not images["off"].tonemap
    assert "tonemap" in notes["on"] and "tonemap" not in notes["off"]
    from PIL import Image as PILImage
    on_png = np.asarray(PILImage.open(tmp_path / "on.png"))
    off_png = np.asarray(PILImage.open(tmp_path / "off.png"))
    assert on_png[0, 0, 0] == round(255 * (1.055 * 0.4 ** (1 / 2.4) - 0.055)) and off_png[0, 0, 0] == round(0.2 * 255)


def test_point_light_falls_off_with_the_square_of_distance():
    model = constant_ptm(0.5)
    for height in (1.0, 2.0):
        scene = plane_scene(8, 8)
        scene["lights"] = [{"type": "point", "position": [0, 0, height], "intensity": 4.0}]
        image, _ = draw(scene, {"stone": model})
        d2 = height ** 2 + 2 * 0.125 ** 2              # the four central pixels sit at (+-0.125, +-0.125, 0)
        np.testing.assert_allclose(image[3:5, 3:5], 0.5 * 4.0 / d2, rtol=1e-5)


def test_point_light_shadow_darkens_exactly_the_occluded_region():
    """A square occluder between a point light and the ground: shadows black out exactly the ground points whose
    segment to the light crosses the square; a plane beyond the light (on the same lines) shadows nothing."""
    from btforge.plugins.render.renderer import camera_rays
    light = np.array([1.5, 0.0, 2.0])
    scene = {
        "camera": {"type": "orthographic", "width": 64, "height": 64, "position": [0, 0, 5], "look_at": [0, 0, 0],
                   "extent": 4.0},
        "meshes": {"ground": {"primitive": "plane", "size": 4.0, "material": "stone"},
                   "square": {"primitive": "plane", "size": 0.4, "position": [0, 0, 0.5]},
                   # out of view, above and beyond the light: only a ray running past the light could reach it
                   "beyond": {"primitive": "plane", "size": [1.0, 4.0], "position": [2.6, 0, 3.0]}},
        "lights": [{"type": "point", "position": light.tolist(), "intensity": 4.0}],
    }
    model = constant_ptm(0.5)
    on, c_on = draw({**scene, "effects": ["shadows"]}, {"stone": model})
    off, c_off = draw({**scene, "effects": []}, {"stone": model})
    assert c_on.passes["shadows"]["rays"] > 0 and "shadows" not in c_off.passes
    origins, _ = camera_rays(load_scene(scene, paths()).spec.camera, 1)
    ground = origins[:, :2].reshape(64, 64, 2)                      # straight down: the ground point under each pixel
    crossing = ground + 0.25 * (light[:2] - ground)                 # where the segment to the light is at z = 0.5
    edge = np.abs(crossing).max(-1) - 0.2                           # < 0: through the square
    seen_square = np.abs(ground).max(-1) < 0.2 + 1e-3              # the camera sees the square there, not the ground
    shadowed = (edge < -1e-3) & ~seen_square
    unshadowed = (edge > 1e-3) & ~seen_square
    assert shadowed.sum() > 50
    assert np.all(on[shadowed] == 0) and np.all(off[shadowed] > 0)
    np.testing.assert_array_equal(on[unshadowed], off[unshadowed])  # no shadow from the plane beyond the light
    np.testing.assert_array_equal(on[seen_square], off[seen_square])


def test_sh_and_importance_agree_on_a_band_limited_environment(tmp_path):
    """Under an environment of bands 0-1 the SH method is exact for any model (orthogonality), whatever the frame:
    on a sphere (frames in every orientation) importance sampling must converge to it."""
    from btforge.plugins.render.envmap import pixel_directions
    from btforge.plugins.stackio.images import write_exr
    d = pixel_directions(64, 128, np.array([0.0, 0, 1]), np.array([1.0, 0, 0]), 0.0)
    radiance = 1.0 + 0.6 * d[..., 0:1] + 0.3 * d[..., 2:3] * np.array([1.0, 0.5, 0.2])
    write_exr(tmp_path / "smooth.exr", radiance.astype(np.float32))
    scene = sphere_scene(["environment"])
    scene["meshes"]["ball"]["rotate"] = [30, 20, 0]
    images = {}
    for method, n in (("sh", 64), ("importance", 2048)):
        scene["lights"] = [{"type": "environment", "file": "smooth.exr", "method": method, "samples": n, "order": 2}]
        images[method], _ = draw(scene, {"stone": random_ptm(16, 32, seed=7)}, tmp_path)
    hit = images["sh"].max(-1) > 0
    rel = np.abs(images["importance"][hit] - images["sh"][hit]).mean() / images["sh"][hit].mean()
    assert rel < 0.01          # measured 0.4% (3.6% with 64 samples)
