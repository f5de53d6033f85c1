"""HP PTM file I/O: layout and orientation pinned by hand-built files, round trips, corrupt files, real PTMs."""
from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from btforge.errors import BtforgeInputError
from btforge.plugins.ptm.ptmfile import (
    PtmFileContent,
    describe_ptm,
    relit_display_values,
    read_ptm,
    write_ptm,
)

SHARED_PTM = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "ptm"
ONE_LEVEL = 1.0 / 255.0
# Relit values are float32; this absorbs their rounding, not quantisation error.
FLOAT_SLACK = 1e-5


# ----------------------------------------------------------------------------------------------- helpers


def hemisphere_lights(count: int = 200) -> np.ndarray:
    """A Fibonacci spiral over the upper hemisphere, from the zenith down to 3 degrees above the horizon."""
    k = np.arange(count) + 0.5
    z = 1.0 - (k / count) * (1.0 - np.sin(np.radians(3)))
    azimuth = np.pi * (1 + 5 ** 0.5) * k
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], axis=1)


def relit_changes(before: PtmFileContent | tuple, after: PtmFileContent, lights: np.ndarray,
                  chunk: int = 16) -> np.ndarray:
    """Per light, the largest change of a relit, [0, 1]-clipped display value over pixels and channels."""
    coeffs, albedo = (before.coeffs, before.albedo) if isinstance(before, PtmFileContent) else before
    changes = []
    for start in range(0, len(lights), chunk):
        block = lights[start:start + chunk]
        a = np.clip(relit_display_values(coeffs, albedo, block), 0, 1)
        b = np.clip(relit_display_values(after.coeffs, after.albedo, block), 0, 1)
        changes.append(np.abs(a - b).max(axis=(1, 2, 3)))
    return np.concatenate(changes)


def max_relit_change(before: PtmFileContent | tuple, after: PtmFileContent, lights: np.ndarray) -> float:
    return float(relit_changes(before, after, lights).max())


def header_bytes(file_format: str, width: int, height: int, scale, bias, extra_lines=()) -> bytes:
    lines = ["PTM_1.2", file_format, str(width), str(height),
             " ".join(f"{s:g}" for s in scale), " ".join(str(b) for b in bias), *extra_lines]
    return ("\n".join(lines) + "\n").encode()


def unit(byte_values, scale, bias) -> np.ndarray:
    """The documented decoding: (byte - bias) * scale / 255, per coefficient on the last axis."""
    return ((np.asarray(byte_values, float) - np.asarray(bias, float)) * np.asarray(scale, float) / 255.0)


def quantisation_steps(path: Path) -> np.ndarray:
    return np.asarray(describe_ptm(path)["scale"]) / 255.0


def assert_within_half_step(original: np.ndarray, decoded: np.ndarray, path: Path) -> None:
    """Rounding to nearest: every decoded coefficient is within half a level of its file's grid."""
    half_step = quantisation_steps(path) / 2
    error = np.abs(decoded.astype(np.float64) - original.astype(np.float64))
    allowed = half_step * (1 + 1e-6) + 1e-7 * np.abs(original)
    assert (error <= allowed).all(), f"max error / half step: {(error / half_step).max(axis=(0, 1, 2))}"


def skip_without(folder: Path) -> None:
    if not folder.is_dir():
        pytest.skip(f"shared data not present: {folder}")


# ----------------------------------------------------------------------------------------------- layout


LRGB_SCALE = (2.0, 2.0, 2.0, 1.0, 1.0, 1.5)
LRGB_BIAS = (100, 0, 50, 127, 127, 0)


