"""``LightTableModel``: per-texel coefficients over a light table (the hsh, rbf and bilinear bases).

A texel's display value (sRGB, in [0, 1]) under a light ``l`` is

    v(l) = M (w(l) @ T)[0] + sum_p coeffs[p] M (w(l) @ T)[p + 1]

with ``T [P + 1, D, 3]`` the light table (row 0 the mean response, row ``p + 1`` plane ``p``), ``w(l) [D]`` the
basis's weights over the table (:mod:`.lightfuncs`) and ``M`` the colour matrix (identity, or YCoCg -> RGB).
``relight.images`` clips ``v`` to [0, 1] and decodes it to linear radiance (a model of ``space`` linear holds
linear radiance of an 8-bit capture instead: clipped to [0, 1], not decoded).  The per-texel sum runs on OpenCL
(kernel ``basis_eval`` in ``bases.cl``; NumPy twin :func:`evaluate_numpy`).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import ClassVar

import numpy as np

from btforge.backend import get_backend
from btforge.buffers import (ReflectanceModel, check_array, frozen, scattered_lookup, srgb_to_linear,
                             unit_directions)
from btforge.errors import BtforgeInputError
from btforge.numerics import texel_chunks

from . import weblayout
from .lightfuncs import colour_matrix, table_weights

KERNELS = Path(__file__).with_name("bases.cl")
KINDS = ("hsh", "rbf", "bilinear")
COLORSPACES = ("rgb", "ycc")
HSH_TERMS = (4, 9)
SRGB_STEPS = 4096
SRGB_TABLE = srgb_to_linear(np.linspace(0.0, 1.0, SRGB_STEPS + 1)).astype(np.float32)
LINEAR_TABLE = np.linspace(0.0, 1.0, SRGB_STEPS + 1).astype(np.float32)  # the kernel's decode for linear fits
SPACES = ("srgb", "linear")
EVAL_OPTIONS = (f"-DSRGB_STEPS={SRGB_STEPS}",)


@dataclasses.dataclass(frozen=True, eq=False)
class LightTableModel(ReflectanceModel):
    """Coefficient planes over a light table: the ``hsh``, ``rbf`` and ``bilinear`` bases (see the module docs).

    ``coeffs [H, W, P]`` float32 (units of ``space``: display values, or linear radiance of an 8-bit capture,
    which evaluation clips to [0, 1] instead of decoding); ``table [P + 1, D, 3]`` float32 in ``colorspace`` (rgb or
    ycc, YCoCg); ``table_lights [D, 3]`` the rbf table's light directions (empty otherwise); ``sigma`` the rbf
    interpolation width; ``resolution`` the bilinear grid side; ``yccplanes`` (Y, Co, Cg) plane counts for ycc.
    """

    type_name: ClassVar[str] = "LightTableModel"
    texel_fields: ClassVar[tuple[str, ...]] = ("coeffs",)
    blendable: ClassVar[bool] = False  # coefficients of display values: a blend is not the blend of radiances
    mixes_records: ClassVar[bool] = True  # but their mix is the mix of the display values, before the decode
    web_types: ClassVar[tuple[str, ...]] = ("rbf", "bilinear", "bln")   # web layouts web.read reads into this class
    web_colorspaces: ClassVar[tuple[str, ...]] = ("mrgb", "mycc")

    kind: str
    coeffs: np.ndarray
    table: np.ndarray
    colorspace: str = "rgb"
    table_lights: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3), np.float32))
    sigma: float = 0.125
    resolution: int = 8
    yccplanes: tuple[int, ...] = (0, 0, 0)
    channel_names: tuple[str, ...] = ("R", "G", "B")
    space: str = "srgb"

    def __post_init__(self):
        owner = "LightTableModel"
        if self.kind not in KINDS:
            raise BtforgeInputError(f"{owner} 'kind'", f"must be one of {KINDS}, got {self.kind!r}")
        if self.colorspace not in COLORSPACES:
            raise BtforgeInputError(f"{owner} 'colorspace'", f"must be one of {COLORSPACES}, got {self.colorspace!r}")
        if self.space not in SPACES:
            raise BtforgeInputError(f"{owner} 'space'", f"must be one of {SPACES}, got {self.space!r}")
        if tuple(self.channel_names) != ("R", "G", "B"):
            raise BtforgeInputError(f"{owner} 'channel_names'", f"must be R, G, B, got {self.channel_names!r}")
        check_array("coeffs", self.coeffs, ("H", "W", "P"), np.float32, finite=True, owner=owner)
        n_plane = self.coeffs.shape[2]
        check_array("table", self.table, (n_plane + 1, "D", 3), np.float32, finite=True, owner=owner)
        check_array("table_lights", self.table_lights, ("D", 3), np.float32, finite=True, owner=owner)
        self._check_kind(owner, self.table.shape[1])
        object.__setattr__(self, "sigma", float(self.sigma))
        object.__setattr__(self, "resolution", int(self.resolution))
        object.__setattr__(self, "yccplanes", tuple(int(v) for v in self.yccplanes))
        object.__setattr__(self, "channel_names", tuple(self.channel_names))
        for name in ("coeffs", "table", "table_lights"):
            object.__setattr__(self, name, frozen(getattr(self, name)))

    def _check_kind(self, owner: str, n_table: int) -> None:
        expected = {"hsh": None, "rbf": len(self.table_lights), "bilinear": int(self.resolution) ** 2}[self.kind]
        if self.kind == "hsh" and n_table not in HSH_TERMS:
            raise BtforgeInputError(f"{owner} 'table'", f"an hsh table has 4 or 9 terms, got {n_table}")
        if expected is not None and n_table != expected:
            raise BtforgeInputError(f"{owner} 'table'", f"a {self.kind} table has {expected} directions "
                                    f"(table_lights / resolution^2), got {n_table}")
        if self.kind == "rbf" and not self.sigma > 0:
            raise BtforgeInputError(f"{owner} 'sigma'", f"must be > 0, got {self.sigma!r}")
        if self.kind == "bilinear" and not 2 <= int(self.resolution) <= 64:
            raise BtforgeInputError(f"{owner} 'resolution'", f"must be in [2, 64], got {self.resolution!r}")

    @property
    def channels(self) -> tuple[str, ...]:
        return self.channel_names

    @property
    def n_plane(self) -> int:
        return self.coeffs.shape[2]

    def light_weights(self, lights: np.ndarray) -> np.ndarray:
        """The basis at unit ``lights [L, 3]`` in RGB: ``lw [L, P + 1, 3]`` float32 (row 0 the mean)."""
        w = table_weights(self.kind, lights, terms=self.table.shape[1], table_lights=self.table_lights,
                          sigma=self.sigma, resolution=self.resolution)
        lw = np.einsum("ld,pdk->lpk", w, self.table.astype(np.float64))
        return (lw @ colour_matrix(self.colorspace).T).astype(np.float32)

    def web_layout(self) -> tuple[dict, np.ndarray]:
        """``(info fields, planes [P, H, W])`` for relight's web layout (:mod:`.weblayout`)."""
        return weblayout.web_layout(self)

    @classmethod
    def from_web(cls, info: dict, planes: np.ndarray) -> "LightTableModel":
        """The model an ``rbf`` or ``bilinear`` web layout holds (``planes`` the decoded coefficient planes)."""
        return weblayout.from_web(cls, info, planes)

    def evaluate(self, lights: np.ndarray, views: np.ndarray | None = None, *, engine: str = "opencl") -> np.ndarray:
        """Linear radiance ``[1, L, H, W, 3]``: the display value clipped to [0, 1] and decoded."""
        lights = unit_directions("lights", lights, owner=f"{self.kind} evaluation")
        lw = self.light_weights(lights)
        coeffs = self.coeffs.reshape(-1, self.n_plane)
        run = evaluate_numpy if engine == "numpy" else evaluate_opencl
        out = np.empty((len(lights), coeffs.shape[0], 3), np.float32)
        for chunk in texel_chunks(coeffs.shape[0], 4 * (self.n_plane + 3 * max(len(lights), 1))):
            out[:, chunk] = run(coeffs[chunk], lw, self.space)
        return out.reshape(1, len(lights), self.height, self.width, 3)

    def evaluate_texels(self, rows: np.ndarray, cols: np.ndarray, lights_local: np.ndarray,
                        views_local: np.ndarray | None = None) -> np.ndarray:
        """Linear radiance ``[N, 3]`` of texels ``(rows[i], cols[i])``, each at its own light ``[N, 3]``."""
        rows, cols, lights, _ = scattered_lookup(self, rows, cols, lights_local, views_local)
        norm = np.linalg.norm(lights, axis=1, keepdims=True)
        lw = self.light_weights(lights / np.where(norm > 0, norm, 1.0))
        c = self.coeffs[rows, cols]
        value = lw[:, 0] + np.einsum("np,npk->nk", c, lw[:, 1:])
        return decode(value, self.space)


