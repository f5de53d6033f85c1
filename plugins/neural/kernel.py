"""Relighting a ``NeuralModel`` on the OpenCL device: kernel ``neural_relight`` of ``neural.cl``, one work-item per
texel (its NumPy twin is ``NeuralModel.evaluate(..., engine="numpy")``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from btforge.backend import get_backend
from btforge.numerics import texel_chunks

from .lightinput import harmonics, light_features

KERNELS = Path(__file__).with_name("neural.cl")
GROUP = 4             # work-items per work-group (each with its own private arrays on a PoCL thread's stack)
LANES = 8              # texels per work-item (neural.cl)
GROUP_MAX_UNITS = 512  # wider layers run one work-item per group (their private arrays are large)


def network_buffer(layers) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The layers ``[W [in, out], b]`` as neural.cl reads them: (weights output-major then biases, per layer;
    each layer's offset; the unit counts)."""
    parts, offsets, at = [], [], 0
    for w, b in layers:
        offsets.append(at)
        parts += [np.ascontiguousarray(w.T).reshape(-1), b]
        at += w.size + b.size
    sizes = [layers[0][0].shape[0]] + [w.shape[1] for w, _ in layers]
    return (np.concatenate(parts).astype(np.float32), np.asarray(offsets, np.int32), np.asarray(sizes, np.int32))


def relight_opencl(codes: np.ndarray, lights: np.ndarray, layers, decoder: str, light_order: int,
                   n_channel: int, budget_bytes: int = 128 << 20) -> np.ndarray:
    """Linear radiance ``[L, T, C]`` float32 of ``codes [T, K]`` at unit ``lights [L, 3]``."""
    backend = get_backend()
    net, offsets, sizes = network_buffer(layers)
    harmonic = decoder == "harmonics"
    widest = int(sizes.max())
    options = (f"-DN_LAYERS={len(layers)}", f"-DMAX_UNITS={widest}") + (("-DHARMONICS",) if harmonic else ())
    kernel = backend.kernel(KERNELS, "neural_relight", options)
    k, n_light, n_texel = codes.shape[1], len(lights), codes.shape[0]
    if harmonic:
        basis, light_part = harmonics(lights, light_order), np.zeros(1, np.float32)
    else:
        w1, b1 = layers[0]
        basis, light_part = np.zeros(1, np.float32), light_features(lights, light_order) @ w1[k:] + b1
    buffers = [backend.to_device(np.ascontiguousarray(a, dtype)) for a, dtype in
               ((net, np.float32), (offsets, np.int32), (sizes, np.int32), (light_part, np.float32),
                (basis, np.float32))]
    group = GROUP if widest <= GROUP_MAX_UNITS else 1
    out = np.empty((n_light, n_texel, n_channel), np.float32)
    for chunk in texel_chunks(n_texel, 4 * (k + n_light * n_channel), budget_bytes):
        n = chunk.stop - chunk.start
        padded = -(-n // (LANES * group)) * LANES * group
        lanes = np.zeros((k, padded), np.float32)      # texel-minor: a work-item reads 8 texels' code j at once
        lanes[:, :n] = codes[chunk].T
        out_dev = backend.empty(4 * n_light * padded * n_channel)
        backend.run(kernel, (padded // LANES,), backend.to_device(lanes), *buffers, np.int32(k), np.int32(padded),
                    np.int32(n_light), np.int32(n_channel), out_dev, local_size=(group,))
        out[:, chunk] = backend.from_device(out_dev, (n_light, padded, n_channel), np.float32)[:, :n]
    return out