def tiny_lrgb_file(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    """A 3 x 2 PTM_FORMAT_LRGB written byte by byte; returns it with the coefficient and RGB bytes, top row first."""
    width, height = 3, 2
    coeff_bytes = np.zeros((height, width, 6), np.uint8)  # row 0 = top
    rgb_bytes = np.zeros((height, width, 3), np.uint8)
    payload = bytearray()
    for file_row in range(height):  # the file starts with the bottom row
        for x in range(width):
            values = [10 * (3 * file_row + x) + i for i in range(6)]
            coeff_bytes[height - 1 - file_row, x] = values
            payload += bytes(values)
    for file_row in range(height):
        for x in range(width):
            values = [200 + 10 * file_row + x, 7 * x, 255 - file_row]
            rgb_bytes[height - 1 - file_row, x] = values
            payload += bytes(values)
    path = tmp_path / "tiny_lrgb.ptm"
    path.write_bytes(header_bytes("PTM_FORMAT_LRGB", width, height, LRGB_SCALE, LRGB_BIAS) + payload)
    return path, coeff_bytes, rgb_bytes


def test_hand_built_lrgb_file_reads_to_the_expected_arrays(tmp_path):
    path, coeff_bytes, rgb_bytes = tiny_lrgb_file(tmp_path)
    content = read_ptm(path)
    assert content.variant == "lrgb" and content.file_format == "PTM_FORMAT_LRGB"
    assert content.scale == LRGB_SCALE and content.bias == LRGB_BIAS
    assert content.coeffs.shape == (2, 3, 1, 6) and content.coeffs.dtype == np.float32
    np.testing.assert_allclose(content.coeffs[:, :, 0, :], unit(coeff_bytes, LRGB_SCALE, LRGB_BIAS), rtol=1e-6)
    np.testing.assert_allclose(content.albedo, rgb_bytes / 255.0, rtol=1e-6)
    # Spot-check one pixel by hand: the top-left pixel is the first pixel of the file's second row.
    assert content.coeffs[0, 0, 0, 0] == pytest.approx((30 - 100) * 2.0 / 255)
    assert content.albedo[0, 0, 0] == pytest.approx(210 / 255)


def test_hand_built_rgb_file_reads_to_the_expected_arrays(tmp_path):
    width, height = 3, 2
    scale, bias = (1.0, 2.0, 3.0, 4.0, 0.5, 2.0), (0, 10, 20, 30, 40, 128)
    expected = np.zeros((height, width, 3, 6), np.uint8)  # row 0 = top
    payload = bytearray()
    for channel in range(3):  # a block per colour channel: R, then G, then B
        for file_row in range(height):  # bottom row first
            for x in range(width):
                values = [(40 * channel + 10 * (3 * file_row + x) + i) % 256 for i in range(6)]
                expected[height - 1 - file_row, x, channel] = values
                payload += bytes(values)
    path = tmp_path / "tiny_rgb.ptm"
    path.write_bytes(header_bytes("PTM_FORMAT_RGB", width, height, scale, bias) + payload)
    content = read_ptm(path)
    assert content.variant == "rgb" and content.albedo is None
    assert content.coeffs.shape == (2, 3, 3, 6)
    np.testing.assert_allclose(content.coeffs, unit(expected, scale, bias), rtol=1e-6)
    # Green channel, constant term, bottom-right pixel = file block 1, row 0, pixel 2, byte 5.
    assert content.coeffs[1, 2, 1, 5] == pytest.approx(((40 + 20 + 5) - 128) * 2.0 / 255)


@pytest.mark.parametrize("variant", ["lrgb", "rgb"])
def test_written_bytes_follow_the_layout(tmp_path, variant):
    """The writer's bytes, decoded by hand with the spec layout, give back the model."""
    rng = np.random.default_rng(1)
    channels = 1 if variant == "lrgb" else 3
    coeffs = rng.uniform(-1, 1, (2, 3, channels, 6)).astype(np.float32)
    albedo = rng.uniform(0, 1, (2, 3, 3)).astype(np.float32) if variant == "lrgb" else None
    path = tmp_path / "w.ptm"
    write_ptm(path, variant, coeffs, albedo)
    facts = describe_ptm(path)
    raw = np.frombuffer(path.read_bytes()[facts["header_bytes"]:], np.uint8)
    if variant == "lrgb":
        coeff_bytes = raw[:36].reshape(2, 3, 1, 6)[::-1]
        rgb_bytes = raw[36:].reshape(2, 3, 3)[::-1]
        np.testing.assert_array_equal(rgb_bytes, np.rint(albedo * 255))
    else:
        coeff_bytes = raw.reshape(3, 2, 3, 6).transpose(1, 2, 0, 3)[::-1]
    decoded = unit(coeff_bytes, facts["scale"], facts["bias"])
    assert np.abs(decoded - coeffs).max() <= max(facts["scale"]) / 510 * 1.0001


def test_evaluate_follows_the_documented_polynomial():
    coeffs = np.array([0.1, -0.2, 0.3, 0.4, -0.5, 0.6], np.float32).reshape(1, 1, 1, 6)
    albedo = np.array([0.5, 1.0, 0.25], np.float32).reshape(1, 1, 3)
    light = np.array([[0.6, 0.0, 0.8], [0.0, 0.0, 2.0]])  # the second is not unit length: normalised
    lu, lv = 0.6, 0.0
    poly = 0.1 * lu * lu - 0.2 * lv * lv + 0.3 * lu * lv + 0.4 * lu - 0.5 * lv + 0.6
    values = relit_display_values(coeffs, albedo, light)
    assert values.shape == (2, 1, 1, 3) and values.dtype == np.float32
    np.testing.assert_allclose(values[0, 0, 0], poly * albedo[0, 0], rtol=1e-6)
    np.testing.assert_allclose(values[1, 0, 0], 0.6 * albedo[0, 0], rtol=1e-6)
    rgb = np.stack([coeffs[0, 0, 0], 2 * coeffs[0, 0, 0], -coeffs[0, 0, 0]]).reshape(1, 1, 3, 6)
    np.testing.assert_allclose(relit_display_values(rgb, None, light[:1])[0, 0, 0], [poly, 2 * poly, -poly],
                               rtol=1e-6)
    # Not clipped: callers decide.
    assert relit_display_values(rgb * 10, None, light[:1]).max() > 1


# ----------------------------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("variant", ["lrgb", "rgb"])
def test_random_model_round_trip_rounds_to_nearest(tmp_path, variant):
    rng = np.random.default_rng(7)
    channels = 1 if variant == "lrgb" else 3
    coeffs = (rng.normal(0, 0.4, (17, 13, channels, 6)) + [-0.5, -0.5, 0, 0.1, -0.1, 0.7]).astype(np.float32)
    albedo = rng.uniform(0, 1, (17, 13, 3)).astype(np.float32) if variant == "lrgb" else None
    path = tmp_path / "random.ptm"
    write_ptm(path, variant, coeffs, albedo)
    back = read_ptm(path)
    assert back.variant == variant and back.coeffs.shape == coeffs.shape
    assert back.file_format == {"lrgb": "PTM_FORMAT_LRGB", "rgb": "PTM_FORMAT_RGB"}[variant]
    assert all(0 <= b <= 255 for b in back.bias) and all(s > 0 for s in back.scale)
    assert_within_half_step(coeffs, back.coeffs, path)
    if variant == "lrgb":
        assert np.abs(back.albedo - albedo).max() <= 0.5 / 255 + 1e-7
    # Each level is as fine as the data's range allows: scale = range of the coefficient (including 0).
    span = np.maximum(coeffs.max(axis=(0, 1, 2)), 0) - np.minimum(coeffs.min(axis=(0, 1, 2)), 0)
    np.testing.assert_allclose(back.scale, span, rtol=1e-6)
    # Writing what was read changes nothing: the second write finds the first one's grid.
    again = tmp_path / "again.ptm"
    write_ptm(again, variant, back.coeffs, back.albedo)
    np.testing.assert_array_equal(read_ptm(again).coeffs, back.coeffs)


def test_coefficients_on_a_byte_grid_round_trip_exactly(tmp_path):
    rng = np.random.default_rng(3)
    scale, bias = np.array([2.0, 2.0, 2.0, 1.0, 1.0, 1.5]), np.array([160, 160, 160, 127, 127, 0])
    levels = rng.integers(0, 256, (9, 11, 1, 6))
    coeffs = unit(levels, scale, bias).astype(np.float32)
    albedo = (rng.integers(0, 256, (9, 11, 3)) / 255).astype(np.float32)
    path = tmp_path / "grid.ptm"
    write_ptm(path, "lrgb", coeffs, albedo)
    back = read_ptm(path)
    np.testing.assert_array_equal(back.coeffs, coeffs)
    np.testing.assert_array_equal(back.albedo, albedo)
    assert back.scale == tuple(scale)


def test_constant_planes_get_a_valid_scale_and_round_trip_exactly(tmp_path):
    coeffs = np.zeros((4, 5, 3, 6), np.float32)
    coeffs[..., 1] = 0.37
    coeffs[..., 2] = -12.5
    coeffs[..., 5] = 1e-20
    path = tmp_path / "constant.ptm"
    write_ptm(path, "rgb", coeffs, None)
    back = read_ptm(path)
    assert all(s > 0 for s in back.scale) and all(0 <= b <= 255 for b in back.bias)
    np.testing.assert_allclose(back.coeffs, coeffs, rtol=1e-6, atol=0)


def test_written_file_is_described_from_its_header(tmp_path):
    rng = np.random.default_rng(5)
    path = tmp_path / "d.ptm"
    write_ptm(path, "rgb", rng.normal(size=(6, 4, 3, 6)).astype(np.float32), None)
    facts = describe_ptm(path)
    assert facts["version"] == "PTM_1.2" and facts["format"] == "PTM_FORMAT_RGB"
    assert (facts["width"], facts["height"]) == (4, 6)
    assert facts["size_bytes"] == path.stat().st_size == facts["expected_size_bytes"]
    assert facts["size_bytes"] == facts["header_bytes"] + 4 * 6 * 18
    assert len(facts["scale"]) == 6 and len(facts["bias"]) == 6


def test_write_leaves_no_partial_file_on_bad_input(tmp_path):
    path = tmp_path / "out.ptm"
    with pytest.raises(BtforgeInputError):
        write_ptm(path, "lrgb", np.zeros((2, 2, 1, 6), np.float32), None)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("variant, coeffs, albedo, needle", [
    ("xyz", np.zeros((2, 2, 1, 6), np.float32), None, "variant"),
    ("lrgb", np.zeros((2, 2, 3, 6), np.float32), np.zeros((2, 2, 3), np.float32), "[H, W, 1, 6]"),
    ("rgb", np.zeros((2, 2, 1, 6), np.float32), None, "[H, W, 3, 6]"),
    ("rgb", np.zeros((2, 2, 3, 6), np.int32), None, "float"),
    ("rgb", np.zeros((2, 2, 3, 6), np.float32), np.zeros((2, 2, 3), np.float32), "None"),
    ("lrgb", np.zeros((2, 2, 1, 6), np.float32), np.zeros((2, 3, 3), np.float32), "albedo"),
    ("lrgb", np.zeros((2, 2, 1, 6), np.float32), np.full((2, 2, 3), 1.5, np.float32), "[0, 1]"),
    ("lrgb", np.full((2, 2, 1, 6), np.nan, np.float32), np.zeros((2, 2, 3), np.float32), "finite"),
    ("rgb", [[0.0] * 6], None, "numpy array"),
])
def test_write_rejects_bad_models_with_clear_errors(tmp_path, variant, coeffs, albedo, needle):
    with pytest.raises(BtforgeInputError) as info:
        write_ptm(tmp_path / "bad.ptm", variant, coeffs, albedo)
    assert needle in str(info.value)


def coefficient_planes(draw, shape) -> np.ndarray:
    """One coefficient plane: constant, zero, or spread over a range of any magnitude and offset."""
    kind = draw(st.sampled_from(["constant", "zero", "range"]))
    magnitude = 10.0 ** draw(st.integers(-20, 20))
    if kind == "zero":
        return np.zeros(shape, np.float32)
    centre = draw(st.floats(-2, 2)) * magnitude
    if kind == "constant":
        return np.full(shape, centre, np.float32)
    seed = draw(st.integers(0, 2 ** 32 - 1))
    spread = draw(st.floats(1e-3, 2)) * magnitude
    return (centre + spread * np.random.default_rng(seed).uniform(-1, 1, shape)).astype(np.float32)


@st.composite
def models(draw):
    variant = draw(st.sampled_from(["lrgb", "rgb"]))
    height, width = draw(st.integers(1, 4)), draw(st.integers(1, 4))
    shape = (height, width, 1 if variant == "lrgb" else 3)
    coeffs = np.stack([coefficient_planes(draw, shape) for _ in range(6)], axis=-1)
    albedo = None
    if variant == "lrgb":
        seed = draw(st.integers(0, 2 ** 32 - 1))
        albedo = np.random.default_rng(seed).uniform(0, 1, (height, width, 3)).astype(np.float32)
    return variant, coeffs, albedo


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(model=models())
def test_round_trip_property(tmp_path, model):
    variant, coeffs, albedo = model
    path = tmp_path / "prop.ptm"
    write_ptm(path, variant, coeffs, albedo)
    back = read_ptm(path)
    assert back.coeffs.shape == coeffs.shape
    assert all(s > 0 for s in back.scale) and all(0 <= b <= 255 for b in back.bias)
    assert_within_half_step(coeffs, back.coeffs, path)
    # No precision wasted: never worse than 256 levels spread over the coefficient's range (zero included).
    # (Data that happens to lie on a coarser grid may be stored on it, exactly.)
    wide = coeffs.astype(np.float64)
    span = np.maximum(wide.max(axis=(0, 1, 2)), 0) - np.minimum(wide.min(axis=(0, 1, 2)), 0)
    error = np.abs(back.coeffs.astype(np.float64) - wide)
    assert (error <= span / 510 * (1 + 1e-6) + 1e-7 * np.abs(wide)).all()
    write_ptm(path, variant, back.coeffs, back.albedo)
    np.testing.assert_array_equal(read_ptm(path).coeffs, back.coeffs)


# ----------------------------------------------------------------------------------------------- JPEG_LRGB


def jpeg_stream(plane: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(plane).save(buffer, "JPEG", quality=100, subsampling=0)
    return buffer.getvalue()


def jpeg_lrgb_file(tmp_path: Path, planes_top_first: np.ndarray, order, reference, transforms, side=None,
                   name="j.ptm", mangle=None, raw_side=None) -> Path:
    """A PTM_FORMAT_JPEG_LRGB built the way the format describes, from planes [9, H, W] (row 0 = top)."""
    side = side or {}
    height, width = planes_top_first.shape[1:]
    file_planes = planes_top_first[:, ::-1].astype(np.int16)  # streams hold the bottom row first
    streams, side_bytes = [], []
    for plane in range(9):
        stored = file_planes[plane]
        ref = reference[plane]
        if ref >= 0:
            base = 255 - file_planes[ref] if transforms[plane] & 1 else file_planes[ref]
            stored = stored - base + 128
        assert 0 <= stored.min() and stored.max() <= 255, "test planes must not overflow the prediction"
        streams.append(jpeg_stream(stored.astype(np.uint8)))
        records = b"".join(int(index).to_bytes(4, "big") + bytes([value]) for index, value in side.get(plane, []))
        side_bytes.append((raw_side or {}).get(plane, records))
    lines = ["95", " ".join(map(str, transforms)), " ".join(["0"] * 9), " ".join(["0"] * 9),
             " ".join(map(str, order)), " ".join(map(str, reference)),
             " ".join(str(len(s)) for s in streams), " ".join(str(len(s)) for s in side_bytes)]
    if mangle:
        lines = mangle(lines)
    payload = b"".join(s + t for s, t in zip(streams, side_bytes))
    path = tmp_path / name
    path.write_bytes(header_bytes("PTM_FORMAT_JPEG_LRGB", width, height, (2.0,) * 6, (128,) * 6, lines) + payload)
    return path


def smooth_planes(height=16, width=24) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width]
    planes = [60 + 4 * x + 2 * k + y * (k % 3) for k in range(9)]
    return np.clip(np.stack(planes), 0, 255).astype(np.uint8)


PREDICTED = dict(order=[4, 8, 3, 0, 1, 7, 5, 2, 6], reference=[-1, 5, -1, -1, -1, 0, 7, -1, 7],
                 transforms=[0, 1, 0, 0, 0, 1, 0, 0, 0])  # the pattern of the real tablet1 file


def test_jpeg_lrgb_prediction_inversion_and_side_information(tmp_path):
    planes = smooth_planes()
    planes[5] = 255 - planes[0] // 2  # anti-correlated with its reference, as plane inversion expects
    planes[1] = 255 - planes[5] // 2
    # Side information: exact bytes at (file-order) pixel indices, applied after prediction.
    side = {1: [(0, 3), (24 * 16 - 1, 250)], 6: [(30, 0)]}
    path = jpeg_lrgb_file(tmp_path, planes, side=side, **PREDICTED)
    content = read_ptm(path)
    expected = planes.astype(np.int16).copy()
    height, width = planes.shape[1:]
    for plane, records in side.items():
        for index, value in records:
            file_row, x = divmod(index, width)
            expected[plane, height - 1 - file_row, x] = value
    decoded_bytes = np.concatenate([content.coeffs[:, :, 0, :] * 255 / 2.0 + 128, content.albedo * 255], axis=-1)
    error = np.abs(decoded_bytes - expected.transpose(1, 2, 0))
    assert error.max() <= 3, "JPEG at quality 100 stays within a few levels"
    # Side-information pixels are exact.  Index 0 is the first pixel of the file's first (bottom) row.
    assert decoded_bytes[height - 1, 0, 1] == pytest.approx(3, abs=1e-4)
    assert decoded_bytes[0, width - 1, 1] == pytest.approx(250, abs=1e-4)
    assert decoded_bytes[height - 2, 6, 6] == pytest.approx(0, abs=1e-4)
    facts = describe_ptm(path)
    assert facts["reference_planes"] == tuple(PREDICTED["reference"])
    assert facts["size_bytes"] == facts["expected_size_bytes"]


# ----------------------------------------------------------------------------------------------- corrupt files

GOOD_HEADER = header_bytes("PTM_FORMAT_LRGB", 2, 2, (1,) * 6, (0,) * 6)
GOOD_PAYLOAD = bytes(range(36))


def corrupt_cases():
    def replace(old: bytes, new: bytes):
        return GOOD_HEADER.replace(old, new, 1) + GOOD_PAYLOAD

    return {
        "empty": (b"", "end of the file"),
        "png": (b"\x89PNG\r\n\x1a\n" + bytes(64), "not a PTM file"),
        "no newline": (bytes(100), "not a PTM file"),
        "old version": (replace(b"PTM_1.2", b"PTM_1.1"), "line 1"),
        "wrong magic": (replace(b"PTM_1.2", b"PTX_9"), "line 1"),
        "unknown format": (replace(b"PTM_FORMAT_LRGB", b"PTM_FORMAT_XYZ"), "line 2"),
        "unsupported format": (replace(b"PTM_FORMAT_LRGB", b"PTM_FORMAT_LUM"), "not supported"),
        "non-numeric width": (replace(b"\n2\n2\n", b"\nwide\n2\n"), "line 3"),
        "zero height": (replace(b"\n2\n2\n", b"\n2\n0\n"), "positive"),
        "non-numeric scale": (replace(b"1 1 1 1 1 1", b"1 1 x 1 1 1"), "line 5"),
        "infinite scale": (replace(b"1 1 1 1 1 1", b"1 1 inf 1 1 1"), "line 5"),
        "five biases": (replace(b"0 0 0 0 0 0", b"0 0 0 0 0"), "line 6"),
        "fractional bias": (replace(b"0 0 0 0 0 0", b"0 0 0.5 0 0 0"), "line 6"),
        "truncated header": (GOOD_HEADER[:20], "truncated"),
        "truncated payload": (GOOD_HEADER + GOOD_PAYLOAD[:-5], "truncated"),
        "extra payload": (GOOD_HEADER + GOOD_PAYLOAD + b"junk", "mismatch"),
        "header says bigger": (replace(b"\n2\n2\n", b"\n200\n200\n"), "truncated"),
    }


@pytest.mark.parametrize("case", list(corrupt_cases()))
def test_corrupt_files_raise_input_errors_naming_the_file(tmp_path, case):
    data, needle = corrupt_cases()[case]
    path = tmp_path / f"broken_{case.replace(' ', '_')}.ptm"
    path.write_bytes(data)
    with pytest.raises(BtforgeInputError) as info:
        read_ptm(path)
    message = str(info.value)
    assert path.name in message and needle in message, message
    if case not in ("truncated payload", "extra payload", "header says bigger"):  # header faults
        with pytest.raises(BtforgeInputError):
            describe_ptm(path)


def jpeg_cases():
    def set_line(index, text):
        def mangle(lines):
            lines = list(lines)
            lines[index] = text
            return lines
        return mangle

    return {
        "sizes too big": (dict(mangle=set_line(6, " ".join(["99999"] * 9))), "truncated"),
        "order not a permutation": (dict(mangle=set_line(4, "0 0 1 2 3 4 5 6 7")), "permutation"),
        "reference decoded later": (dict(mangle=set_line(4, "0 1 2 3 4 5 6 7 8")), "after it"),
        "motion compensation": (dict(mangle=set_line(1, "2 0 0 0 0 0 0 0 0")), "motion compensation"),
        "non-numeric order": (dict(mangle=set_line(4, "a b c d e f g h i")), "line 11"),
        "eight sizes": (dict(mangle=set_line(6, "1 2 3 4 5 6 7 8")), "line 13"),
        "side info not records": (dict(raw_side={0: b"\x00\x00\x00\x01"}), "multiple of 5"),
        "side info out of range": (dict(side={2: [(10 ** 6, 1)]}), "pixel indices"),
    }


@pytest.mark.parametrize("case", list(jpeg_cases()))
def test_corrupt_jpeg_files_raise_input_errors_naming_the_file(tmp_path, case):
    options, needle = jpeg_cases()[case]
    name = f"broken_{case.replace(' ', '_')}.ptm"
    path = jpeg_lrgb_file(tmp_path, smooth_planes(), name=name, **{**PREDICTED, **options})
    with pytest.raises(BtforgeInputError) as info:
        read_ptm(path)
    assert path.name in str(info.value) and needle in str(info.value), str(info.value)


def test_a_garbled_jpeg_stream_is_an_input_error(tmp_path):
    path = jpeg_lrgb_file(tmp_path, smooth_planes(), **PREDICTED)
    data = bytearray(path.read_bytes())
    start = describe_ptm(path)["header_bytes"]
    data[start:start + 40] = bytes(40)  # wipe the first stream's JPEG header
    path.write_bytes(bytes(data))
    with pytest.raises(BtforgeInputError) as info:
        read_ptm(path)
    assert path.name in str(info.value) and "JPEG stream 0" in str(info.value)


def test_jpeg_rgb_is_described_but_not_read(tmp_path):
    eighteen = " ".join(["0"] * 18)
    lines = ["90", eighteen, eighteen, eighteen, " ".join(map(str, range(18))), " ".join(["-1"] * 18),
             " ".join(["10"] * 18), eighteen]
    path = tmp_path / "jrgb.ptm"
    path.write_bytes(header_bytes("PTM_FORMAT_JPEG_RGB", 4, 4, (1,) * 6, (0,) * 6, lines) + bytes(180))
    facts = describe_ptm(path)
    assert facts["format"] == "PTM_FORMAT_JPEG_RGB" and facts["variant"] == "rgb"
    assert facts["size_bytes"] == facts["expected_size_bytes"] and facts["quality"] == 90
    with pytest.raises(BtforgeInputError, match="not supported") as info:
        read_ptm(path)
    assert "jrgb.ptm" in str(info.value)


def test_width_and_height_may_share_a_line(tmp_path):
    path, coeff_bytes, _ = tiny_lrgb_file(tmp_path)
    data = path.read_bytes().replace(b"\n3\n2\n", b"\n3 2 \n", 1)
    path.write_bytes(data)
    content = read_ptm(path)
    np.testing.assert_allclose(content.coeffs[:, :, 0, :], unit(coeff_bytes, LRGB_SCALE, LRGB_BIAS), rtol=1e-6)


def test_missing_file_is_an_input_error(tmp_path):
    with pytest.raises(BtforgeInputError, match="no such file"):
        read_ptm(tmp_path / "absent.ptm")
    with pytest.raises(BtforgeInputError, match="no such file"):
        describe_ptm(tmp_path / "absent.ptm")


# ----------------------------------------------------------------------------------------------- real data


@pytest.mark.shared_data
def test_real_jpeg_lrgb_tablet_decodes_to_a_plausible_image(tmp_path):
    path = SHARED_PTM / "tablet1" / "tablet1.ptm"
    skip_without(path.parent)
    content = read_ptm(path)
    assert content.variant == "lrgb" and content.file_format == "PTM_FORMAT_JPEG_LRGB"
    assert content.coeffs.shape == (512, 512, 1, 6)
    assert content.scale == (2.0,) * 6 and content.bias == (160, 160, 160, 127, 127, 0)
    lights = np.array([[0, 0, 1], [0, 0.7, 0.714], [0, -0.7, 0.714], [0.7, 0, 0.714], [-0.7, 0, 0.714]])
    relit = relit_display_values(content.coeffs, content.albedo, lights).mean(axis=-1)
    top = relit[0]
    assert ((top >= 0) & (top <= 1)).mean() > 0.99, "display values in [0, 1], so the unit scale is right"
    # A photograph, not noise: neighbouring pixels are strongly correlated (noise would give ~0).
    assert np.corrcoef(top[:, :-1].ravel(), top[:, 1:].ravel())[0, 1] > 0.95
    assert np.corrcoef(top[:-1].ravel(), top[1:].ravel())[0, 1] > 0.95
    # Orientation: the tablet is a cushion, so a light from +v (toward the image top) brightens its upper
    # half and a light from +u its right half.  Unflipped rows would make the first correlation negative.
    tablet = content.albedo.mean(axis=-1) > 0.25
    rows, cols = np.nonzero(tablet)
    lit_from_top = (relit[1] - relit[2])[tablet]
    lit_from_right = (relit[3] - relit[4])[tablet]
    assert np.corrcoef(lit_from_top, -rows)[0, 1] > 0.6
    assert np.corrcoef(lit_from_right, cols)[0, 1] > 0.6


@pytest.mark.shared_data
def test_real_jpeg_lrgb_tablet_round_trips_as_raw_lrgb(tmp_path):
    path = SHARED_PTM / "tablet1" / "tablet1.ptm"
    skip_without(path.parent)
    content = read_ptm(path)
    out = tmp_path / "tablet1_raw.ptm"
    write_ptm(out, "lrgb", content.coeffs, content.albedo)
    back = read_ptm(out)
    assert back.file_format == "PTM_FORMAT_LRGB"
    assert max_relit_change(content, back, hemisphere_lights(48)) <= ONE_LEVEL + FLOAT_SLACK
    # Stronger than the criterion: the 8-bit grid of the file is found again, so nothing changes at all.
    np.testing.assert_array_equal(back.coeffs, content.coeffs)
    np.testing.assert_array_equal(back.albedo, content.albedo)
    assert back.scale == content.scale
    assert describe_ptm(out)["size_bytes"] == describe_ptm(out)["header_bytes"] + 512 * 512 * 9


def load_openlime_ptm(folder: Path, crop: tuple[slice, slice]) -> tuple[np.ndarray, np.ndarray]:
    """Relight's web PTM: plane_j.jpg holds basis term j = (1, x, y, x^2, xy, y^2) for R, G, B, decoded as
    (byte / 255 - bias[3j + c]) * scale[3j + c]; already display-unit scale.  Returns [H, W, 3, 6] in
    btforge's term order and the capture's light directions."""
    info = json.loads((folder / "info.json").read_text())
    material = info["materials"][0]
    scale = np.asarray(material["scale"], float).reshape(6, 3)
    bias = np.asarray(material["bias"], float).reshape(6, 3)
    ours = {0: 5, 1: 3, 2: 4, 3: 0, 4: 2, 5: 1}  # relight plane -> (lu^2, lv^2, lu*lv, lu, lv, 1) index
    planes = [np.asarray(Image.open(folder / f"plane_{j}.jpg"), float)[crop] for j in range(6)]
    coeffs = np.zeros(planes[0].shape[:2] + (3, 6), np.float32)
    for j, plane in enumerate(planes):
        coeffs[:, :, :, ours[j]] = (plane / 255.0 - bias[j]) * scale[j]
    return coeffs, np.asarray(info["lights"], float).reshape(-1, 3)


OPENLIME_CROP = (slice(384, 640), slice(384, 640))


@pytest.mark.shared_data
def test_real_relight_rgb_ptm_round_trips_as_raw_rgb(tmp_path):
    folder = SHARED_PTM / "openlime_relight_ptm"
    skip_without(folder)
    coeffs, capture_lights = load_openlime_ptm(folder, OPENLIME_CROP)
    top = relit_display_values(coeffs, None, np.array([[0.0, 0.0, 1.0]]))[0]
    # Display values: a gold coin, so some highlights saturate a little above 1.
    assert top.min() > -0.05 and np.percentile(top, 99) < 1.1
    out = tmp_path / "coin.ptm"
    write_ptm(out, "rgb", coeffs, None)
    back = read_ptm(out)
    assert back.file_format == "PTM_FORMAT_RGB"
    assert_within_half_step(coeffs, back.coeffs, out)
    # Lights within 25 degrees of the zenith keep every relit value within one level.
    near_zenith = hemisphere_lights(400)
    near_zenith = near_zenith[near_zenith[:, 2] >= np.cos(np.radians(25))]
    assert max_relit_change((coeffs, None), back, near_zenith) <= ONE_LEVEL + FLOAT_SLACK
    # At any light, the change is bounded by half a level per coefficient, weighted by its term.
    lights = np.concatenate([capture_lights, hemisphere_lights(100)])
    unit_lights = lights / np.linalg.norm(lights, axis=1, keepdims=True)
    lu, lv = unit_lights[:, 0], unit_lights[:, 1]
    terms = np.abs(np.stack([lu * lu, lv * lv, lu * lv, lu, lv, np.ones_like(lu)], axis=1))
    bound = terms @ (quantisation_steps(out) / 2)
    assert (relit_changes((coeffs, None), back, lights) <= bound + FLOAT_SLACK).all()


@pytest.mark.shared_data
@pytest.mark.xfail(strict=True, reason="PTM_FORMAT_RGB shares one 8-bit grid per coefficient across R, G, B; "
                                       "relight's per-channel grids do not fit it within 1/255 at grazing lights")
def test_real_relight_rgb_ptm_round_trip_within_one_level_at_all_lights(tmp_path):
    folder = SHARED_PTM / "openlime_relight_ptm"
    skip_without(folder)
    coeffs, capture_lights = load_openlime_ptm(folder, OPENLIME_CROP)
    out = tmp_path / "coin.ptm"
    write_ptm(out, "rgb", coeffs, None)
    lights = np.concatenate([capture_lights, hemisphere_lights(100)])
    assert max_relit_change((coeffs, None), read_ptm(out), lights) <= ONE_LEVEL + FLOAT_SLACK


@pytest.mark.shared_data
def test_real_lossless_lrgb_leaf_crop_round_trips(tmp_path):
    folder = SHARED_PTM / "leaf_lrgb_png"
    skip_without(folder)
    info = json.loads((folder / "info.json").read_text())["PTM"]
    scale, bias = np.asarray(info["scale"], float), np.asarray(info["bias"], float)
    box = (1800, 1900, 2056, 2156)  # 256 x 256 inside the leaf (content spans rows 1424..2673, cols 819..3278)
    high, low, rgb = (np.asarray(Image.open(folder / f"1_{k}.png").crop(box)) for k in (1, 2, 3))
    coeffs = unit(np.concatenate([high, low], axis=-1), scale, bias)[:, :, None, :].astype(np.float32)
    albedo = (rgb / 255.0).astype(np.float32)
    out = tmp_path / "leaf.ptm"
    write_ptm(out, "lrgb", coeffs, albedo)
    back = read_ptm(out)
    assert max_relit_change((coeffs, albedo), back, hemisphere_lights(120)) <= ONE_LEVEL + FLOAT_SLACK
    np.testing.assert_array_equal(back.coeffs, coeffs)  # lossless PNG data lies on a byte grid


@pytest.mark.parametrize("n", [1, 511, 512, 1030, 4096])
def test_column_range_equals_numpy_on_any_row_count(n):
    from btforge.plugins.ptm.ptmfile import _column_range
    flat = np.random.default_rng(n).normal(size=(n, 6)).astype(np.float32)
    flat[n // 2, 3] = -1e30  # an extreme value in a block and, for most n, not in the first one
    lows, highs = _column_range(flat)
    np.testing.assert_array_equal(lows, flat.min(axis=0))
    np.testing.assert_array_equal(highs, flat.max(axis=0))
