"""Reading and writing multi-light captures: light files (.lp / .lvp) and the image stacks they list."""
from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from btforge.buffers import SRGB8_TO_LINEAR, SampleStack, srgb_to_linear
from btforge.errors import BtforgeInputError, BtforgeWarning
from btforge.plugins.stackio.images import (
    load_stack, read_exr, read_image, write_exr, write_png, write_stack)
from btforge.plugins.stackio.lightfile import (
    LightFileEntry, parse_light_list, read_light_file, write_light_file)

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

LIGHTS = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 0.8660254], [0.0, -0.6, 0.8], [-0.7071068, 0.0, 0.7071068]])


def shared(relative: str) -> Path:
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"shared capture data not available ({path})")
    return path


def make_capture(folder: Path, n: int = 3, size: tuple[int, int] = (6, 5), mode: str = "RGB",
                 names: list[str] | None = None) -> list[str]:
    """``n`` small 8-bit PNGs (width x height = ``size``) with distinct contents; returns their names."""
    names = names or [f"img{i:02d}.png" for i in range(n)]
    rng = np.random.default_rng(7)
    channels = 3 if mode == "RGB" else 1
    for name in names:
        pixels = rng.integers(0, 256, (size[1], size[0], channels), dtype=np.uint8)
        Image.fromarray(pixels if channels == 3 else pixels[..., 0], mode).save(folder / name)
    return names


def lp_text(names: list[str], lights=LIGHTS, count: int | None = None, newline: str = "\n") -> str:
    rows = [str(len(names) if count is None else count)]
    rows += [f"{name} {x!r} {y!r} {z!r}" for name, (x, y, z) in zip(names, np.asarray(lights).tolist())]
    return newline.join(rows) + newline


def write_lp(folder: Path, text: str, name: str = "dirs.lp") -> Path:
    path = folder / name
    path.write_bytes(text.encode())
    return path


def expect_error(path: Path, line: int, *fragments: str, **kwargs) -> BtforgeInputError:
    with pytest.raises(BtforgeInputError) as info:
        load_stack(path, **kwargs) if path.suffix in (".lp", ".lvp") else read_light_file(path)
    error = info.value
    assert error.what == f"{path}, line {line}", error.render()
    for fragment in fragments:
        assert fragment in error.problem, error.render()
    assert error.hint, "every light-file error should say how to fix it"
    return error


def encode_png16(pixels: np.ndarray, colour_type: int) -> bytes:
    """A 16-bit PNG using every filter type in turn, so a decoder's unfiltering is fully exercised."""
    height = pixels.shape[0]
    rows = pixels.astype(">u2").reshape(height, -1).view(np.uint8).astype(np.int64)
    bpp = 2 * (pixels.shape[2] if pixels.ndim == 3 else 1)
    previous = np.zeros_like(rows[0])
    out = bytearray()
    for y, row in enumerate(rows):
        left = np.concatenate([np.zeros(bpp, np.int64), row[:-bpp]])
        up_left = np.concatenate([np.zeros(bpp, np.int64), previous[:-bpp]])
        estimate = left + previous - up_left
        pa, pb, pc = abs(estimate - left), abs(estimate - previous), abs(estimate - up_left)
        paeth = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, previous, up_left))
        predictors = [0, left, previous, (left + previous) // 2, paeth]
        kind = y % 5
        out += bytes([kind]) + ((row - predictors[kind]) % 256).astype(np.uint8).tobytes()
        previous = row

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    header = struct.pack(">IIBBBBB", pixels.shape[1], height, 16, colour_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(bytes(out)))
            + chunk(b"IEND", b""))


# ----------------------------------------------------------------------------------------------- real data


@pytest.mark.shared_data
def test_icon_san_michele_loads_as_srgb8_stack():
    light_file = shared("rti/icon_san_michele/dirs.lp")
    stack = load_stack(light_file)
    assert isinstance(stack, SampleStack)
    # README says 402x395: that is width x height.
    assert stack.samples.shape == (1, 72, 395, 402, 3)
    assert stack.encoding == "srgb8" and stack.samples.dtype == np.uint8
    assert stack.channels == ("R", "G", "B")
    assert stack.names[0] == "image01.jpg" and len(stack.names) == 72
    np.testing.assert_allclose(stack.views, [[0, 0, 1]])
    np.testing.assert_allclose(stack.lights[0], [0.205158607891401, -0.237020612397229, 0.949595268999854],
                               atol=1e-6)
    with Image.open(light_file.parent / "image05.jpg") as image:
        np.testing.assert_array_equal(stack.samples[0, 4], np.asarray(image))
    np.testing.assert_array_equal(stack.linear(slice(0, 2))[0, 4], SRGB8_TO_LINEAR[stack.samples[0, 4, :2]])


