"""Re-create this folder: 24 photographs of two mirror spheres (chrome/) and of a bumpy painted tile (tile/)
under the same 24 lamp positions, as JPEG q85.  The lights are known (lights_truth.lp), so the calibration can
be checked against them.  Run from the repository root: python3 graphs/data/chrome_demo/make_chrome_demo.py"""
from pathlib import Path

import numpy as np
from PIL import Image

from btforge.plugins.calibrate.synthetic import fibonacci_lights, render_capture
from btforge.plugins.demo.procedural import make_material, render_lights

HERE = Path(__file__).resolve().parent
LIGHTS = fibonacci_lights(24, min_elevation_deg=25.0, seed=3)


def srgb8(linear: np.ndarray) -> np.ndarray:
    linear = np.clip(linear, 0.0, 1.0)
    encoded = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
    return np.round(255 * encoded).astype(np.uint8)


def main() -> None:
    (HERE / "chrome").mkdir(exist_ok=True)
    (HERE / "tile").mkdir(exist_ok=True)
    render_capture(HERE / "chrome", LIGHTS, [(80, 100, 44), (240, 110, 40)], size=(240, 320), quality=85)
    material = make_material(160, 160, bumps=30, bump_height=4.0, seed=7)
    radiance = render_lights(material, LIGHTS.astype(np.float32), shadows=True)
    for index, image in enumerate(radiance):
        Image.fromarray(srgb8(0.9 * image)).save(HERE / "tile" / f"tile_{index:02d}.jpg", quality=85)
    rows = [f"tile_{i:02d}.jpg {x:.6f} {y:.6f} {z:.6f}" for i, (x, y, z) in enumerate(LIGHTS)]
    (HERE / "lights_truth.lp").write_text(f"{len(rows)}\n" + "\n".join(rows) + "\n")


if __name__ == "__main__":
    main()