def decode(value: np.ndarray, space: str) -> np.ndarray:
    """Evaluated values -> linear radiance float32: clipped to [0, 1], then decoded by the sRGB curve (``srgb``)
    or kept (``linear``)."""
    clipped = np.clip(value, 0.0, 1.0)
    return (srgb_to_linear(clipped) if space == "srgb" else clipped).astype(np.float32)


def evaluate_numpy(coeffs: np.ndarray, lw: np.ndarray, space: str = "srgb") -> np.ndarray:
    """Twin of kernel ``basis_eval``: ``coeffs [T, P]``, ``lw [L, P + 1, 3]`` -> linear ``[L, T, 3]`` float32
    (the exact sRGB curve; the kernel interpolates a table of it)."""
    value = lw[:, None, 0, :] + np.einsum("tp,lpk->ltk", coeffs.astype(np.float64), lw[:, 1:].astype(np.float64))
    return decode(value, space)


def evaluate_opencl(coeffs: np.ndarray, lw: np.ndarray, space: str = "srgb") -> np.ndarray:
    """Kernel ``basis_eval`` on ``coeffs [T, P]`` and ``lw [L, P + 1, 3]`` -> linear ``[L, T, 3]`` float32 (its
    decode table: the sRGB curve, or for ``space`` linear the identity)."""
    backend = get_backend()
    n_texel, n_plane = coeffs.shape
    n_light = lw.shape[0]
    out = np.empty((n_light, n_texel, 3), np.float32)
    if out.size == 0:
        return out
    kernel = backend.kernel(KERNELS, "basis_eval", EVAL_OPTIONS)
    o_dev = backend.host_output(out)
    backend.run(kernel, (n_texel, n_light), backend.host_input(np.ascontiguousarray(coeffs, np.float32)),
                backend.to_device(np.ascontiguousarray(lw, np.float32)),
                backend.to_device(SRGB_TABLE if space == "srgb" else LINEAR_TABLE),
                np.int32(n_plane), np.int32(n_texel), np.int32(n_light), o_dev)
    backend.finish_output(o_dev, out)
    return out