@pytest.mark.shared_data
def test_realrti_item1_loads_with_unit_lights():
    stack = load_stack(shared("rti/realrti/item1/dirs.lp"))
    assert stack.samples.shape[:2] == (1, 60)
    np.testing.assert_allclose(np.linalg.norm(stack.lights, axis=1), 1.0, atol=1e-6)


@pytest.mark.shared_data
def test_realrti_non_unit_vectors_are_normalised():
    # item1's vectors are unit to 1e-6; item2's are 0.96-0.99 long, so they exercise the normalisation.
    light_file = shared("rti/realrti/item2/dirs.lp")
    raw = np.array([[float(v) for v in row.split()[-3:]] for row in light_file.read_text().splitlines()[1:]
                    if row.strip()])
    assert np.linalg.norm(raw, axis=1).min() < 0.97
    entries = read_light_file(light_file)
    lights = np.array([entry.light for entry in entries])
    np.testing.assert_allclose(np.linalg.norm(lights, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(lights, raw / np.linalg.norm(raw, axis=1, keepdims=True), atol=1e-12)


@pytest.mark.shared_data
def test_synthrti_dome_loads():
    stack = load_stack(shared("rti/synthrti/Single_Object1/material1/Dome/dirs.lp"), threads=3)
    assert stack.samples.shape == (1, 49, 320, 320, 3)
    assert stack.names[-1] == "image49.jpg"
    assert (stack.lights[:, 2] >= 0).all()


# ----------------------------------------------------------------------------------------------- broken light files


def test_count_larger_than_rows(tmp_path):
    names = make_capture(tmp_path)
    path = write_lp(tmp_path, lp_text(names, count=4))
    expect_error(path, 1, "count says 4 images", "3 rows follow")


def test_count_smaller_than_rows(tmp_path):
    names = make_capture(tmp_path)
    path = write_lp(tmp_path, lp_text(names, count=2))
    error = expect_error(path, 1, "count says 2 images", "3 rows follow", "line 4")
    assert "never guesses" in error.hint


def test_missing_image(tmp_path):
    names = make_capture(tmp_path)
    (tmp_path / names[1]).unlink()
    path = write_lp(tmp_path, lp_text(names))
    expect_error(path, 3, repr(names[1]), "no such file")
    # Without the image check the same file parses.
    assert len(read_light_file(path, require_images=False)) == 3


def test_missing_image_suggests_case_mismatch(tmp_path):
    names = make_capture(tmp_path)
    path = write_lp(tmp_path, lp_text([names[0].upper()] + names[1:]))
    error = expect_error(path, 2)
    assert repr(names[0]) in error.hint


def test_non_numeric_value(tmp_path):
    names = make_capture(tmp_path)
    text = lp_text(names).replace("0.5 ", "0.5x ", 1)
    expect_error(write_lp(tmp_path, text), 3, "expected a number", "'0.5x'")


def test_nan_is_not_a_direction(tmp_path):
    names = make_capture(tmp_path)
    text = lp_text(names).replace("0.5 ", "nan ", 1)
    expect_error(write_lp(tmp_path, text), 3, "expected a number", "'nan'")


def test_wrong_number_of_fields(tmp_path):
    names = make_capture(tmp_path)
    rows = lp_text(names).splitlines()
    short = rows[:2] + [rows[2].rsplit(" ", 1)[0]] + rows[3:]
    expect_error(write_lp(tmp_path, "\n".join(short)), 3, "expected a file name and 3 numbers", "found 3 fields")
    long = rows[:3] + [rows[3] + " 0.1"] + rows[4:]
    expect_error(write_lp(tmp_path, "\n".join(long)), 4, "expected 3 numbers", "found 4")


def test_six_numbers_in_lp_hints_at_lvp(tmp_path):
    names = make_capture(tmp_path, n=1)
    error = expect_error(write_lp(tmp_path, f"1\n{names[0]} 0 0 1 0 0 1\n"), 2, "found 6")
    assert ".lvp" in error.hint


def test_zero_vector(tmp_path):
    names = make_capture(tmp_path)
    expect_error(write_lp(tmp_path, lp_text(names, lights=[[0, 0, 1], [0, 0, 0], [0, 0.6, 0.8]])), 3,
                 "non-zero light direction")


def test_clearly_downward_vector(tmp_path):
    names = make_capture(tmp_path)
    down = [0.9, 0.0, -0.3]
    expect_error(write_lp(tmp_path, lp_text(names, lights=[[0, 0, 1], [0, 0.6, 0.8], down])), 4,
                 "above the horizon", "degrees below")


def test_slightly_below_horizon_is_clamped_with_warning(tmp_path):
    names = make_capture(tmp_path)
    slightly = [0.8, 0.6, -0.01]  # about 0.57 degrees below the horizon
    path = write_lp(tmp_path, lp_text(names, lights=[[0, 0, 1], slightly, [0, 0.6, 0.8]]))
    with pytest.warns(BtforgeWarning, match=rf"{path}, line 3: light direction is 0\.5\d degrees below"):
        stack = load_stack(path)
    np.testing.assert_allclose(stack.lights[1], [0.8, 0.6, 0.0], atol=1e-6)


def test_decimal_commas(tmp_path):
    names = make_capture(tmp_path)
    text = "3\n" + "".join(f"{n} {x} {y} {z}\n" for n, (x, y, z) in
                           zip(names, [("0", "0", "1"), ("0,6", "0", "0,8"), ("-0,6", "0,0", "0,8")]))
    entries = read_light_file(write_lp(tmp_path, text))
    np.testing.assert_allclose([e.light for e in entries], [[0, 0, 1], [0.6, 0, 0.8], [-0.6, 0, 0.8]])


def test_filenames_with_spaces(tmp_path):
    names = make_capture(tmp_path, names=["shot 1.png", "my  shot 2.png", "007.png"])
    path = write_lp(tmp_path, "# exported by hand\n\n" + lp_text(names).replace("\n", "   \n"))
    stack = load_stack(path)
    assert stack.names == ("shot 1.png", "my  shot 2.png", "007.png")
    entry = read_light_file(path)[0]
    assert entry == LightFileEntry(line=4, filename="shot 1.png", light=(0.0, 0.0, 1.0), view=None)


def test_crlf_and_bom(tmp_path):
    names = make_capture(tmp_path)
    path = tmp_path / "dirs.lp"
    path.write_bytes(b"\xef\xbb\xbf" + lp_text(names, newline="\r\n").encode())
    stack = load_stack(path)
    assert stack.n_light == 3 and stack.names == tuple(names)
    np.testing.assert_allclose(stack.lights, LIGHTS[:3], atol=1e-6)


def test_utf16_light_file(tmp_path):
    names = make_capture(tmp_path)
    path = tmp_path / "dirs.lp"
    path.write_bytes(lp_text(names, newline="\r\n").encode("utf-16"))  # Notepad's "Unicode", with its BOM
    assert load_stack(path).names == tuple(names)


def test_windows_paths(tmp_path):
    (tmp_path / "sub").mkdir()
    names = make_capture(tmp_path / "sub")
    stack = load_stack(write_lp(tmp_path, lp_text([f"sub\\{n}" for n in names])))
    assert stack.n_light == 3
    elsewhere = write_lp(tmp_path / "sub", lp_text([f"C:\\capture\\{n}" for n in names]))
    with pytest.raises(BtforgeInputError) as info:  # every row names a missing image: all in one message
        load_stack(elsewhere)
    assert f"{elsewhere}, line 2: expected the image" in str(info.value)
    assert f"did you mean {names[0]!r}" in str(info.value)  # the image beside the light file is suggested


def test_writer_refuses_names_that_read_back_differently(tmp_path):
    with pytest.raises(BtforgeInputError, match="unchanged") as info:
        write_light_file(tmp_path / "out.lp", ["a.png", "take 2"], LIGHTS[:2])
    assert "file name 1" in info.value.what and not (tmp_path / "out.lp").exists()
    write_light_file(tmp_path / "ok.lp", ["a b.png", "take 2.png"], LIGHTS[:2])
    assert [e.filename for e in read_light_file(tmp_path / "ok.lp", require_images=False)] == ["a b.png", "take 2.png"]


def test_mismatched_image_sizes(tmp_path):
    names = make_capture(tmp_path)
    Image.new("RGB", (7, 5)).save(tmp_path / names[2])
    expect_error(write_lp(tmp_path, lp_text(names)), 4, "6 x 5", "7 x 5", repr(names[2]), "line 2")


def test_mismatched_channel_counts(tmp_path):
    names = make_capture(tmp_path)
    Image.new("L", (6, 5)).save(tmp_path / names[1])
    expect_error(write_lp(tmp_path, lp_text(names)), 3, "3 channel(s)", "found 1", repr(names[1]))


def test_mismatched_bit_depth(tmp_path):
    names = make_capture(tmp_path, mode="L")
    Image.fromarray(np.full((5, 6), 1000, np.uint16)).save(tmp_path / names[1])
    expect_error(write_lp(tmp_path, lp_text(names)), 3, "8-bit", "16-bit")


def test_nan_in_exr(tmp_path):
    import OpenEXR

    pixels = np.ones((4, 5, 3), np.float32)
    write_exr(tmp_path / "a.exr", pixels)
    pixels[2, 3, 1] = np.nan
    # write_exr refuses NaN, so write the broken file with the bindings directly.
    OpenEXR.File({"type": OpenEXR.scanlineimage},
                 {c: np.ascontiguousarray(pixels[..., i]) for i, c in enumerate("RGB")}).write(str(tmp_path / "b.exr"))
    path = write_lp(tmp_path, lp_text(["a.exr", "b.exr"]))
    expect_error(path, 3, "'b.exr'", "NaN/Inf", "row 2, column 3")


def test_lvp_with_unequal_lights_per_view(tmp_path):
    names = make_capture(tmp_path, n=4)
    rows = [f"{names[0]} 0 0 1 0 0 1", f"{names[1]} 0.6 0 0.8 0 0 1",
            f"{names[2]} 0 0 1 0.6 0 0.8", f"{names[3]} 0 0.6 0.8 0.6 0 0.8"]
    path = write_lp(tmp_path, "4\n" + "\n".join(rows) + "\n", "dirs.lvp")
    expect_error(path, 5, "light 1 of view 1")
    path = write_lp(tmp_path, "3\n" + "\n".join(rows[:3]) + "\n", "dirs.lvp")
    expect_error(path, 4, "expected 2 lights for view 1", "found 1")


def test_bad_image_file_names_its_line(tmp_path):
    names = make_capture(tmp_path)
    (tmp_path / names[1]).write_bytes(b"not an image")
    expect_error(write_lp(tmp_path, lp_text(names)), 3, "cannot identify")


def test_parse_light_list():
    lights = parse_light_list([[0, 0, 2], [1, 0, 1]])
    assert lights.dtype == np.float32 and lights.shape == (2, 3)
    np.testing.assert_allclose(lights[1], [2 ** -0.5, 0, 2 ** -0.5], atol=1e-7)
    with pytest.warns(BtforgeWarning, match="entry 0"):
        np.testing.assert_allclose(parse_light_list([[1, 0, -0.001]]), [[1, 0, 0]])
    for bad, fragment in [([[0, 0, 0]], "non-zero"), ([[0, 0, -1]], "above the horizon"), ([[0, 1]], "[x, y, z]"),
                          ([[0, "a", 1]], "expected a number"), ([], "at least one"), (3, "list of")]:
        with pytest.raises(BtforgeInputError, match=fragment):
            parse_light_list(bad)


def test_write_light_file_round_trip(tmp_path):
    names = ["a b.png", "c.png"]
    write_light_file(tmp_path / "x.lp", names, [[0, 0, 3], [0.6, 0, 0.8]])
    entries = read_light_file(tmp_path / "x.lp", require_images=False)
    assert [e.filename for e in entries] == names
    np.testing.assert_allclose([e.light for e in entries], [[0, 0, 1], [0.6, 0, 0.8]], atol=1e-7)
    write_light_file(tmp_path / "x.lvp", names, [[0, 0, 1]] * 2, views=[[0, 0.6, 0.8]] * 2)
    assert read_light_file(tmp_path / "x.lvp", require_images=False)[1].view == pytest.approx((0, 0.6, 0.8))
    with pytest.raises(BtforgeInputError, match=".lvp name"):
        write_light_file(tmp_path / "y.lp", names, [[0, 0, 1]] * 2, views=[[0, 0, 1]] * 2)
    with pytest.raises(BtforgeInputError, match="leading"):
        write_light_file(tmp_path / "y.lp", [" a.png", "b.png"], [[0, 0, 1]] * 2)
    assert not (tmp_path / "y.lp").exists()


# ----------------------------------------------------------------------------------------------- round trips


def linear_stack(n_view: int = 1, channels: int = 3, scale: float = 1.0) -> SampleStack:
    rng = np.random.default_rng(3)
    samples = (rng.random((n_view, 4, 5, 6, channels)) * scale).astype(np.float32)
    views = [[0, 0, 1], [0.6, 0, 0.8]][:n_view]
    return SampleStack(samples=samples, lights=LIGHTS, views=np.array(views),
                       channels=("R", "G", "B") if channels == 3 else ("Y",))


def test_exr_float32_round_trip(tmp_path):
    stack = linear_stack(scale=40.0)  # radiance above 1 must survive
    written = write_stack(stack, tmp_path / "out")
    assert [p.name for p in written] == ["light_000.exr", "light_001.exr", "light_002.exr", "light_003.exr",
                                         "lights.lp"]
    loaded = load_stack(written[-1])
    assert loaded.encoding == "linear" and loaded.names == tuple(p.name for p in written[:-1])
    np.testing.assert_array_equal(loaded.samples, stack.samples)
    np.testing.assert_allclose(loaded.lights, stack.lights, atol=1e-7)
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".")], "temporary files left behind"


