"""Environment orientation, and that the render report says what ran, per light, and what was asked but skipped."""
import math

import numpy as np
import pytest

from btforge.plugins.render import renderer
from btforge.plugins.stackio.images import write_exr
from test_render import ToyViewModel, constant_ptm, draw, plane_scene, random_ptm, shadow_scene

H, W = 16, 32


def marker_map(folder, row: int, col: int, value: float = 100.0, name: str = "marker.exr") -> str:
    """A black lat-long map with one bright pixel."""
    pixels = np.zeros((H, W, 3), np.float32)
    pixels[row, col] = value
    write_exr(folder / name, pixels)
    return name


def expected_direction(row: int, col: int) -> np.ndarray:
    """The documented layout with the defaults (up +z, forward +x): polar angle from +z, azimuth from +x toward
    forward x up = -y (clockwise seen from above; from inside, the panorama reads left to right)."""
    theta = math.pi * (row + 0.5) / H
    phi = 2 * math.pi * (col + 0.5) / W
    return np.array([math.sin(theta) * math.cos(phi), -math.sin(theta) * math.sin(phi), math.cos(theta)])


# ----------------------------------------------------------------------------------------------- orientation


def test_a_map_pixel_lights_from_its_documented_direction(tmp_path):
    """Importance sampling puts all the energy of a one-pixel map in that pixel's direction: the render equals one
    directional light from there (a random PTM depends on both light components, so a mirror would show)."""
    row, col = 4, 8
    name = marker_map(tmp_path, row, col)
    model = random_ptm(16, 24, seed=11)
    env = plane_scene(effects=["environment"],
                      lights=[{"type": "environment", "file": name, "method": "importance", "samples": 4}])
    lit, counters = draw(env, {"stone": model}, tmp_path)
    assert counters.passes["environment"]["lights[0]"]["lights"] == 1
    d = expected_direction(row, col)
    assert d[1] < -0.7                                     # a quarter turn from forward: toward -y, not +y
    omega = (2 * math.pi / W) * (math.pi / H) * math.sin(math.pi * (row + 0.5) / H)
    one = plane_scene(lights=[{"type": "directional", "direction": d.tolist(), "intensity": 100.0 * omega}])
    expected, _ = draw(one, {"stone": model})
    np.testing.assert_allclose(lit, expected, rtol=1e-5, atol=1e-7)


def test_sh_projection_uses_the_same_layout(tmp_path):
    """The band-1 SH coefficients of a one-pixel map point at the pixel's direction (y, z, x order)."""
    from btforge.plugins.render.envmap import project_sh
    from btforge.plugins.render.scene import LightSpec
    row, col = 5, 21
    pixels = np.zeros((H, W, 3), np.float32)
    pixels[row, col] = 1.0
    coeffs = project_sh(pixels, LightSpec(0, "environment", (1.0, 1.0, 1.0)), 2)[:, 0]
    band1 = np.array([coeffs[3], coeffs[1], coeffs[2]])
    np.testing.assert_allclose(band1 / np.linalg.norm(band1), expected_direction(row, col), atol=1e-6)


def background_scene(name: str, effects=("environment",), **light) -> dict:
    """A camera at the origin facing +x (the map's forward) with +z up, seeing only the background."""
    return {"camera": {"type": "perspective", "width": W, "height": H, "position": [0, 0, 0], "look_at": [1, 0, 0],
                       "up": [0, 0, 1], "fov": 60},
            "meshes": {"behind": {"primitive": "plane", "size": 1.0, "position": [-50, 0, 0]}},
            "lights": [{"type": "environment", "file": name, **light}],
            "background": "environment", "effects": list(effects)}


