"""PLY and OBJ triangle meshes read and checked in NumPy, so no damaged file reaches native code.

Every count in a header is checked against what the file can hold before anything is allocated, every index
against the vertex count, every value for being finite.  A mesh comes back as ``positions [V, 3]`` float32,
``triangles [F, 3]`` int32 (polygons fanned into triangles) and ``corner_uv [F, 3, 2]`` float32 (``[0, 3, 2]``
without texture coordinates).  Like common mesh loaders, a vertex whose corners carry different texture
coordinates (an OBJ ``v`` used with several ``vt``) is split into one vertex per coordinate; the renderer welds
positions back together where it needs the surface's connectivity.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from btforge.errors import BtforgeInputError, file_reader

PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
PLY_FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
UV_NAMES = (("u", "v"), ("s", "t"), ("texture_u", "texture_v"), ("texture_s", "texture_t"))
INDEX_NAMES = ("vertex_indices", "vertex_index")
MAX_HEADER_BYTES = 1 << 16
MAX_POLYGON = 255  # corners of one face


class MeshFileError(BtforgeInputError):
    """A mesh file that cannot be used: names the file (and line), what is wrong and the fix."""

    def __init__(self, path: Path, problem: str, line: int | None = None,
                 hint: str = "re-export the mesh (PLY or OBJ with triangles or polygons)"):
        super().__init__(f"{path}" + (f", line {line}" if line else ""), problem, hint)


@file_reader("a PLY or OBJ mesh", "re-export the mesh (PLY or OBJ with triangles or polygons)")
def read_mesh(path: str | Path) -> dict[str, np.ndarray]:
    """Read a ``.ply`` or ``.obj`` mesh (chosen by suffix), checked; see the module docstring."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise MeshFileError(path, f"cannot be read ({exc.strerror or exc})", hint="check the path and permissions")
    positions, triangles, corner_uv = (read_obj if path.suffix.lower() == ".obj" else read_ply)(data, path)
    if len(triangles) == 0:
        raise MeshFileError(path, "has no faces: expected a triangle mesh, found only points")
    if not np.isfinite(positions).all():
        raise MeshFileError(path, "has NaN/Inf vertex positions")
    if corner_uv.size and not np.isfinite(corner_uv).all():
        raise MeshFileError(path, "has NaN/Inf texture coordinates")
    if np.abs(positions).max() > 1e30:
        raise MeshFileError(path, f"has vertex coordinates up to {np.abs(positions).max():.3g}, expected below 1e30")
    return {"positions": positions.astype(np.float32), "triangles": triangles.astype(np.int32),
            "corner_uv": corner_uv.astype(np.float32)}


def fan(polygons: np.ndarray) -> np.ndarray:
    """Triangles ``[F * (k - 2), 3]`` of polygons given as rows of ``k >= 3`` corner indices, each fanned from its
    first corner."""
    k = polygons.shape[1]
    return np.stack([np.stack([polygons[:, 0], polygons[:, i], polygons[:, i + 1]], 1)
                     for i in range(1, k - 1)], 1).reshape(-1, 3)


