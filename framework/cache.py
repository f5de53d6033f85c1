"""Content-addressed cache of node outputs on disk.

A node's key is a BLAKE2 hash of its stage name and version, its parameters, the stat fingerprint of the files
it reads, and the content keys of its inputs - so a changed parameter or input invalidates exactly the nodes
downstream of it.  An entry is a folder ``<root>/<key[:2]>/<key>/`` holding one ``.npz`` per output port and a
``manifest.json`` written last: an entry without its manifest (a crash mid-write) is simply a miss.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

from .atomic import atomic_write_bytes, atomic_write_text
from .buffers import Buffer


def file_fingerprint(paths: Iterable[Path]) -> list[list[Any]]:
    out = []
    for p in sorted({Path(p).resolve() for p in paths}):
        try:
            st = p.stat()
            out.append([str(p), st.st_size, st.st_mtime_ns])
        except FileNotFoundError:
            out.append([str(p), None, None])
    return out


def node_key(stage: str, version: str, params: Mapping[str, Any], input_keys: Mapping[str, str],
             files: Iterable[Path]) -> str:
    blob = json.dumps(
        {"stage": stage, "version": version, "params": params, "inputs": dict(sorted(input_keys.items())),
         "files": file_fingerprint(files)},
        sort_keys=True, default=str,
    )
    return hashlib.blake2b(blob.encode(), digest_size=20).hexdigest()


class NodeCache:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def _entry(self, key: str) -> Path:
        return self.root / key[:2] / key

    def manifest(self, key: str) -> dict[str, Any] | None:
        path = self._entry(key) / "manifest.json"
        try:
            return json.loads(path.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return None

    def load(self, key: str, port: str, types: Mapping[str, type[Buffer]]) -> Buffer:
        return Buffer.from_file(self._entry(key) / f"{port}.npz", types)

    def store(self, key: str, outputs: Mapping[str, Buffer], notes: Mapping[str, Any]) -> None:
        entry = self._entry(key)
        for port, buf in outputs.items():
            atomic_write_bytes(entry / f"{port}.npz", buf.to_bytes())
        manifest = {
            "outputs": {port: {"type": buf.type_name, "content_key": buf.content_key} for port, buf in outputs.items()},
            "notes": notes,
        }
        atomic_write_text(entry / "manifest.json", json.dumps(manifest, default=str))