def test_exr_half_round_trip(tmp_path):
    stack = linear_stack(channels=1, scale=3.0)
    loaded = load_stack(write_stack(stack, tmp_path, half=True, stem="h")[-1])
    assert loaded.channels == ("Y",)
    np.testing.assert_allclose(loaded.samples, stack.samples, rtol=2 ** -11, atol=2 ** -24)
    assert not np.array_equal(loaded.samples, stack.samples)  # it really was stored as half


def test_exr_half_refuses_out_of_range(tmp_path):
    with pytest.raises(BtforgeInputError, match="half range"):
        write_exr(tmp_path / "x.exr", np.full((2, 2, 3), 1e6, np.float32), half=True)


def test_multi_view_round_trip(tmp_path):
    stack = linear_stack(n_view=2)
    written = write_stack(stack, tmp_path)
    assert written[0].name == "light_v000_l000.exr" and written[-1].name == "lights.lvp"
    loaded = load_stack(written[-1])
    assert loaded.samples.shape == stack.samples.shape
    np.testing.assert_array_equal(loaded.samples, stack.samples)
    np.testing.assert_allclose(loaded.views, stack.views, atol=1e-7)


def test_png_round_trip_within_one_step(tmp_path):
    stack = linear_stack()
    loaded = load_stack(write_stack(stack, tmp_path, fmt="png")[-1])
    assert loaded.encoding == "srgb8"
    expected = np.rint(np.clip(
        np.where(stack.samples <= 0.0031308, stack.samples * 12.92,
                 1.055 * np.power(stack.samples, 1 / 2.4) - 0.055), 0, 1) * 255)
    assert np.abs(loaded.samples.astype(int) - expected).max() <= 1
    # And an 8-bit stack goes out and back unchanged.
    again = load_stack(write_stack(loaded, tmp_path / "again", fmt="png")[-1])
    np.testing.assert_array_equal(again.samples, loaded.samples)


