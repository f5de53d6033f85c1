"""Content-addressed cache of node outputs on disk.

A node's key (made in :mod:`btforge.cachekey`) is a BLAKE2 hash of its stage name and version, the digest of
the code that computes it, its parameters, the contents of the files it reads and the content keys of its
inputs - so a changed parameter, input, file or plugin invalidates exactly the nodes downstream of it.  An entry is a folder ``<root>/<key[:2]>/<key>/`` holding one ``.npz`` per
output port and a ``manifest.json`` written last, which records each output's size and BLAKE2 checksum: an
entry without its manifest (a crash mid-write) is simply a miss, and so is one whose outputs do not match it.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

from .atomic import atomic_write, atomic_write_text
from .buffers import Buffer
from .cachekey import (  # noqa: F401  (the key's parts, importable from here as before)
    code_digest, code_files, file_digest, imported_modules, node_key, node_key_of_output, remember_digest)




class DamagedEntry(Exception):
    """A cache entry whose manifest is intact but whose output files do not match it."""


class _HashingWriter(io.RawIOBase):
    """A write-only, non-seekable stream that hashes what passes through (zip writers then stream too)."""

    def __init__(self, handle):
        self.handle, self.size, self.digest = handle, 0, hashlib.blake2b(digest_size=20)

    def writable(self) -> bool:
        return True

    def write(self, data) -> int:
        self.digest.update(data)
        self.size += len(data)
        self.handle.write(data)
        return len(data)


def plain_notes(notes: Mapping[str, Any]) -> dict[str, Any]:
    """``notes`` as the cache stores them (JSON numbers, strings, lists and mappings with text keys), so a node
    served from the cache reports exactly the notes it reported when it ran."""
    return {str(k): _plain(v) for k, v in notes.items()}


def _plain(value: Any) -> Any:
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, Mapping):
        return plain_notes(value)
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist"):  # NumPy scalars and arrays: their Python numbers, not their text
        return _plain(value.tolist())
    return str(value)


class NodeCache:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def _entry(self, key: str) -> Path:
        return self.root / key[:2] / key

    @property
    def file_memo(self) -> Path:
        """Where digests of input files are remembered."""
        return self.root / "files"

    def key(self, stage: str, version: str, params: Mapping[str, Any], input_keys: Mapping[str, str],
            files: Iterable[Path], code: str = "") -> str:
        return node_key(stage, version, params, input_keys, files, self.file_memo, code)

    def manifest(self, key: str, ports: Iterable[str] | None = None) -> dict[str, Any] | None:
        """The entry's manifest, or None for a miss: no entry, a damaged manifest, other ports than ``ports``.

        Raises :class:`DamagedEntry` when an output file is missing or does not match the size and checksum
        the manifest recorded (the caller recomputes, and says so).
        """
        entry = self._entry(key)
        try:
            manifest = json.loads((entry / "manifest.json").read_text())
            outputs = manifest["outputs"]
            if ports is not None and set(outputs) != set(ports):
                return None
            for port, info in outputs.items():
                self._verify(entry / f"{port}.npz", info)
        except (OSError, ValueError, KeyError, TypeError):
            return None
        return manifest

    def _verify(self, path: Path, info: Mapping[str, Any]) -> None:
        try:
            size = path.stat().st_size
        except FileNotFoundError:
            raise DamagedEntry(f"{path.name} is missing") from None
        if size != info["bytes"]:
            raise DamagedEntry(f"{path.name} has {size} bytes, the manifest says {info['bytes']}")
        # Digests are remembered by (size, inode, mtime, ctime), so an untouched entry is not re-read on a hit.
        if file_digest(path, self.file_memo) != info["blake2b"]:
            raise DamagedEntry(f"{path.name} does not match its checksum")

    def load(self, key: str, port: str, types: Mapping[str, type[Buffer]]) -> Buffer:
        return Buffer.from_file(self._entry(key) / f"{port}.npz", types)

    def store(self, key: str, outputs: Mapping[str, Buffer], notes: Mapping[str, Any]) -> None:
        entry = self._entry(key)
        written = {}
        for port, buf in outputs.items():
            path = entry / f"{port}.npz"
            # Streamed, hashed on the way, not fsynced: the checksum catches a file torn by a power cut.
            with atomic_write(path, durable=False) as handle:
                stream = _HashingWriter(handle)
                buf.write_npz(stream)
            written[port] = {"bytes": stream.size, "blake2b": stream.digest.hexdigest()}
            remember_digest(path, written[port]["blake2b"], self.file_memo)
        manifest = {
            "outputs": {port: {"type": buf.type_name, "content_key": buf.content_key, **written[port]}
                        for port, buf in outputs.items()},
            "notes": plain_notes(notes),
        }
        atomic_write_text(entry / "manifest.json", json.dumps(manifest))