def fan_runs(corners: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Triangles of polygons given as consecutive runs of ``corners``, ``sizes[i] >= 3`` corners each, fanned and
    kept in the order of the polygons."""
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    parts, owners = [], []
    for k in np.unique(sizes):  # one vectorised fan per polygon size, put back in file order after
        rows = np.flatnonzero(sizes == k)
        parts.append(fan(corners[starts[rows, None] + np.arange(k)]))
        owners.append(np.repeat(rows, k - 2))
    order = np.argsort(np.concatenate(owners), kind="stable")
    return np.concatenate(parts)[order]


# ----------------------------------------------------------------------------------------------- PLY


def _ply_header(data: bytes, path: Path) -> tuple[str, list[dict], int]:
    """``(format, elements, body offset)``; each element ``{"name", "count", "props": [(name, type, list_type)]}``."""
    end = data.find(b"end_header", 0, MAX_HEADER_BYTES)
    if not data.startswith(b"ply") or end < 0:
        raise MeshFileError(path, "is not a PLY file (expected 'ply' first and 'end_header' within 64 KB)")
    newline = data.find(b"\n", end)
    body = newline + 1 if newline >= 0 else len(data)
    fmt, elements = None, []
    for number, raw in enumerate(data[:end].split(b"\n")[1:], start=2):
        words = raw.decode("ascii", "replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3 and words[1] in PLY_FORMATS:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and re.fullmatch(r"\d{1,12}", words[2]):
            elements.append({"name": words[1], "count": int(words[2]), "props": []})
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in PLY_TYPES:
            elements[-1]["props"].append((words[2], words[1], None))
        elif (words[0] == "property" and elements and len(words) == 5 and words[1] == "list"
              and words[2] in PLY_TYPES and words[3] in PLY_TYPES and not PLY_TYPES[words[2]].startswith("f")):
            elements[-1]["props"].append((words[4], words[3], words[2]))
        else:
            raise MeshFileError(path, f"unreadable PLY header line {raw[:60]!r}", number,
                                "expected format / element NAME COUNT / property TYPE NAME / property list ...")
    if fmt is None:
        raise MeshFileError(path, "the PLY header has no valid 'format' line (ascii, binary_little_endian or "
                            "binary_big_endian)")
    return fmt, elements, body


def _ply_binary_element(data: bytes, offset: int, element: dict, order: str, path: Path):
    """Rows of one binary element as a dict of arrays (list properties: ``[count, k]`` when every row has ``k``
    items, else a list of arrays), and the offset after it."""
    props, count = element["props"], element["count"]
    if not props:
        return {}, offset
    fixed = [(n, order + PLY_TYPES[t]) for n, t, lt in props if lt is None]
    lists = [p for p in props if p[2] is not None]
    row = np.dtype(fixed).itemsize if fixed else 0
    least = row + sum(np.dtype(PLY_TYPES[lt]).itemsize for _, _, lt in lists)
    if count * least > len(data) - offset:
        raise MeshFileError(path, f"element '{element['name']}' declares {count} rows of at least {least} bytes, but "
                            f"only {len(data) - offset} bytes follow", hint="the file is truncated or its header wrong")
    if not lists:
        table = np.frombuffer(data, np.dtype(fixed), count, offset) if count else np.zeros(0, np.dtype(fixed))
        return {n: table[n] for n, _ in fixed}, offset + count * row
    if count and len(lists) == 1 and props[-1][2] is not None:  # the usual face: scalars, then one list
        name, item_type, length_type = lists[0]
        k = int(np.frombuffer(data, order + PLY_TYPES[length_type], 1, offset + row)[0])
        layout = np.dtype(fixed + [("_n", order + PLY_TYPES[length_type]), (name, order + PLY_TYPES[item_type], (k,))])
        if 0 < k <= MAX_POLYGON and count * layout.itemsize <= len(data) - offset:
            table = np.frombuffer(data, layout, count, offset)
            if np.all(table["_n"] == k):
                return {n: table[n] for n in layout.names if n != "_n"}, offset + count * layout.itemsize
    return _ply_binary_rows(data, offset, element, order, path)


def _ply_binary_rows(data: bytes, offset: int, element: dict, order: str, path: Path):
    """Row by row, for elements whose rows differ in length (polygons of several sizes)."""
    out: dict[str, list] = {n: [] for n, _, _ in element["props"]}
    for _ in range(element["count"]):
        for name, item_type, length_type in element["props"]:
            if length_type is None:
                kind = np.dtype(order + PLY_TYPES[item_type])
                if offset + kind.itemsize > len(data):
                    raise MeshFileError(path, f"element '{element['name']}' runs past the end of the file",
                                        hint="the file is truncated; write it again")
                out[name].append(np.frombuffer(data, kind, 1, offset)[0])
                offset += kind.itemsize
                continue
            length = np.dtype(order + PLY_TYPES[length_type])
            item = np.dtype(order + PLY_TYPES[item_type])
            if offset + length.itemsize > len(data):
                raise MeshFileError(path, f"element '{element['name']}' runs past the end of the file",
                                    hint="the file is truncated; write it again")
            k = int(np.frombuffer(data, length, 1, offset)[0])
            offset += length.itemsize
            if not 0 <= k <= MAX_POLYGON:
                raise MeshFileError(path, f"element '{element['name']}' has a list of {k} items, expected 0 to "
                                    f"{MAX_POLYGON}")
            if offset + k * item.itemsize > len(data):
                raise MeshFileError(path, f"element '{element['name']}' runs past the end of the file",
                                    hint="the file is truncated; write it again")
            out[name].append(np.frombuffer(data, item, k, offset))
            offset += k * item.itemsize
    return {n: (np.asarray(v) if v and np.ndim(v[0]) == 0 else v) for n, v in out.items()}, offset


def _ply_ascii_elements(data: bytes, body: int, elements: list[dict], path: Path, header_lines: int):
    lines = [ln for ln in data[body:].split(b"\n") if ln.strip()]
    need = sum(e["count"] for e in elements)
    if need > len(lines):
        raise MeshFileError(path, f"the header declares {need} rows, the file has {len(lines)} lines after it",
                            hint="the file is truncated or its header wrong")
    tables, start = [], 0
    for element in elements:
        rows = lines[start:start + element["count"]]
        table: dict[str, list] = {n: [] for n, _, _ in element["props"]}
        for k, raw in enumerate(rows):
            line_number = header_lines + start + k + 1
            try:
                words = [float(w) for w in raw.split()]
            except ValueError:
                raise MeshFileError(path, f"expected numbers, found {raw[:60].decode('ascii', 'replace')!r}",
                                    line_number) from None
            at = 0
            for name, _, length_type in element["props"]:
                if length_type is None:
                    table[name].append(words[at] if at < len(words) else None)
                    at += 1
                    continue
                n = int(words[at]) if at < len(words) and words[at].is_integer() else -1
                if not 0 <= n <= MAX_POLYGON or at + 1 + n > len(words):
                    raise MeshFileError(path, f"property '{name}': expected a count 0 to {MAX_POLYGON} and that "
                                        f"many values, found {raw[:60].decode('ascii', 'replace')!r}", line_number)
                table[name].append(np.asarray(words[at + 1:at + 1 + n]))
                at += 1 + n
            if at != len(words) or None in (table[n][-1] for n, _, lt in element["props"] if lt is None):
                raise MeshFileError(path, f"element '{element['name']}' expects {len(element['props'])} properties "
                                    f"per line, found {len(words)} numbers", line_number)
        tables.append({n: (np.asarray(v, np.float64) if v and np.ndim(v[0]) == 0 else v) for n, v in table.items()})
        start += element["count"]
    return tables


def _ply_faces(indices: np.ndarray | list, n_vertex: int, path: Path) -> np.ndarray:
    """Fanned triangles of the face element's index lists, every index checked against the vertex count."""
    polygons = [np.asarray(p) for p in ([] if isinstance(indices, np.ndarray) else indices)]
    corners = indices.shape[1] if isinstance(indices, np.ndarray) else min(len(p) for p in polygons)
    if corners < 3:
        raise MeshFileError(path, f"a face has {corners} corners, expected at least 3")
    flat = indices.ravel() if isinstance(indices, np.ndarray) else np.concatenate(polygons)
    if not np.all(np.mod(flat, 1) == 0) or flat.min() < 0 or flat.max() >= n_vertex:
        raise MeshFileError(path, f"face vertex indices must be integers in [0, {n_vertex}), found "
                            f"{flat.min():.0f} to {flat.max():.0f}")
    if isinstance(indices, np.ndarray):
        return fan(indices.astype(np.int64))
    return fan_runs(flat.astype(np.int64), np.asarray([len(p) for p in polygons]))


def read_ply(data: bytes, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    fmt, elements, body = _ply_header(data, path)
    if fmt == "ascii":
        tables = _ply_ascii_elements(data, body, elements, path, data[:body].count(b"\n"))
    else:
        tables, offset = [], body
        for element in elements:
            table, offset = _ply_binary_element(data, offset, element, PLY_FORMATS[fmt], path)
            tables.append(table)
    named = {e["name"]: t for e, t in zip(elements, tables)}
    scalars = {p[0] for e in elements if e["name"] == "vertex" for p in e["props"] if p[2] is None}
    vertex, face = named.get("vertex"), named.get("face")
    if vertex is None or not {"x", "y", "z"} <= scalars or face is None:
        raise MeshFileError(path, "expected a 'vertex' element with scalar x, y, z and a 'face' element")
    positions = np.stack([np.asarray(vertex[a], np.float64) for a in "xyz"], 1)
    index_name = next((n for n in INDEX_NAMES if n in face), None)
    if index_name is None:
        raise MeshFileError(path, f"the 'face' element has no list property {' or '.join(INDEX_NAMES)}")
    if not len(face[index_name]):
        return positions, np.zeros((0, 3), np.int64), np.zeros((0, 3, 2))
    triangles = _ply_faces(face[index_name], len(positions), path)
    pair = next(((a, b) for a, b in UV_NAMES if a in scalars and b in scalars), None)
    corner_uv = np.zeros((0, 3, 2))
    if pair is not None:
        corner_uv = np.stack([np.asarray(vertex[pair[0]], np.float64), np.asarray(vertex[pair[1]], np.float64)],
                             1)[triangles]
    return positions, triangles, corner_uv


# ----------------------------------------------------------------------------------------------- OBJ


def _obj_index(word: bytes, count: int, path: Path, line: int, what: str) -> int:
    """A 1-based (or negative, counted back) OBJ index as a 0-based one, checked against ``count``."""
    try:
        k = int(word)
    except ValueError:
        raise MeshFileError(path, f"expected an integer {what} index, found {word[:20].decode('ascii', 'replace')!r}",
                            line) from None
    index = k - 1 if k > 0 else count + k
    if k == 0 or not 0 <= index < count:
        raise MeshFileError(path, f"{what} index {k} is out of range: {count} {what}s are defined before it", line)
    return index


def _obj_floats(words: list[bytes], least: int, path: Path, line: int, what: str) -> list[float]:
    try:
        values = [float(w) for w in words[:3 if what == "vertex" else 2]]
    except ValueError:
        values = []
    if len(values) < least:
        raise MeshFileError(path, f"expected at least {least} numbers for a {what}, found "
                            f"{b' '.join(words)[:60].decode('ascii', 'replace')!r}", line)
    return values + [0.0] * (2 - len(values)) if what == "texture coordinate" else values


def _obj_tables(data: bytes):
    """``(positions [V, 3], uvs [T, 2], corners [N, 2], sizes [F])`` of an OBJ, parsed by NumPy: each face corner as
    0-based (vertex, uv or -1), faces as runs of ``sizes`` corners.  None when anything is unusual (an unparsable
    number, a negative or out-of-range index, corners of mixed forms): the line-by-line reader then reads the file
    or says where it is wrong."""
    comments = b"#" in data
    v_rows, vt_rows, f_rows, v_seen, vt_seen = [], [], [], [], []
    for line in data.split(b"\n"):
        words = (line.split(b"#", 1)[0] if comments else line).split()
        if not words:
            continue
        if words[0] == b"v":
            v_rows.append(words[1:4])
        elif words[0] == b"vt":
            vt_rows.append(words[1:3] if len(words) > 2 else words[1:2] + [b"0"])
        elif words[0] == b"f":
            f_rows.append(words[1:])
            v_seen.append(len(v_rows))
            vt_seen.append(len(vt_rows))
    sizes = np.fromiter((len(f) for f in f_rows), np.int64, len(f_rows))
    if any(len(r) != 3 for r in v_rows) or any(len(r) != 2 for r in vt_rows) or (
            len(sizes) and (sizes.min() < 3 or sizes.max() > MAX_POLYGON)):
        return None
    corners = np.array([c for f in f_rows for c in f] or [b"1"])[:int(sizes.sum())]
    slashes = np.char.count(corners, b"/") if len(corners) else np.zeros(0, np.int64)
    if len(corners) and (slashes.min() != slashes.max() or slashes.max() > 2):
        return None
    try:
        positions = np.array(v_rows or np.zeros((0, 3)), dtype=np.bytes_).astype(np.float64).reshape(-1, 3)
        uvs = np.array(vt_rows or np.zeros((0, 2)), dtype=np.bytes_).astype(np.float64).reshape(-1, 2)
        parts = int(slashes.max()) + 1 if len(corners) else 1
        text = b" ".join(corners.tolist()).replace(b"//", b"/0/").replace(b"/", b" ")
        numbers = np.array(text.split() or [], dtype=np.bytes_).astype(np.int64).reshape(-1, parts)
    except ValueError:
        return None
    face_of = np.repeat(np.arange(len(sizes)), sizes)
    v = numbers[:, 0]
    t = numbers[:, 1] if parts > 1 else np.zeros(len(numbers), np.int64)
    if (v < 1).any() or (v > np.asarray(v_seen, np.int64)[face_of]).any() or (t < 0).any() or \
            (t > np.asarray(vt_seen, np.int64)[face_of]).any():
        return None
    return positions, uvs, np.stack([v - 1, t - 1], 1), sizes


def read_obj(data: bytes, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    tables = _obj_tables(data)
    if tables is None:
        tables = _obj_tables_line_by_line(data, path)
    position_array, uv_array, pairs, sizes = tables
    if not len(sizes):
        return position_array, np.zeros((0, 3), np.int64), np.zeros((0, 3, 2))
    if (pairs[:, 1] < 0).any():  # UVs only where every corner has one; the vertices stay as the file numbers them
        return position_array, fan_runs(pairs[:, 0], sizes), np.zeros((0, 3, 2))
    keys = pairs[:, 0] * len(uv_array) + pairs[:, 1]          # one vertex per (position, UV) pair
    unique, vertex_of = np.unique(keys, return_inverse=True)
    triangles = fan_runs(vertex_of, sizes)
    return position_array[unique // len(uv_array)], triangles, uv_array[unique % len(uv_array)][triangles]


def _obj_tables_line_by_line(data: bytes, path: Path):
    """:func:`_obj_tables` one line at a time, refusing the first line that is wrong with its number."""
    positions, uvs, corners = [], [], []   # corners: (vertex, uv or -1) per face corner, faces as lists
    for number, raw in enumerate(data.split(b"\n"), start=1):
        words = raw.split(b"#", 1)[0].split()
        if not words:
            continue
        if words[0] == b"v":
            positions.append(_obj_floats(words[1:], 3, path, number, "vertex"))
        elif words[0] == b"vt":
            uvs.append(_obj_floats(words[1:], 1, path, number, "texture coordinate"))
        elif words[0] == b"f":
            if not 3 <= len(words) - 1 <= MAX_POLYGON:
                raise MeshFileError(path, f"a face needs 3 to {MAX_POLYGON} corners, found {len(words) - 1}", number)
            face = []
            for corner in words[1:]:
                parts = corner.split(b"/")
                v = _obj_index(parts[0], len(positions), path, number, "vertex")
                t = _obj_index(parts[1], len(uvs), path, number, "texture coordinate") \
                    if len(parts) > 1 and parts[1] else -1
                face.append((v, t))
            corners.append(face)
    pairs = np.asarray([c for face in corners for c in face], np.int64).reshape(-1, 2)
    return (np.asarray(positions, np.float64).reshape(-1, 3), np.asarray(uvs, np.float64).reshape(-1, 2), pairs,
            np.asarray([len(f) for f in corners], np.int64))