def test_png16_grey_read_as_linear(tmp_path):
    values = np.array([[0, 1, 32768, 65535]], np.uint16)
    Image.fromarray(values).save(tmp_path / "g.png")
    array, transfer = read_image(tmp_path / "g.png")
    assert transfer == "linear" and array.dtype == np.uint16 and array.shape == (1, 4, 1)
    np.testing.assert_array_equal(array[..., 0], values)
    write_lp(tmp_path, lp_text(["g.png"]))
    stack = load_stack(tmp_path / "dirs.lp")
    assert stack.encoding == "linear" and stack.channels == ("Y",)
    np.testing.assert_allclose(stack.samples[0, 0, ..., 0], values / 65535, rtol=1e-6)
    srgb = load_stack(tmp_path / "dirs.lp", transfer="srgb")
    np.testing.assert_allclose(srgb.samples[0, 0, ..., 0], srgb_to_linear(values / 65535), rtol=1e-6)


@pytest.mark.parametrize("colour_type, n_channel", [(2, 3), (6, 4), (4, 2)])
def test_png16_colour_keeps_all_16_bits(tmp_path, colour_type, n_channel):
    # Pillow alone would return only the high byte of these layouts.
    pixels = np.random.default_rng(colour_type).integers(0, 65536, (7, 9, n_channel)).astype(np.uint16)
    (tmp_path / "c.png").write_bytes(encode_png16(pixels, colour_type))
    array, transfer = read_image(tmp_path / "c.png")
    kept = pixels[..., :1] if n_channel == 2 else pixels[..., :3]
    assert transfer == "linear"
    np.testing.assert_array_equal(array, kept)