def test_background_shows_the_map_left_to_right_from_inside(tmp_path):
    """A marker a few columns right of the map's left edge (which faces forward) appears right of the view's
    centre; rotate turns the map clockwise seen from above, so the marker moves further right."""
    name = marker_map(tmp_path, 7, 2)                      # just above the horizon, 28 degrees from forward
    image, _ = draw(background_scene(name), {}, tmp_path)
    ys, xs = np.nonzero(image[..., 0] > 0)
    assert len(xs) and np.all(xs > W // 2) and abs(xs.mean() - 23.4) < 2.5   # tan 28 / (2 tan 30) -> column 23.4
    assert np.all(ys < H // 2 + 1)
    turned, _ = draw(background_scene(name, rotate=10), {}, tmp_path)
    assert np.nonzero(turned[..., 0] > 0)[1].mean() > xs.mean() + 1.5


# ----------------------------------------------------------------------------------------------- what runs


def test_environment_background_is_black_and_unread_without_the_effect(tmp_path, monkeypatch):
    name = marker_map(tmp_path, 7, 2)
    on, _ = draw(background_scene(name), {}, tmp_path)
    assert on.max() > 0                                    # the effect on: the background shows the map
    read = []
    original = renderer.environment_pixels
    monkeypatch.setattr(renderer, "environment_pixels", lambda light, scene: read.append(light) or
                        original(light, scene))
    off, counters = draw(background_scene(name, effects=[]), {}, tmp_path)
    assert np.all(off == 0) and read == []
    assert "background is black" in counters.skipped["environment"]
    draw(background_scene(name), {}, tmp_path)
    assert len(read) == 1                                  # read once for the whole image, when used


def test_every_environment_light_is_reported(tmp_path):
    name = marker_map(tmp_path, 4, 8)
    scene = plane_scene(effects=["environment"], lights=[
        {"type": "environment", "sky": {"sun": [0.2, 0.1, 0.9]}, "method": "importance", "samples": 8},
        {"type": "directional", "direction": [0, 0, 1]},
        {"type": "environment", "file": name, "method": "sh", "order": 2}])
    _, counters = draw(scene, {"stone": constant_ptm(0.2)}, tmp_path)
    env = counters.passes["environment"]
    assert sorted(env) == ["lights[0]", "lights[2]"]
    assert env["lights[0]"]["method"] == "importance" and env["lights[0]"]["evaluations"] > 0
    assert env["lights[2]"] == {"method": "sh", "order": 2, "sh_rotations": 16 * 24}


def sh_only_scene(effects, direct: bool = False) -> dict:
    scene = shadow_scene(effects)                          # a plane under a torus: something can occlude
    env = {"type": "environment", "sky": {"sun": [0.3, 0.2, 0.9]}, "method": "sh", "order": 3}
    scene["lights"] = (scene["lights"] if direct else []) + [env]
    return scene


def test_sh_environment_alone_runs_no_shadows_views_or_record_gathering(monkeypatch):
    """The SH method takes no shadow rays and evaluates at the canonical view: with it alone, the report says so
    instead of counting views, and no per-sample model records are gathered."""
    gathered = []
    original = renderer.ModelShader._gather_model
    monkeypatch.setattr(renderer.ModelShader, "_gather_model", lambda self: gathered.append(1) or original(self))
    toy = ToyViewModel(np.full((8, 8, 3), 0.5, np.float32))
    effects = ["shadows", "environment", "view_dependence"]
    _, counters = draw(sh_only_scene(effects), {"stone": toy})
    assert counters.passes["environment"]["lights[0]"]["sh_rotations"] > 0
    assert "shadows" not in counters.passes and "view_dependence" not in counters.passes
    assert "sh method (lights[0]) ignores shadows" in counters.skipped["shadows"]
    assert "canonical view" in counters.skipped["view_dependence"]
    assert gathered == []
    # with a directional light too, both run for it, and the report says the SH light had neither
    _, counters = draw(sh_only_scene(effects, direct=True), {"stone": toy})
    assert counters.passes["shadows"]["rays"] > 0 and counters.passes["view_dependence"]["views"] > 0
    assert counters.skipped["shadows"].startswith("not for lights[1]")
    assert counters.skipped["view_dependence"].startswith("not for lights[1]")
    assert gathered


def test_view_dependence_on_a_ptm_is_reported_skipped():
    _, counters = draw(plane_scene(effects=["view_dependence"]), {"stone": random_ptm()})
    assert "view_dependence" not in counters.passes
    assert "no material's model depends on the view" in counters.skipped["view_dependence"]
    _, counters = draw(plane_scene(effects=[]), {"stone": random_ptm()})
    assert "view_dependence" not in counters.skipped      # not asked for: nothing to report


@pytest.mark.parametrize("effects", [["shadows"], []])
def test_shadows_without_any_light_are_reported_skipped(effects):
    scene = shadow_scene(effects)
    scene["lights"] = []
    image, counters = draw(scene, {"stone": constant_ptm(0.5)})
    assert np.all(image == 0) and "shadows" not in counters.passes
    assert ("no light" in counters.skipped.get("shadows", "")) == bool(effects)
