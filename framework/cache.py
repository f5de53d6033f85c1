"""Content-addressed cache of node outputs on disk.

A node's key is a BLAKE2 hash of its stage name and version, its parameters, the contents of the files it reads
and the content keys of its inputs - so a changed parameter, input or file invalidates exactly the nodes
downstream of it.  An entry is a folder ``<root>/<key[:2]>/<key>/`` holding one ``.npz`` per output port and a
``manifest.json`` written last: an entry without its manifest (a crash mid-write) is simply a miss, and so is
one whose outputs cannot be read back.

Hashing a large capture on every run would cost as much as reading it, so a file's digest is remembered under
``<root>/files/`` keyed by its path, size, inode and both its modification and status-change times: restoring
an old modification time (``cp -p``, ``rsync -t``) still changes the status-change time, which no user command
can set, so an edited file is always hashed again.
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any, Iterable, Mapping

from .atomic import atomic_write, atomic_write_text
from .buffers import Buffer


HASH_BLOCK = 1 << 20


def _hash(text: str) -> str:
    return hashlib.blake2b(text.encode(), digest_size=20).hexdigest()


def file_digest(path: Path, memo: Path | None = None) -> str | None:
    """BLAKE2 digest of a file's contents (of a zarr store folder: of every file in it; of another folder: its
    sorted entry names), None if it does not exist.

    With ``memo`` (a folder), digests are remembered per (path, size, inode, mtime, ctime) and reused.
    """
    try:
        st = path.stat()
    except FileNotFoundError:
        return None
    if path.is_dir():
        if (path / "zarr.json").is_file():  # a chunked store: keyed by its contents, chunk by chunk
            files = sorted(p for p in path.rglob("*") if p.is_file())
            return _hash("\n".join(f"{p.relative_to(path)} {file_digest(p, memo)}" for p in files))
        return _hash("\n".join(sorted(os.listdir(path))))
    memo_file = None
    if memo is not None:
        memo_file = memo / _hash(json.dumps([str(path), st.st_size, st.st_ino, st.st_mtime_ns, st.st_ctime_ns]))
        try:
            return memo_file.read_text()
        except FileNotFoundError:
            pass
    digest = hashlib.blake2b(digest_size=20)
    with open(path, "rb") as handle:
        while block := handle.read(HASH_BLOCK):
            digest.update(block)
    value = digest.hexdigest()
    if memo_file is not None:
        atomic_write_text(memo_file, value)
    return value


def node_key(stage: str, version: str, params: Mapping[str, Any], input_keys: Mapping[str, str],
             files: Iterable[Path], memo: Path | None = None) -> str:
    """The cache key of one node evaluation (``memo``: where file digests are remembered)."""
    paths = sorted({Path(p).resolve() for p in files})
    blob = json.dumps(
        {"stage": stage, "version": version, "params": params, "inputs": dict(sorted(input_keys.items())),
         "files": [[str(p), file_digest(p, memo)] for p in paths]},
        sort_keys=True, default=str,
    )
    return _hash(blob)


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
            files: Iterable[Path]) -> str:
        return node_key(stage, version, params, input_keys, files, self.file_memo)

    def manifest(self, key: str, ports: Iterable[str] | None = None) -> dict[str, Any] | None:
        """The entry's manifest, or None for a miss: no entry, a damaged manifest, other ports than ``ports``, or
        an output file that is missing or not the size that was written."""
        entry = self._entry(key)
        try:
            manifest = json.loads((entry / "manifest.json").read_text())
            outputs = manifest["outputs"]
            if ports is not None and set(outputs) != set(ports):
                return None
            for port, info in outputs.items():
                if (entry / f"{port}.npz").stat().st_size != info["bytes"]:
                    return None
        except (OSError, ValueError, KeyError, TypeError):
            return None
        return manifest

    def load(self, key: str, port: str, types: Mapping[str, type[Buffer]]) -> Buffer:
        return Buffer.from_file(self._entry(key) / f"{port}.npz", types)

    def store(self, key: str, outputs: Mapping[str, Buffer], notes: Mapping[str, Any]) -> None:
        entry = self._entry(key)
        sizes = {}
        for port, buf in outputs.items():
            with atomic_write(entry / f"{port}.npz") as handle:
                buf.write_npz(handle)
            sizes[port] = (entry / f"{port}.npz").stat().st_size
        manifest = {
            "outputs": {port: {"type": buf.type_name, "content_key": buf.content_key, "bytes": sizes[port]}
                        for port, buf in outputs.items()},
            "notes": notes,
        }
        atomic_write_text(entry / "manifest.json", json.dumps(manifest, default=str))
