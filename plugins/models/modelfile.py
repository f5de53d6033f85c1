"""The btforge model file (``.btfm``): any reflectance model, saved losslessly, readable by later versions.

Layout (format version 1).  A ZIP archive (stored, uncompressed) holding

* ``manifest.json``, first, UTF-8 JSON::

      {"format": "btforge.model", "format_version": 1, "written_by": "btforge 0.1.0",
       "representation": "SHModel",                       # the buffer's type_name
       "parameters": {"light_order": 5, "quantized": true, ...},   # every field that is not an array
       "arrays": {"coeffs": {"file": "arrays/coeffs.npy", "dtype": "|u1", "shape": [H, W, C, kv, kl],
                             "blake2b": "..."}, ...},
       "texels": [H, W], "content_key": "..."}

* one ``arrays/<field>.npy`` (NumPy's own ``.npy`` format) per array field, bit for bit as the model holds it.

The split into parameters and arrays is the buffer's own :meth:`~btforge.buffers.Buffer.payload`, so every
representation - PTM, SH, Lafortune and any a plugin adds - is saved without this module knowing its fields:
a quantized SH model is its 8-bit coefficient planes with their per-coefficient ``scale`` and ``bias``.

Compatibility.  A reader accepts every format version it lists in :data:`READERS`; a file of a later version
is refused, naming both versions.  A representation that gained a field since the file was written reads
the file with the field's default; one that lost a field refuses it, naming the field.  Each array's BLAKE2
digest is checked, so a damaged file is refused rather than read wrong.
"""
from __future__ import annotations

import hashlib
import json
import os
import zipfile
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from btforge.atomic import atomic_write
from btforge.buffers import Buffer
from btforge.errors import BtforgeInputError, file_reader
from btforge.spill import pages, read_npy, write_npy

FORMAT = "btforge.model"
FORMAT_VERSION = 1
SUFFIX = ".btfm"
MANIFEST = "manifest.json"


def _digest(array: np.ndarray) -> str:
    h = hashlib.blake2b(digest_size=20)
    for part in pages(np.ascontiguousarray(array)):  # page by page: a spilled model never becomes resident
        h.update(part.reshape(-1).view(np.uint8))
    return h.hexdigest()


def _json_parameters(meta: Mapping[str, Any], representation: str) -> dict[str, Any]:
    try:
        return json.loads(json.dumps(meta, allow_nan=True))
    except TypeError as exc:  # a representation whose payload is not plain JSON: a bug in its plugin
        raise BtforgeInputError(f"models.write ({representation})", f"its parameters are not plain JSON: {exc}",
                                "the representation's payload() must return JSON-serialisable metadata") from None


