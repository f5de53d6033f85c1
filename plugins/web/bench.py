"""``btforge bench web``: export / read times of relight's web layout and the round trip's relit PSNR."""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def bench_web(args: list[str]) -> int:
    """Web-layout export and read time, and relit PSNR of export -> read against the original model."""
    import btforge
    from btforge.buffers import linear_to_srgb
    from .layout import read_web, write_web
    parser = argparse.ArgumentParser(prog="btforge bench web")
    parser.add_argument("model", help="a web layout (folder or info.json) to read, re-export and read back")
    parser.add_argument("--format", choices=("png", "jpg"), default="png")
    opts = parser.parse_args(args)
    start = time.perf_counter()
    model = read_web(Path(opts.model))
    read_s = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as scratch:
        start = time.perf_counter()
        write_web(model, scratch, opts.format)
        write_s = time.perf_counter() - start
        again = read_web(Path(scratch))
    rng = np.random.default_rng(0)
    z = rng.uniform(0.2, 1.0, 16)
    phi = rng.uniform(0, 2 * np.pi, 16)
    lights = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], 1)
    relight = btforge.stage("relight.images")
    a = linear_to_srgb(relight(model=model, lights=lights.tolist())["stack"].samples)
    b = linear_to_srgb(relight(model=again, lights=lights.tolist())["stack"].samples)
    psnr = 10 * np.log10(1.0 / max(float(np.mean((a - b) ** 2)), 1e-20))
    print(f"{model.type_name} {model.width} x {model.height}: read {read_s:.2f} s, export ({opts.format}) "
          f"{write_s:.2f} s, round trip at 16 lights {psnr:.1f} dB")
    return 0