def test_write_png16_round_trip(tmp_path):
    linear = np.random.default_rng(1).random((5, 6, 3)).astype(np.float32)
    write_png(tmp_path / "c.png", linear, bits=16)
    array, transfer = read_image(tmp_path / "c.png")
    assert transfer == "linear" and array.dtype == np.uint16
    np.testing.assert_allclose(array / 65535, linear, atol=0.5 / 65535 + 1e-7)


def test_transfer_linear_on_8bit(tmp_path):
    names = make_capture(tmp_path, n=1)
    stack = load_stack(write_lp(tmp_path, lp_text(names)), transfer="linear")
    assert stack.encoding == "linear"
    with Image.open(tmp_path / names[0]) as image:
        np.testing.assert_allclose(stack.samples[0, 0], np.asarray(image) / 255, rtol=1e-6)
    with pytest.raises(BtforgeInputError, match="transfer"):
        load_stack(tmp_path / "dirs.lp", transfer="gamma")


def test_read_exr_rgba_half_and_y(tmp_path):
    import OpenEXR

    rgba = np.random.default_rng(0).random((3, 4, 4)).astype(np.float16)
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"RGBA": rgba}).write(str(tmp_path / "a.exr"))
    array = read_exr(tmp_path / "a.exr")
    assert array.dtype == np.float32
    np.testing.assert_array_equal(array, rgba[..., :3].astype(np.float32))
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"Z": rgba[..., 0]}).write(str(tmp_path / "z.exr"))
    with pytest.raises(BtforgeInputError, match=r"found \['Z'\]"):
        read_exr(tmp_path / "z.exr")


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # imageio's vendored tifffile
def test_16bit_colour_tiff_via_imageio(tmp_path):
    iio = pytest.importorskip("imageio.v3")
    pixels = np.random.default_rng(5).integers(0, 65536, (5, 6, 3)).astype(np.uint16)
    iio.imwrite(tmp_path / "c.tif", pixels)
    array, transfer = read_image(tmp_path / "c.tif")
    assert transfer == "linear"
    np.testing.assert_array_equal(array, pixels)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_16bit_colour_tiff_without_imageio_is_a_clear_error(tmp_path, monkeypatch):
    iio = pytest.importorskip("imageio.v3")
    iio.imwrite(tmp_path / "c.tif", np.zeros((2, 3, 3), np.uint16))
    monkeypatch.setitem(__import__("sys").modules, "imageio.v3", None)  # makes 'import imageio.v3' fail
    with pytest.raises(BtforgeInputError, match="without losing precision") as info:
        read_image(tmp_path / "c.tif")
    assert "install imageio" in info.value.hint


