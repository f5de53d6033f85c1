"""The ``TileSet`` buffer: a complete Wang-tile set over one exemplar, stored as a BTFel table.

Tiles are never copies of reflectance data.  The **BTFel table** lists, once each, the exemplar texels any tile
references (``table [B, 2]`` row, column, sorted); each tile is a ``w x w`` map of indices into it
(``indices [T, w, w]``).  Tile ``t``'s coordinate map into the exemplar is ``table[indices[t]]``; replaying it on
any per-texel buffer of the exemplar gives the tile's texels (Leung et al. 2007, section 5.3 and Table III).  A set
whose interior seams are feathered also has a blend layer: ``blend_indices [T, w, w]`` into the same table and
``blend_weight [T, w, w]`` (0 where a texel does not blend), replayed as a coordinate map's blend layer is.

Colours: tile ``t`` has ``tile_colors[t] = (N, E, S, W)``; N and S take one of ``colors_h`` horizontal-edge
colours, E and W one of ``colors_v`` vertical-edge colours.  Two tiles may sit side by side when the left one's
E equals the right one's W, one above the other when the upper one's S equals the lower one's N.  A complete set
holds every combination ``variants`` times; tile ``((((N * colors_v + E) * colors_h + S) * colors_v + W) *
variants + k)`` is variant ``k`` of its combination.  ``edge_seams [T, 4]`` records, per tile edge (N, E, S, W),
the mean seam distance across it to every tile that may sit there, over the exemplar's mean neighbouring-texel
distance in that direction (1 = as smooth as the exemplar).

**File format** (``wang.write_tiles``, ``.wang``): a ZIP archive holding ``manifest.json`` and one ``.npy`` file per
array (``table.npy`` int32 [B, 2], ``indices.npy`` int32 [T, w, w], ``tile_colors.npy`` int32 [T, 4],
``edge_seams.npy`` float32 [T, 4], and with a blend layer ``blend_indices.npy`` int32 [T, w, w] and
``blend_weight.npy`` float32 [T, w, w]).  The manifest: ``{"format": "btforge-wang-tiles", "version": 2,
"colors_h", "colors_v", "variants", "tile", "edge", "source_size": [H, W], "texel_bytes", "tiles", "blends",
"btfels"}``; ``texel_bytes`` is the size of one exemplar texel of the representation the set was built on.
Version 1 archives (no blend layer) are read as they are.
"""
from __future__ import annotations

import dataclasses
import io
import json
import zipfile
from pathlib import Path
from typing import ClassVar

import numpy as np

from btforge.buffers import Buffer, CoordMap, check_array, frozen
from btforge.errors import BtforgeInputError, file_reader
from btforge.spill import read_npy

FORMAT = "btforge-wang-tiles"
VERSION = 2
READABLE_VERSIONS = (1, 2)
ARRAYS = ("table", "indices", "tile_colors", "edge_seams")
BLEND_ARRAYS = ("blend_indices", "blend_weight")  # written and read only where the set has a blend layer


LARGEST = 1 << 31  # bound of every size and count of a tile set


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


