"""Light calibration from mirror spheres: rendered spheres with known lights, the real chrome ball of psm_uw."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from btforge.cli import main
from btforge.plugins.calibrate.bench import implied_sphere
from btforge.plugins.calibrate.lights import calibrate, image_list
from btforge.plugins.calibrate.testing import fibonacci_lights, render_capture
from btforge.plugins.calibrate.sphere import Circle
from btforge.plugins.stackio.lightfile import read_light_file

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))


def test_rendered_spheres_jpeg_within_one_degree(tmp_path):
    lights = fibonacci_lights(14)
    paths = render_capture(tmp_path, lights, [(110, 90, 42), (230, 100, 36)])
    result = calibrate(image_list(tmp_path))
    assert len(result.spheres) == 2
    for (sx, sy, sr) in [(110, 90, 42), (230, 100, 36)]:
        c = min(result.spheres, key=lambda c: math.hypot(c.x - sx, c.y - sy))
        assert math.hypot(c.x - sx, c.y - sy) < 1.0 and abs(c.r - sr) < 1.0
    assert result.found.all()
    error = angles_deg(result.lights, lights)
    assert error.mean() <= 1.0, error.round(2)
    assert (result.confidence > 0).all() and (result.confidence <= 1).all()
    assert [p.name for p in result.images] == [p.name for p in paths]


def test_perspective_with_focal(tmp_path):
    lights = fibonacci_lights(10, seed=3)
    render_capture(tmp_path, lights, [(200, 80, 40)], focal=400.0)
    ortho = angles_deg(calibrate(image_list(tmp_path)).lights, lights)
    persp = angles_deg(calibrate(image_list(tmp_path), focal=400.0).lights, lights)
    assert persp.mean() <= 1.0 and persp.mean() < ortho.mean(), (persp.mean(), ortho.mean())


def test_perspective_with_an_off_centre_principal_point(tmp_path):
    """A cropped photograph: the principal point is far from the image centre, and assuming the centre costs."""
    lights = fibonacci_lights(10, seed=4)
    render_capture(tmp_path, lights, [(200, 80, 40)], focal=400.0, principal=(230.0, 180.0))
    centred = angles_deg(calibrate(image_list(tmp_path), focal=400.0).lights, lights)
    given = angles_deg(calibrate(image_list(tmp_path), focal=400.0, principal=(230.0, 180.0)).lights, lights)
    assert given.mean() <= 1.0 and centred.mean() > 4.0, (given.mean(), centred.mean())


def test_principal_point_option_is_checked(tmp_path, capsys):
    render_capture(tmp_path, fibonacci_lights(3), [(120, 100, 45)])
    out = str(tmp_path / "a.lp")
    assert main(["calibrate", str(tmp_path), "--out", out, "--focal", "300", "--principal", "1"]) == 2
    assert "X,Y" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path), "--out", out, "--principal", "100,90"]) == 2
    assert "needs a focal length" in capsys.readouterr().err
    assert main(["calibrate", str(tmp_path), "--out", out, "--focal", "300", "--principal", "160,120"]) == 0


def test_missing_highlight_named_and_left_out(tmp_path, capsys):
    lights = fibonacci_lights(8, seed=5)
    render_capture(tmp_path, lights, [(120, 100, 45)], dark=(3,))
    out = tmp_path / "out" / "dirs.lp"
    code = main(["calibrate", str(tmp_path), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 1
    assert "shot_03.jpg" in err and "too dim" in err
    entries = read_light_file(out, require_images=True)
    assert [e.filename.rsplit("/", 1)[-1] for e in entries] == [f"shot_{i:02d}.jpg" for i in range(8) if i != 3]
    # the remaining lights stay with their own images: nothing shifted
    got = np.array([e.light for e in entries])
    assert angles_deg(got, np.delete(lights, 3, axis=0)).max() < 2.0
    assert (out.parent / "dirs_calibration.png").stat().st_size > 0


def test_apply_lights_to_a_later_capture(tmp_path):
    lights = fibonacci_lights(6, seed=7)
    (tmp_path / "ball").mkdir()
    (tmp_path / "object").mkdir()
    render_capture(tmp_path / "ball", lights, [(120, 100, 45)])
    for i in range(6):
        Image.new("RGB", (320, 240), (40 + 30 * i,) * 3).save(tmp_path / "object" / f"obj_{i}.png")
    out = tmp_path / "object" / "dirs.lp"
    assert main(["calibrate", str(tmp_path / "ball"), "--out", str(out), "--apply-to",
                 str(tmp_path / "object" / "*.png")]) == 0
    entries = read_light_file(out, require_images=True)
    assert [e.filename for e in entries] == [f"obj_{i}.png" for i in range(6)]
    assert angles_deg(np.array([e.light for e in entries]), lights).max() < 2.0


def test_bad_sphere_argument_is_a_clear_error(tmp_path, capsys):
    render_capture(tmp_path, fibonacci_lights(3), [(120, 100, 45)])
    assert main(["calibrate", str(tmp_path), "--out", str(tmp_path / "a.lp"), "--sphere", "1,2"]) == 2
    assert "X,Y,R" in capsys.readouterr().err


def test_given_sphere_is_used(tmp_path):
    lights = fibonacci_lights(6, seed=2)
    render_capture(tmp_path, lights, [(120, 100, 45)])
    result = calibrate(image_list(tmp_path), [Circle(120, 100, 45)])
    assert angles_deg(result.lights, lights).mean() < 1.0


@pytest.mark.shared_data
def test_psm_uw_chrome_sphere():
    folder = SHARED / "rti" / "psm_uw"
    if not folder.is_dir():
        pytest.skip("../shared/data is not present")
    result = calibrate(image_list(folder / "chrome"))
    truth = np.loadtxt(folder / "lights.txt", skiprows=1)
    error = angles_deg(result.lights, truth)
    # Measured: 2.66 mean, 7.89 worst; the goal of 2.5 / 6 is not reached (README, "The RTI user's day":
    # lights.txt implies a sphere 13% larger than the visible ball, or a camera whose focal length is unknown).
    assert error.mean() <= 2.7 and error.max() <= 8.0, error.round(2)
    # The highlights themselves agree with lights.txt: the sphere those lights imply places them within 1.4 px.
    xy = np.array([[h.x, h.y] for h in result.highlights[0]])
    implied, rms = implied_sphere(xy, truth)
    assert rms <= 1.4 and implied.r > 1.1 * result.spheres[0].r, (implied, rms)
    # Nor does a camera explain it: the wide lens the lights imply would stretch the outline by over a pixel
    # toward its principal point; the outline is round to a third of that.
    from btforge.plugins.calibrate.bench import implied_camera
    from btforge.plugins.calibrate.lights import load_luminance
    from btforge.plugins.calibrate.sphere import measure_stretch, outline_stretch
    focal, principal = implied_camera(xy, truth / np.linalg.norm(truth, axis=1, keepdims=True), result.spheres[0],
                                      result.shape)
    seen, se, _ = measure_stretch(result.spheres[0], np.median(load_luminance(result.images), axis=0))
    assert outline_stretch(result.spheres[0], focal, principal) > 1.0 and seen + 3 * se < 0.7, (focal, principal, seen)
    # So estimating the focal length from the outline keeps the orthographic camera.
    assert calibrate(image_list(folder / "chrome"), focal="auto").focal is None


def test_outline_is_found_to_a_tenth_of_a_pixel(tmp_path):
    """The sub-pixel outline fit: the rendered ball's centre and radius within 0.15 px (the strongest edge pixels
    alone put the radius 0.1-0.2 px short)."""
    lights = fibonacci_lights(10, seed=4)
    render_capture(tmp_path, lights, [(150, 110, 50)])
    (found,) = calibrate(image_list(tmp_path)).spheres
    assert math.hypot(found.x - 150, found.y - 110) < 0.15 and abs(found.r - 50) < 0.15, found


def test_outline_one_level_above_a_black_ball():
    """A black ball against a wall one 8-bit level brighter (psm_uw's chrome ball): the outline is still found to
    a third of a pixel, and a bright reflection inside the rim does not pull it."""
    from btforge.plugins.calibrate.sphere import refine_limb
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:240, 0:320].astype(np.float64)
    truth = Circle(161.3, 118.6, 90.4)
    dist = np.hypot(xx - truth.x, yy - truth.y)
    wall = np.where(dist > truth.r, 1.0, 0.0) + rng.normal(0, 0.3, dist.shape)
    crescent = (dist < truth.r - 3) & (dist > truth.r - 12) & (xx < truth.x - 60)  # a window reflected on the rim
    image = (np.clip(np.round(np.where(crescent, 40.0, wall)), 0, 255) / 255).astype(np.float32)
    found = refine_limb(Circle(160.0, 118.0, 89.0), [image])
    assert math.hypot(found.x - truth.x, found.y - truth.y) < 0.35 and abs(found.r - truth.r) < 0.35, found


@settings(max_examples=20, deadline=None)
@given(kind=st.sampled_from(["black", "saturated", "noise", "step", "half"]), radius=st.integers(6, 60),
       seed=st.integers(0, 10))
def test_outline_fit_on_hard_images(kind, radius, seed):
    """Flat, noisy or half-visible outlines: the sub-pixel fit keeps the circle or moves it a little, the stretch is
    finite or NaN, and a focal length is estimated only from a real stretch."""
    from btforge.plugins.calibrate.sphere import estimate_focal, measure_stretch, refine_limb
    rng = np.random.default_rng(seed)
    size = 2 * radius + 30
    circle = Circle(size / 2 + 0.3, size / 2 - 0.2, float(radius))
    yy, xx = np.mgrid[0:size, 0:size]
    outside = np.hypot(xx - circle.x, yy - circle.y) > circle.r
    image = {"black": np.zeros((size, size)), "saturated": np.ones((size, size)),
             "noise": rng.uniform(0, 1, (size, size)), "step": np.where(outside, 0.5, 0.1),
             "half": np.where(outside & (yy < circle.y), 0.5, 0.1)}[kind].astype(np.float32)
    start = Circle(circle.x + 0.7, circle.y - 0.5, circle.r + 0.6)
    fitted = refine_limb(start, [image])
    assert np.isfinite([fitted.x, fitted.y, fitted.r]).all() and fitted.r > 0
    if kind in ("step", "half"):
        assert math.hypot(fitted.x - circle.x, fitted.y - circle.y) < 0.3 and abs(fitted.r - circle.r) < 0.3, fitted
    else:
        assert fitted == start
    stretch, se, direction = measure_stretch(fitted, image)
    assert (math.isnan(stretch) and kind not in ("step",)) or (stretch >= 0 and se >= 0 and -90 <= direction < 90)
    focal, note = estimate_focal(fitted, image, (0.0, 0.0))
    assert note and (focal is None or (math.isfinite(focal) and focal > 0))
    if kind != "half":
        assert focal is None, note  # a round outline, or none: orthographic


def test_robust_circle_fit_ignores_outliers():
    from btforge.plugins.calibrate.sphere import _fit_circle
    rng = np.random.default_rng(0)
    angle = rng.uniform(0, np.pi, 200)  # half an outline, as on a ball whose lower half is lost in the dark
    radius = 40 + rng.normal(0, 0.05, 200)
    radius[:40] -= rng.uniform(3, 8, 40)  # a reflection's inner edge
    fitted = _fit_circle(10 + radius * np.cos(angle), 20 - radius * np.sin(angle), Circle(11, 19, 38))
    assert math.hypot(fitted.x - 10, fitted.y - 20) < 0.05 and abs(fitted.r - 40) < 0.05, fitted
    assert _fit_circle(np.arange(5.0), np.arange(5.0), Circle(0, 0, 1)) is None


def test_outline_stretch_and_implied_camera_of_a_perspective_render(tmp_path):
    """A wide lens stretches a sphere's outline toward the principal point by as much as the tangent cone
    predicts; the known lights give back the camera (a diagnostic of ``bench calibrate``), and so does the
    outline alone (``focal='auto'``)."""
    from btforge.plugins.calibrate.bench import implied_camera
    from btforge.plugins.calibrate.lights import load_luminance
    from btforge.plugins.calibrate.sphere import measure_stretch, outline_stretch
    lights = fibonacci_lights(10, seed=3)
    render_capture(tmp_path, lights, [(200, 90, 60)], focal=250)
    files = image_list(tmp_path)
    result = calibrate(files, focal=250)
    (circle,) = result.spheres
    predicted = outline_stretch(circle, 250, (159.5, 119.5))
    seen, se, direction = measure_stretch(circle, np.median(load_luminance(files), axis=0))
    toward = math.degrees(math.atan2(circle.y - 119.5, 159.5 - circle.x)) + 180  # the axis through the point
    assert 1.0 < predicted < 1.5 and abs(seen - predicted) < 0.15 and se < 0.1, (predicted, seen, se)
    assert abs(direction - toward) < 8, (direction, toward)
    xy = np.array([[h.x, h.y] for h in result.highlights[0]])
    focal, principal = implied_camera(xy, lights, circle, result.shape)
    assert abs(focal / 250 - 1) < 0.1 and math.hypot(principal[0] - 159.5, principal[1] - 119.5) < 10, \
        (focal, principal)
    estimated = calibrate(files, focal="auto")
    assert abs(estimated.focal / 250 - 1) < 0.05, estimated.focal_notes
    assert angles_deg(estimated.lights, lights).mean() < 0.5 and angles_deg(calibrate(files).lights, lights).mean() > 4


def test_estimated_focal_stays_orthographic_on_an_orthographic_capture(tmp_path, capsys):
    render_capture(tmp_path, fibonacci_lights(8, seed=2), [(110, 90, 42), (230, 100, 36)])
    out = str(tmp_path / "a.lp")
    assert main(["calibrate", str(tmp_path), "--out", out, "--focal", "auto"]) == 0
    printed = capsys.readouterr().out
    assert "camera: orthographic" in printed and printed.count("orthographic") >= 3, printed
    assert main(["calibrate", str(tmp_path), "--out", out, "--focal", "wide"]) == 2
    assert "'auto'" in capsys.readouterr().err


def test_implied_sphere_of_rendered_spheres_is_the_sphere(tmp_path):
    lights = fibonacci_lights(12, seed=6)
    render_capture(tmp_path, lights, [(150, 110, 50)])
    result = calibrate(image_list(tmp_path))
    implied, rms = implied_sphere(np.array([[h.x, h.y] for h in result.highlights[0]]), lights)
    assert rms < 0.5 and math.hypot(implied.x - 150, implied.y - 110) < 0.5 and abs(implied.r - 50) < 0.5, implied


def test_stage_in_a_graph_writes_the_light_file_and_report(tmp_path):
    import btforge
    lights = fibonacci_lights(8, seed=9)
    (tmp_path / "shots").mkdir()
    render_capture(tmp_path / "shots", lights, [(120, 100, 45)], dark=(2,))
    graph = tmp_path / "g.yaml"
    graph.write_text("nodes:\n  lights: {stage: calibrate.lights,\n"
                     "           params: {images: 'shots/*.jpg', estimate_focal: true}}\n"
                     "  fit: {stage: ptm.fit, inputs: {stack: lights.stack}}\n")
    with pytest.warns(Warning, match="shot_02.jpg"):
        result = btforge.run(str(graph), only=["lights", "fit"], out_dir=str(tmp_path / "out"), quiet=True)
    stack = result["lights"]["stack"]
    assert stack.n_light == 7 and "shot_02.jpg" not in stack.names
    assert angles_deg(stack.lights, np.delete(lights, 2, axis=0)).max() < 2.0
    assert (tmp_path / "out" / "lights.lp").is_file() and (tmp_path / "out" / "calibration.png").is_file()
    assert result["fit"]["model"].height == 240


def test_a_wrong_light_can_be_deleted(tmp_path, capsys):
    lights = fibonacci_lights(6, seed=12)
    render_capture(tmp_path, lights, [(120, 100, 45)])
    out = tmp_path / "dirs.lp"
    assert main(["calibrate", str(tmp_path), "--out", str(out), "--exclude", "shot_04.jpg"]) == 0
    assert "shot_04.jpg" in capsys.readouterr().err
    assert [e.filename for e in read_light_file(out)] == [f"shot_{i:02d}.jpg" for i in (0, 1, 2, 3, 5)]
    assert main(["calibrate", str(tmp_path), "--out", str(out), "--exclude", "nope.jpg"]) == 2
    assert "names no calibrated image" in capsys.readouterr().err


@settings(max_examples=30, deadline=None)
@given(elevation=st.floats(0.5, 90.0), azimuth=st.floats(0.0, 360.0), radius=st.floats(3.0, 2000.0),
       focal=st.sampled_from([None, 200.0, 5000.0]), principal=st.sampled_from([None, (0.0, 0.0), (790.0, 20.0)]))
def test_reflection_inverts_the_mirror_geometry(elevation, azimuth, radius, focal, principal):
    """Grazing and overhead lights, tiny and huge spheres: the direction of a highlight placed by the mirror law
    comes back, finite and unit length (orthographic exactly; perspective through the same ray geometry)."""
    from btforge.plugins.calibrate.sphere import reflect
    e, a = np.radians(elevation), np.radians(azimuth)
    light = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    circle = Circle(400.0, 300.0, radius)
    if focal is None:
        normal = (light + [0, 0, 1]) / np.linalg.norm(light + [0, 0, 1])
        xy = np.array([[circle.x + radius * normal[0], circle.y - radius * normal[1]]])
        got = reflect(xy, circle, (600, 800))
        np.testing.assert_allclose(got[0], light, atol=1e-9)
    else:
        rng = np.random.default_rng(int(elevation * 1000) % 997)
        rho = rng.uniform(0, 0.999, 5)
        phi = rng.uniform(0, 2 * np.pi, 5)
        xy = np.stack([circle.x + radius * rho * np.cos(phi), circle.y + radius * rho * np.sin(phi)], 1)
        got = reflect(xy, circle, (600, 800), focal, principal)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(kind=st.sampled_from(["black", "saturated", "noise", "rim", "spot", "two"]), radius=st.integers(8, 60),
       seed=st.integers(0, 10))
def test_highlight_search_on_hard_images(kind, radius, seed):
    """Black, saturated or noisy balls, a highlight at the rim, two lights: a position inside the disc or a
    reason, never a crash or a silent guess."""
    from btforge.plugins.calibrate.sphere import find_highlight
    rng = np.random.default_rng(seed)
    h = w = 2 * radius + 20
    circle = Circle(w / 2, h / 2, float(radius))
    yy, xx = np.mgrid[0:h, 0:w]
    image = np.zeros((h, w), np.float32)

    def spot(x, y):
        return np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 2.0).astype(np.float32)

    if kind == "saturated":
        image[:] = 1.0
    elif kind == "noise":
        image = rng.uniform(0, 0.02, (h, w)).astype(np.float32)
    elif kind == "rim":
        a = rng.uniform(0, 2 * np.pi)
        image = spot(circle.x + 0.9 * radius * np.cos(a), circle.y + 0.9 * radius * np.sin(a))
    elif kind == "spot":
        image = spot(circle.x + rng.uniform(-0.5, 0.5) * radius, circle.y + rng.uniform(-0.5, 0.5) * radius)
    elif kind == "two":
        image = spot(circle.x - 0.4 * radius, circle.y) + spot(circle.x + 0.4 * radius, circle.y)
    result = find_highlight(image, np.zeros_like(image), circle)
    if kind in ("black", "saturated", "noise"):
        assert not result.found and result.problem
    elif kind in ("rim", "spot"):
        assert result.found and np.hypot(result.x - circle.x, result.y - circle.y) <= radius
    else:
        assert result.found or result.problem  # one of the two lamps, or refused: never in between
        if result.found:
            assert min(abs(result.x - (circle.x - 0.4 * radius)), abs(result.x - (circle.x + 0.4 * radius))) < 1.0
