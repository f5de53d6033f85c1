"""Patch-placement error over the whole exemplar: the heavy distance work of graph-cut patch filling.

For a window of ``ph x pw`` pixels whose known pixels have features ``target [n, D]`` at offsets ``(dy, dx)``,
the error of placing the window's origin at exemplar texel ``(y, x)`` is ``sum_p |F[y + dy_p, x + dx_p] -
target_p|^2`` over every placement that keeps the window inside the exemplar.  Kernel ``placement_ssd``
(``placement.cl``, one work item per placement) and its NumPy twin :func:`placement_errors_numpy`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from btforge.backend import get_backend
from btforge.errors import BtforgeInputError

KERNELS = Path(__file__).with_name("placement.cl")


def _checked(feats, offsets, target, window, stride=1):
    feats = np.ascontiguousarray(feats, np.float32)
    offsets = np.ascontiguousarray(offsets, np.int32).reshape(-1, 2)
    target = np.ascontiguousarray(target, np.float32).reshape(len(offsets), feats.shape[2])
    ph, pw = window
    n_rows, n_cols = -(-(feats.shape[0] - ph + 1) // stride), -(-(feats.shape[1] - pw + 1) // stride)
    if n_rows < 1 or n_cols < 1:
        raise BtforgeInputError("wang.tiles", f"expected a window ({ph} x {pw}) no larger than the "
                                f"{feats.shape[0]} x {feats.shape[1]} exemplar", "lower 'tile' or 'edge'")
    if len(offsets) and (offsets.min() < 0 or offsets[:, 0].max() >= ph or offsets[:, 1].max() >= pw):
        raise BtforgeInputError("wang placement", "offsets must lie inside the window")
    return feats, offsets, target, n_rows, n_cols


#: Gathered values per step of the NumPy twin (offsets x placements): a small search (the local refinement's few
#: placements) gathers all its offsets in one step, a search over the whole exemplar a few offsets at a time.
GATHER_CAP = 1 << 16


def placement_errors_numpy(feats: np.ndarray, offsets: np.ndarray, target: np.ndarray,
                           window: tuple[int, int], stride: int = 1) -> np.ndarray:
    """Reference: ``[ceil((H - ph + 1) / stride), ceil((W - pw + 1) / stride)]`` float32 errors of the
    placements at multiples of ``stride``, summed in float64 over the offsets in their order."""
    feats, offsets, target, n_rows, n_cols = _checked(feats, offsets, target, window, stride)
    acc = np.zeros((n_rows, n_cols), np.float64)
    chunk = max(1, GATHER_CAP // (n_rows * n_cols))
    steps_y, steps_x = stride * np.arange(n_rows), stride * np.arange(n_cols)
    for start in range(0, len(offsets), chunk):
        dy, dx = offsets[start:start + chunk].T
        part = feats[dy[:, None, None] + steps_y[None, :, None], dx[:, None, None] + steps_x[None, None, :]]
        diff = part.astype(np.float64) - target[start:start + chunk].astype(np.float64)[:, None, None, :]
        for error in np.einsum("nijd,nijd->nij", diff, diff):
            acc += error
    return acc.astype(np.float32)


def placement_errors_opencl(feats: np.ndarray, offsets: np.ndarray, target: np.ndarray,
                            window: tuple[int, int], stride: int = 1, device_feats=None) -> np.ndarray:
    """The same errors from kernel ``placement_ssd``; ``device_feats`` reuses an uploaded exemplar."""
    feats, offsets, target, n_rows, n_cols = _checked(feats, offsets, target, window, stride)
    backend = get_backend()
    if len(offsets) == 0:
        return np.zeros((n_rows, n_cols), np.float32)
    kernel = backend.kernel(KERNELS, "placement_ssd")
    feats_dev = device_feats if device_feats is not None else backend.host_input(feats)
    out = np.empty((n_rows, n_cols), np.float32)
    out_dev = backend.empty(out.nbytes)
    backend.run(kernel, (n_cols, n_rows), feats_dev, np.int32(feats.shape[1]), np.int32(feats.shape[2]),
                backend.to_device(offsets), backend.to_device(target), np.int32(len(offsets)), np.int32(n_cols),
                np.int32(stride), out_dev)
    backend.cl.enqueue_copy(backend.queue, out, out_dev)
    backend.queue.finish()
    return out


class PlacementSearch:
    """Placement errors over one exemplar's features, uploaded once (``engine`` ``opencl`` or ``numpy``)."""

    def __init__(self, feats: np.ndarray, engine: str = "opencl"):
        if engine not in ("opencl", "numpy"):
            raise BtforgeInputError("wang.tiles 'engine'", f"must be 'opencl' or 'numpy', got {engine!r}")
        self.feats = np.ascontiguousarray(feats, np.float32)
        self.engine = engine
        self._device = get_backend().host_input(self.feats) if engine == "opencl" else None
        self.calls = 0

    def errors(self, offsets: np.ndarray, target: np.ndarray, window: tuple[int, int], stride: int = 1) -> np.ndarray:
        self.calls += 1
        if self.engine == "numpy":
            return placement_errors_numpy(self.feats, offsets, target, window, stride)
        return placement_errors_opencl(self.feats, offsets, target, window, stride, self._device)

    def refine(self, offsets: np.ndarray, target: np.ndarray, window: tuple[int, int], y: int, x: int,
               reach: int) -> tuple[int, int]:
        """The best placement within ``reach`` texels of ``(y, x)`` (exact, on the host: a handful of them)."""
        ph, pw = window
        y0, x0 = max(0, y - reach), max(0, x - reach)
        y1 = min(self.feats.shape[0] - ph, y + reach)
        x1 = min(self.feats.shape[1] - pw, x + reach)
        local = self.feats[y0:y1 + ph, x0:x1 + pw]
        errors = placement_errors_numpy(local, offsets, target, window)
        dy, dx = np.unravel_index(int(np.argmin(errors)), errors.shape)
        return y0 + int(dy), x0 + int(dx)
