"""A writer of Bonn UBO2014 ``.btf`` files (DFMF) for the tests, following the public layout that
``btforge.plugins.stackio.ubo2014`` documents: the tests write small files and check the reader returns exactly
what went in."""
import struct

import numpy as np


def _text(value: str, size: int) -> bytes:
    return value.encode("latin-1")[:size].ljust(size, b"\0")


def meta_block(*, version=4, channels=("R", "G", "B"), cosine=False, xml="<measurement/>") -> bytes:
    body = struct.pack("<I", version) + _text("test dome", 80) + _text("test sensor", 80) + _text("test LEDs", 80)
    body += struct.pack("<4f", 10.5, 1.0, 1.0, 1.0)
    if version > 1:
        body += struct.pack("<I", int(cosine))
    if version > 2:
        body += struct.pack("<I", len(xml)) + xml.encode()
    if version > 3:
        body += struct.pack("<I", len(channels)) + b"".join(struct.pack("<I", len(c)) + c.encode() for c in channels)
    return struct.pack("<I", 4 + len(body)) + body


def write_dfmf(path, light_angles, view_angles, width, height, factors, *, dtype="<f4", colour_model=0,
               colour_mean=(0.0, 0.0, 0.0), colour_transform=np.eye(3), cosine=False, rotations=2, version=4,
               channels=("R", "G", "B"), signature=b"!DFMF08FCR"):
    """Write ``factors`` (per channel ``(S [K], U [rows, K], SxV [cols, K])``) with the given angles (radians,
    ``[N, 2]`` theta/phi) as a DFMF file; returns the arrays as stored (cast to ``dtype``)."""
    out = bytearray(signature)
    out += meta_block(version=version, channels=channels, cosine=cosine)
    out += struct.pack("<I", len(view_angles))
    lights = np.asarray(light_angles, "<f4")
    for theta, phi in np.asarray(view_angles, "<f4"):
        out += struct.pack("<ffI", theta, phi, len(lights)) + lights.tobytes()
    out += struct.pack("<II", width, height)
    if signature.endswith(b"R"):
        out += struct.pack("<I", rotations) + np.tile(np.eye(3, dtype="<f4"), (rotations, 1, 1)).tobytes()
    out += struct.pack("<Ii", max(len(f[0]) for f in factors), colour_model)
    out += np.asarray(colour_mean, "<f4").tobytes() + np.asarray(colour_transform, "<f4").tobytes()
    stored = []
    for singular, left, right in factors:
        arrays = [np.ascontiguousarray(a, dtype) for a in (singular, left, right)]
        out += struct.pack("<BIII", np.dtype(dtype).itemsize, len(singular), left.shape[0], right.shape[0])
        out += b"".join(a.tobytes() for a in arrays)
        stored.append(arrays)
    path.write_bytes(bytes(out))
    return stored


def random_factors(rng, n_pair, n_texel, components=(3, 2, 2), transposed=False):
    """Per channel (S, U, SxV) of random low-rank BTF matrices (positive-ish values, as radiance would be)."""
    factors = []
    for k in components:
        angular = rng.uniform(0.0, 1.0, (n_pair, k)) / np.sqrt(k)
        spatial = rng.uniform(0.0, 1.0, (n_texel, k))
        singular = np.linalg.norm(spatial, axis=0)
        factors.append((singular, spatial, angular) if transposed else (singular, angular, spatial))
    return factors