def write_model(path: str | os.PathLike, model: Buffer) -> dict[str, Any]:
    """Write ``model`` to ``path`` atomically; return the manifest written."""
    from btforge import __version__
    meta, arrays = model.payload()
    manifest = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "written_by": f"btforge {__version__}",
        "representation": model.type_name, "parameters": _json_parameters(meta, model.type_name),
        "arrays": {name: {"file": f"arrays/{name}.npy", "dtype": a.dtype.str, "shape": list(a.shape),
                          "blake2b": _digest(a)} for name, a in sorted(arrays.items())},
        "texels": [int(getattr(model, "height", 0)), int(getattr(model, "width", 0))],
        "content_key": model.content_key,
    }
    with atomic_write(path) as handle:
        with zipfile.ZipFile(handle, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
            archive.writestr(MANIFEST, json.dumps(manifest, indent=1))
            for name, info in manifest["arrays"].items():
                with archive.open(info["file"], "w", force_zip64=True) as member:
                    write_npy(member, np.ascontiguousarray(arrays[name]))
    return manifest


def _open(path: Path) -> zipfile.ZipFile:
    try:
        return zipfile.ZipFile(path)
    except FileNotFoundError:
        raise BtforgeInputError(str(path), "model file not found") from None
    except (zipfile.BadZipFile, OSError) as exc:
        raise BtforgeInputError(str(path), f"is not a btforge model file ({exc})",
                                f"write models with the models.write stage ({SUFFIX} files)") from None


DAMAGED = "the file is damaged or truncated; write the model again"


@file_reader("a btforge model file", DAMAGED)
def read_manifest(path: str | os.PathLike, archive: zipfile.ZipFile | None = None) -> dict[str, Any]:
    """The manifest of a model file, checked for format and version (arrays are not read)."""
    path = Path(path)
    own = archive is None
    archive = archive or _open(path)
    try:
        try:
            manifest = json.loads(archive.read(MANIFEST).decode("utf-8"))
        except KeyError:
            raise BtforgeInputError(str(path), f"has no {MANIFEST}: it is a ZIP file but not a btforge model file",
                                    "write models with the models.write stage") from None
        except (ValueError, UnicodeDecodeError) as exc:
            raise BtforgeInputError(str(path), f"its {MANIFEST} is not valid JSON ({exc})",
                                    "the file is damaged; write the model again") from None
    finally:
        if own:
            archive.close()
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        found = manifest.get("format") if isinstance(manifest, dict) else type(manifest).__name__
        raise BtforgeInputError(str(path), f"expected a manifest of format '{FORMAT}', found {found!r}",
                                "write models with the models.write stage")
    version = manifest.get("format_version")
    if version not in READERS:
        newer = isinstance(version, int) and version > max(READERS)
        raise BtforgeInputError(
            str(path), f"is a btforge model file of format version {version!r} (written by "
            f"{manifest.get('written_by', 'an unknown version')}); this btforge reads format versions "
            f"{', '.join(map(str, sorted(READERS)))}",
            "upgrade btforge to read it" if newer else "the file was not written by btforge's models.write")
    return READERS[version](manifest, path)


def _manifest_v1(manifest: dict[str, Any], path: Path) -> dict[str, Any]:
    for key, kind in (("representation", str), ("parameters", dict), ("arrays", dict)):
        if not isinstance(manifest.get(key), kind):
            raise BtforgeInputError(str(path), f"manifest key '{key}' must be a {kind.__name__}, found "
                                    f"{type(manifest.get(key)).__name__}", "the file is damaged; write it again")
    for name, info in manifest["arrays"].items():
        if not _valid_array_entry(info):
            raise BtforgeInputError(str(path), f"manifest entry of array '{name}' is not a mapping of file, dtype, "
                                    f"shape and blake2b, found {str(info)[:80]}", DAMAGED)
    return manifest


def _valid_array_entry(info: Any) -> bool:
    if not isinstance(info, dict) or not all(isinstance(info.get(k), str) for k in ("file", "dtype", "blake2b")):
        return False
    shape = info.get("shape")
    if not isinstance(shape, list) or not all(isinstance(d, int) and d >= 0 for d in shape):
        return False
    try:
        return not np.dtype(info["dtype"]).hasobject
    except (TypeError, ValueError):
        return False


# format version -> function that checks a manifest of that version and returns it in the current layout
READERS: dict[int, Callable[[dict[str, Any], Path], dict[str, Any]]] = {1: _manifest_v1}


@file_reader("a btforge model file", DAMAGED)
def read_model(path: str | os.PathLike, types: Mapping[str, type[Buffer]]) -> Buffer:
    """Read a model file back into the buffer it was written from (exactly: same arrays, same parameters)."""
    path = Path(path)
    with _open(path) as archive:
        manifest = read_manifest(path, archive)
        representation = manifest["representation"]
        cls = types.get(representation)
        if cls is None:
            raise BtforgeInputError(str(path), f"holds a {representation}, which no installed plugin defines",
                                    "install the plugin that provides it (see `btforge stages`)")
        arrays = {}
        for name, info in manifest["arrays"].items():
            try:
                with archive.open(info["file"]) as member:
                    array = read_npy(member, archive.getinfo(info["file"]).file_size,
                                     f"{path}, array '{name}'")
            except (KeyError, ValueError, OSError, zipfile.BadZipFile) as exc:
                raise BtforgeInputError(str(path), f"array '{name}' cannot be read ({exc})",
                                        "the file is damaged or truncated; write the model again") from None
            if array.dtype.str != info["dtype"] or list(array.shape) != info["shape"] or _digest(array) != info["blake2b"]:
                raise BtforgeInputError(str(path), f"array '{name}' does not match its manifest entry (dtype, shape "
                                        "or checksum)", "the file is damaged; write the model again")
            arrays[name] = array
    known = {f for f in getattr(cls, "__dataclass_fields__", {})}
    unknown = sorted(set(manifest["parameters"]) - known)
    if unknown:
        raise BtforgeInputError(str(path), f"its {representation} has fields this btforge's {representation} does "
                                f"not know: {', '.join(unknown)} (written by {manifest.get('written_by')})",
                                f"upgrade the plugin that defines {representation}")
    try:
        return cls.from_payload(manifest["parameters"], arrays)
    except BtforgeInputError as exc:
        raise BtforgeInputError(str(path), f"holds a {representation} this btforge refuses: {exc.problem}",
                                exc.hint) from None
    except TypeError as exc:
        raise BtforgeInputError(str(path), f"cannot rebuild its {representation}: {exc}",
                                f"the file was written by {manifest.get('written_by')}; use a matching plugin") from None


def describe_model(path: str | os.PathLike) -> dict[str, Any]:
    """What ``btforge info`` shows for a model file: read from its manifest alone."""
    manifest = read_manifest(path)
    size = Path(path).stat().st_size
    return {"kind": "btforge model", "representation": manifest["representation"],
            "format_version": manifest["format_version"], "written_by": manifest.get("written_by"),
            "texels": manifest.get("texels"), "parameters": manifest["parameters"],
            "arrays": {name: f"{tuple(info['shape'])} {np.dtype(info['dtype'])}"
                       for name, info in manifest["arrays"].items()},
            "size_bytes": size}