def test_a_light_file_reports_every_problem_at_once(tmp_path):
    (tmp_path / "a.png").write_bytes(b"")
    path = write_lp(tmp_path, "4\na.png 0 0 1\nb.png 0.1 zero 0.9\nc.png 0 0.2 0.98\n")
    with pytest.raises(BtforgeInputError) as info:
        read_light_file(path)
    text = str(info.value)
    assert "3 problems" in text
    assert "line 1: the count says 4 images, but 3 rows follow" in text
    assert "line 3: expected a number, found 'zero'" in text
    assert "line 4: expected the image 'c.png'" in text


def test_info_of_a_light_file_checks_images_and_counts_lights_and_views(tmp_path):
    from btforge.plugins.stackio import _describe_light_file
    rows = [f"img_{v}_{l}.png {lx} 0 {lz} {vx} 0 {vz}" for v, (vx, vz) in enumerate([(0, 1), (0.6, 0.8)])
            for l, (lx, lz) in enumerate([(0, 1), (0.6, 0.8), (-0.6, 0.8)])]
    for row in rows:
        (tmp_path / row.split()[0]).write_bytes(b"")
    lvp = tmp_path / "cap.lvp"
    lvp.write_text(f"{len(rows)}\n" + "\n".join(rows) + "\n")
    info = _describe_light_file(lvp)
    assert (info["images"], info["lights"], info["views"]) == (6, 3, 2)
    (tmp_path / "img_1_2.png").unlink()
    with pytest.raises(BtforgeInputError, match="line 7: expected the image 'img_1_2.png'"):
        _describe_light_file(lvp)
