"""The rendered image buffer and its writers: linear EXR, tonemapped PNG, animated GIF / MP4 (imageio)."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import ClassVar

import numpy as np

from btforge.atomic import atomic_output_path, atomic_write
from btforge.buffers import Buffer, check_array, freeze_fields, linear_to_srgb
from btforge.errors import BtforgeInputError

FORMATS = ("exr", "png", "gif", "mp4")


@dataclasses.dataclass(frozen=True, eq=False)
class Image(Buffer):
    """Linear RGB radiance from a renderer: ``[H, W, 3]`` float32, or ``[F, H, W, 3]`` frames (a light sweep or turntable).

    ``tonemap`` and ``exposure`` (stops) say how display formats (PNG, GIF, MP4) encode it: with ``tonemap`` the
    values are scaled by ``2 ** exposure`` and sRGB-encoded; without, they are clipped to [0, 1] and written as
    they are.  ``fps`` is the frame rate of animations.
    """

    type_name: ClassVar[str] = "Image"

    pixels: np.ndarray
    exposure: float = 0.0
    tonemap: bool = True
    fps: float = 12.0

    def __post_init__(self):
        pixels = self.pixels
        if isinstance(pixels, np.ndarray) and pixels.ndim == 3:
            check_array("pixels", pixels, ("H", "W", 3), np.float32, finite=True, owner="Image")
        else:
            check_array("pixels", pixels, ("F", "H", "W", 3), np.float32, finite=True, owner="Image")
        if 0 in pixels.shape:
            raise BtforgeInputError("Image 'pixels'", f"must not be empty, got shape {pixels.shape}")
        if not np.isfinite(self.exposure):
            raise BtforgeInputError("Image 'exposure'", f"must be finite, got {self.exposure}")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise BtforgeInputError("Image 'fps'", f"must be a positive number, got {self.fps}")
        freeze_fields(self, pixels=pixels, exposure=float(self.exposure), tonemap=bool(self.tonemap),
                      fps=float(self.fps))

    @property
    def frames(self) -> np.ndarray:
        """Always ``[F, H, W, 3]``."""
        return self.pixels if self.pixels.ndim == 4 else self.pixels[None]

    @property
    def n_frames(self) -> int:
        return self.frames.shape[0]

    @property
    def height(self) -> int:
        return self.frames.shape[1]

    @property
    def width(self) -> int:
        return self.frames.shape[2]

    def display(self) -> np.ndarray:
        """8-bit display values ``[F, H, W, 3]`` uint8 (tonemapped: exposure then sRGB; else clipped linear)."""
        frames = self.frames.astype(np.float64)
        if self.tonemap:
            encoded = linear_to_srgb(frames * 2.0 ** self.exposure)
        else:
            encoded = np.clip(frames, 0.0, 1.0)
        return np.rint(encoded * 255.0).astype(np.uint8)


def format_of(path: str, fmt: str) -> str:
    """The format to write: ``fmt`` unless it is ``auto``, else the path's extension."""
    if fmt != "auto":
        return fmt
    ext = Path(path).suffix.lower().lstrip(".")
    if ext not in FORMATS:
        raise BtforgeInputError(f"render.write_image 'path' {path}", f"cannot tell the format from the extension '.{ext}'",
                                f"name the file .exr, .png, .gif or .mp4, or set format: one of {', '.join(FORMATS)}")
    return ext


def mp4_backend() -> str | None:
    """Which imageio plugin can encode MP4 here ('pyav' or 'FFMPEG'), or None."""
    try:
        import av  # noqa: F401
        return "pyav"
    except ImportError:
        pass
    try:
        import imageio_ffmpeg  # noqa: F401
        return "FFMPEG"
    except ImportError:
        return None


def check_writable(fmt: str) -> None:
    """Raise now (at validation) if this machine cannot write ``fmt``."""
    if fmt in ("gif", "mp4"):
        try:
            import imageio  # noqa: F401
        except ImportError:
            raise BtforgeInputError("render.write_image", f"writing {fmt.upper()} needs imageio, which is not installed",
                                    "pip install imageio (or btforge[render])") from None
    if fmt == "mp4" and mp4_backend() is None:
        raise BtforgeInputError("render.write_image", "writing MP4 needs an imageio video plugin, found neither PyAV nor "
                                "imageio-ffmpeg", "pip install imageio-ffmpeg (or av), or write format: gif")


def numbered(path: Path, index: int, count: int) -> Path:
    """``path`` itself for a single frame, else ``stem_NNN.ext``."""
    if count == 1:
        return path
    return path.with_name(f"{path.stem}_{index:03d}{path.suffix}")


def write_image(image: Image, path: str | os.PathLike, fmt: str) -> list[Path]:
    """Write ``image`` as ``fmt``; returns the files written (one per frame for EXR/PNG animations)."""
    from btforge.plugins.stackio.images import write_exr

    path = Path(path)
    check_writable(fmt)
    frames = image.frames
    if fmt == "exr":
        out = [numbered(path, i, len(frames)) for i in range(len(frames))]
        for target, frame in zip(out, frames):
            write_exr(target, frame)
        return out
    display = image.display()
    if fmt == "png":
        from PIL import Image as PILImage
        out = [numbered(path, i, len(frames)) for i in range(len(frames))]
        for target, frame in zip(out, display):
            with atomic_write(target, "wb") as handle:
                PILImage.fromarray(frame).save(handle, format="PNG")
        return out
    import imageio.v3 as iio
    if fmt == "gif":
        with atomic_output_path(path) as temporary:
            iio.imwrite(temporary, display, extension=".gif", duration=1000.0 / image.fps, loop=0)
        return [path]
    # MP4 (H.264, yuv420p) needs even sizes: pad by repeating the last row/column.
    h, w = display.shape[1:3]
    display = np.pad(display, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    plugin = mp4_backend()
    with atomic_output_path(path) as temporary:
        if plugin == "pyav":
            iio.imwrite(temporary, display, plugin="pyav", codec="libx264", fps=image.fps,
                        out_pixel_format="yuv420p")
        else:
            iio.imwrite(temporary, display, plugin="FFMPEG", fps=image.fps, codec="libx264",
                        pixelformat="yuv420p", macro_block_size=1)
    return [path]