@dataclasses.dataclass(frozen=True, eq=False)
class TileSet(Buffer):
    """A Wang-tile set: edge colours per tile and the tiles as index maps into a BTFel table (module docs)."""

    type_name: ClassVar[str] = "TileSet"

    table: np.ndarray
    indices: np.ndarray
    tile_colors: np.ndarray
    edge_seams: np.ndarray
    colors_h: int
    colors_v: int
    source_size: tuple[int, int]
    edge: int
    variants: int = 1
    texel_bytes: int = 0
    blend_indices: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0, 0), np.int32))
    blend_weight: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0, 0), np.float32))

    def __post_init__(self):
        owner = "TileSet"
        check_array("table", self.table, ("B", 2), np.int32, owner=owner)
        check_array("indices", self.indices, ("T", "w", "w"), np.int32, owner=owner)
        t = self.indices.shape[0]
        check_array("tile_colors", self.tile_colors, (t, 4), np.int32, owner=owner)
        check_array("edge_seams", self.edge_seams, (t, 4), np.float32, owner=owner)
        problems = []
        size = tuple(self.source_size) if isinstance(self.source_size, (tuple, list)) else ()
        if len(size) != 2 or not all(_is_int(v) and 1 <= v < LARGEST for v in size):
            problems.append(f"'source_size' must be two ints in [1, {LARGEST}), got {self.source_size!r}")
        for name in ("colors_h", "colors_v", "edge", "variants", "texel_bytes"):
            value, least = getattr(self, name), 0 if name == "texel_bytes" else 1
            if not _is_int(value) or not least <= value < LARGEST:
                problems.append(f"'{name}' must be an int in [{least}, {LARGEST}), got {value!r}")
        if problems:
            raise BtforgeInputError(owner, "; ".join(problems))
        src_h, src_w = (int(v) for v in size)
        if self.table.size and (self.table.min() < 0 or self.table[:, 0].max() >= src_h
                                or self.table[:, 1].max() >= src_w):
            problems.append(f"'table' must lie inside the {src_h} x {src_w} exemplar")
        if self.indices.size and (self.indices.min() < 0 or self.indices.max() >= len(self.table)):
            problems.append(f"'indices' must lie in [0, {len(self.table)})")
        problems += self._blend_problems()
        n, e, s, w = self.tile_colors.T
        if t and (min(n.min(), s.min(), e.min(), w.min()) < 0 or max(n.max(), s.max()) >= self.colors_h
                  or max(e.max(), w.max()) >= self.colors_v):
            problems.append(f"'tile_colors' must hold N/S in [0, {self.colors_h}) and E/W in [0, {self.colors_v})")
        if problems:
            raise BtforgeInputError(owner, "; ".join(problems), "rebuild the tile set with wang.tiles")
        for name in ("colors_h", "colors_v", "edge", "variants", "texel_bytes"):
            object.__setattr__(self, name, int(getattr(self, name)))
        object.__setattr__(self, "source_size", (src_h, src_w))
        for name in ARRAYS + BLEND_ARRAYS:
            object.__setattr__(self, name, frozen(getattr(self, name)))

    def _blend_problems(self) -> list[str]:
        """What is wrong with the blend layer, if anything (none, or one of the indices' shape into the table)."""
        if not self.blend_indices.size and not self.blend_weight.size:
            return []
        shape = self.indices.shape
        index, weight = np.asarray(self.blend_indices), np.asarray(self.blend_weight)
        if index.shape != shape or weight.shape != shape or index.dtype != np.int32 or weight.dtype != np.float32:
            return [f"'blend_indices' (int32) and 'blend_weight' (float32) must both be {list(shape)} like 'indices', "
                    f"found {index.dtype} {list(index.shape)} and {weight.dtype} {list(weight.shape)}"]
        problems = []
        if index.min() < 0 or index.max() >= len(self.table):
            problems.append(f"'blend_indices' must lie in [0, {len(self.table)})")
        if not np.isfinite(weight).all() or weight.min() < 0 or weight.max() > 1:
            problems.append("'blend_weight' must lie in [0, 1]")
        return problems

    # -- construction ----------------------------------------------------------------------------------
    @classmethod
    def from_coords(cls, tile_coords: np.ndarray, tile_colors, edge_seams, *, colors_h: int, colors_v: int,
                    source_size, edge: int, variants: int = 1, texel_bytes: int = 0,
                    blend_coords: np.ndarray | None = None, blend_weight: np.ndarray | None = None) -> "TileSet":
        """Build the BTFel table of tiles given as coordinate maps ``[T, w, w, 2]`` into the exemplar (with their
        blend layer: partners ``blend_coords [T, w, w, 2]`` and weights ``blend_weight [T, w, w]``)."""
        src_w = int(source_size[1])
        maps = [tile_coords] if blend_weight is None else [tile_coords, blend_coords]
        flat = np.stack([m[..., 0].astype(np.int64) * src_w + m[..., 1] for m in maps])
        unique, inverse = np.unique(flat, return_inverse=True)
        inverse = inverse.reshape(flat.shape).astype(np.int32)
        table = np.stack([unique // src_w, unique % src_w], 1).astype(np.int32)
        blend = {} if blend_weight is None else {"blend_indices": inverse[1],
                                                 "blend_weight": np.asarray(blend_weight, np.float32)}
        return cls(table, inverse[0], np.asarray(tile_colors, np.int32), np.asarray(edge_seams, np.float32),
                   colors_h, colors_v, tuple(source_size), edge, variants, texel_bytes, **blend)

    # -- views -----------------------------------------------------------------------------------------
    @property
    def n_tiles(self) -> int:
        return self.indices.shape[0]

    @property
    def tile(self) -> int:
        return self.indices.shape[1]

    @property
    def tile_coords(self) -> np.ndarray:
        """``[T, w, w, 2]`` int32 exemplar coordinates of every tile texel, replayed from the BTFel table."""
        return self.table[self.indices]

    @property
    def blends(self) -> bool:
        return bool(self.blend_weight.size)

    def tile_blend_coords(self) -> np.ndarray:
        """``[T, w, w, 2]`` int32 exemplar coordinates of every tile texel's blend partner (a set with a blend
        layer)."""
        return self.table[self.blend_indices]

    def tile_map(self, index: int) -> CoordMap:
        """One tile as a coordinate map, with its blend layer if any (for ``synth.materialize``)."""
        if not self.blends:
            return CoordMap(np.ascontiguousarray(self.tile_coords[index]), self.source_size)
        return CoordMap(np.ascontiguousarray(self.tile_coords[index]), self.source_size,
                        blend_coords=np.ascontiguousarray(self.table[self.blend_indices[index]]),
                        blend_weight=np.ascontiguousarray(self.blend_weight[index]))

    def lookup(self, n: int, e: int, s: int, w: int) -> np.ndarray:
        """Indices of the tiles (variants) with colours N, E, S, W."""
        want = np.array([n, e, s, w], np.int32)
        return np.flatnonzero((self.tile_colors == want).all(axis=1))

    def statistics(self) -> dict:
        """Table III of the paper: the share of exemplar texels referenced, and the storage of table + indices."""
        index_bytes = 2 if len(self.table) <= 1 << 16 else 4
        table_bytes = len(self.table) * self.texel_bytes
        return {"tiles": self.n_tiles, "tile": self.tile, "edge": self.edge, "colors": [self.colors_h, self.colors_v],
                "variants": self.variants, "btfels": int(len(self.table)),
                "referenced_share": len(self.table) / float(self.source_size[0] * self.source_size[1]),
                "table_bytes": int(table_bytes), "index_bytes": int(self.indices.size * index_bytes),
                "total_bytes": int(table_bytes + self.indices.size * index_bytes),
                "texels_as_copies_bytes": int(self.indices.size * self.texel_bytes)}

    def seam_scores(self, exemplar, coords: CoordMap | None = None) -> dict:
        """The tile-set mode of ``synth.score``: seam ratios over every valid adjacency and 2 x 2 configuration, the
        BTFel statistics, and with ``coords`` (a ``wang.tiling`` of this set) its colour mismatches, tile use and
        whether its tile IDs repeat periodically (keys in :func:`btforge.plugins.wang.seams.tile_set_scores`)."""
        from .seams import tile_set_scores
        return tile_set_scores(self, exemplar, coords)

    # -- files -----------------------------------------------------------------------------------------
    def manifest(self) -> dict:
        return {"format": FORMAT, "version": VERSION, "colors_h": self.colors_h, "colors_v": self.colors_v,
                "variants": self.variants, "tile": self.tile, "edge": self.edge,
                "source_size": list(self.source_size), "texel_bytes": self.texel_bytes, "tiles": self.n_tiles,
                "btfels": int(len(self.table)), "blends": self.blends}

    def write(self, path) -> None:
        """Write the ``.wang`` archive (module docstring) atomically."""
        from btforge.atomic import atomic_output_path
        with atomic_output_path(Path(path)) as temporary:
            with zipfile.ZipFile(temporary, "w", zipfile.ZIP_DEFLATED) as archive:
                archive.writestr("manifest.json", json.dumps(self.manifest(), indent=2))
                for name in ARRAYS + (BLEND_ARRAYS if self.blends else ()):
                    bio = io.BytesIO()
                    np.save(bio, getattr(self, name), allow_pickle=False)
                    archive.writestr(f"{name}.npy", bio.getvalue())


DAMAGED = "the archive is damaged or truncated; write it again with wang.write_tiles"


@file_reader("a tile-set archive", DAMAGED)
def read_manifest(path) -> tuple[dict, zipfile.ZipFile]:
    path = Path(path)
    try:
        archive = zipfile.ZipFile(path)
        manifest = json.loads(archive.read("manifest.json").decode("utf-8"))
    except (zipfile.BadZipFile, KeyError, UnicodeDecodeError, json.JSONDecodeError, OSError) as exc:
        raise BtforgeInputError(str(path), f"is not a tile-set archive ({exc})",
                                "write tile sets with wang.write_tiles (a ZIP with manifest.json and .npy arrays)")
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        archive.close()
        raise BtforgeInputError(str(path), f"expected manifest format '{FORMAT}', found "
                                f"{manifest.get('format') if isinstance(manifest, dict) else manifest!r}")
    if manifest.get("version") not in READABLE_VERSIONS:
        archive.close()
        raise BtforgeInputError(str(path), f"expected format version {' or '.join(map(str, READABLE_VERSIONS))}, "
                                f"found {manifest.get('version')!r}",
                                "rewrite it with this btforge's wang.write_tiles")
    return manifest, archive


@file_reader("a tile-set archive", DAMAGED)
def read_tile_set(path) -> TileSet:
    manifest, archive = read_manifest(path)
    with archive:
        arrays = {}
        for name in ARRAYS + (BLEND_ARRAYS if manifest.get("blends") is True else ()):
            try:
                data = archive.read(f"{name}.npy")
                arrays[name] = read_npy(io.BytesIO(data), len(data), f"{path}, {name}.npy")
            except (KeyError, ValueError) as exc:
                raise BtforgeInputError(str(path), f"'{name}.npy' is missing or damaged ({exc})")
    missing = [k for k in ("colors_h", "colors_v", "source_size", "edge", "variants", "texel_bytes") if k not in manifest]
    if missing:
        raise BtforgeInputError(f"{path} manifest.json", f"lacks {', '.join(missing)}")
    blend = {name: arrays[name] for name in BLEND_ARRAYS if name in arrays}
    return TileSet(arrays["table"], arrays["indices"], arrays["tile_colors"], arrays["edge_seams"],
                   manifest["colors_h"], manifest["colors_v"], tuple(manifest["source_size"]), manifest["edge"],
                   manifest["variants"], manifest["texel_bytes"], **blend)


def describe(path) -> dict:
    """``btforge info`` for a ``.wang`` archive: the manifest and the table statistics."""
    tiles = read_tile_set(path)
    stats = tiles.statistics()
    seams = tiles.edge_seams[np.isfinite(tiles.edge_seams)]
    return {"kind": "Wang tile set", **stats, "source_size": list(tiles.source_size),
            "referenced_share": round(stats["referenced_share"], 4),
            "edge_seam_ratio": [round(float(seams.min()), 3), round(float(seams.max()), 3)] if seams.size else None}
