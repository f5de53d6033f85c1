"""Content-addressed cache of node outputs on disk.

A node's key is a BLAKE2 hash of its stage name and version, the digest of the code that computes it (the
source and ``.cl`` files of the stage's plugin, see :func:`code_digest`), its parameters, the contents of the
files it reads and the content keys of its inputs - so a changed parameter, input, file or plugin invalidates
exactly the nodes downstream of it.  An entry is a folder ``<root>/<key[:2]>/<key>/`` holding one ``.npz`` per
output port and a ``manifest.json`` written last, which records each output's size and BLAKE2 checksum: an
entry without its manifest (a crash mid-write) is simply a miss, and so is one whose outputs do not match it.

Hashing a large capture on every run would cost as much as reading it, so a file's digest is remembered under
``<root>/files/`` keyed by its path, size, inode and both its modification and status-change times: restoring
an old modification time (``cp -p``, ``rsync -t``) still changes the status-change time, which no user command
can set, so an edited file is always hashed again.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import re
from pathlib import Path
from types import ModuleType
from typing import Any, Iterable, Mapping

from .atomic import atomic_write, atomic_write_text
from .buffers import Buffer


HASH_BLOCK = 1 << 20


class DamagedEntry(Exception):
    """A cache entry whose manifest is intact but whose output files do not match it."""


def _hash(text: str) -> str:
    return hashlib.blake2b(text.encode(), digest_size=20).hexdigest()


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


def _memo_file(path: Path, st: os.stat_result, memo: Path) -> Path:
    return memo / _hash(json.dumps([str(path), st.st_size, st.st_ino, st.st_mtime_ns, st.st_ctime_ns]))


def remember_digest(path: Path, digest: str, memo: Path) -> None:
    """Remember the digest of a file just written, so the next look at it need not read it."""
    atomic_write_text(_memo_file(path, path.stat(), memo), digest)


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
        memo_file = _memo_file(path, st, memo)
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


CODE_SUFFIXES = (".py", ".cl")


def code_files(module: ModuleType) -> list[Path]:
    """The files whose contents decide what ``module``'s stages compute: every ``.py`` and ``.cl`` file of its
    package (recursively), or of a plain module its file and the ``.cl`` files beside it."""
    origin = getattr(module, "__file__", None)
    if not origin:
        return []
    origin = Path(origin).resolve()
    if hasattr(module, "__path__"):  # a package: all of it
        found = [p for folder in module.__path__ for p in Path(folder).rglob("*")
                 if p.suffix in CODE_SUFFIXES and "__pycache__" not in p.parts]
    else:
        found = [origin] + sorted(origin.parent.glob("*.cl"))
    return sorted({p.resolve() for p in found if p.is_file()})


_IMPORT = re.compile(r"^[ \t]*(?:import[ \t]+([\w., \t]+)"
                     r"|from[ \t]+(\.*)([\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n#;]*))", re.MULTILINE)


def imported_modules(path: Path, package: str) -> set[str]:
    """The modules the Python file ``path`` (of package ``package``) imports anywhere, also inside functions, with
    relative imports resolved.  Read by pattern, not parsed (a parse of every plugin file would cost a fresh
    process a tenth of a second): an import statement quoted in a docstring counts too, which only errs towards
    re-running."""
    found = set()
    for plain, dots, module, names in _IMPORT.findall(path.read_text(encoding="utf-8", errors="replace")):
        if plain:
            found.update(part.split()[0] for part in plain.split(",") if part.strip())
            continue
        if dots:
            parts = package.split(".")
            module = ".".join(parts[:len(parts) - len(dots) + 1] + ([module] if module else []))
        found.add(module)
        # `from pkg import submodule` imports the submodule too
        found.update(f"{module}.{name.split()[0]}" for name in names.strip("()").replace("\n", " ").split(",")
                     if name.strip() and name.split()[0].isidentifier())
    return found


def code_digest(files: Iterable[Path], memo: Path | None = None) -> str:
    """One digest over the contents (and names) of ``files``: changes when any of them is edited."""
    paths = sorted({Path(p).resolve() for p in files})
    return _hash(json.dumps([[p.name, file_digest(p, memo)] for p in paths]))


def node_key(stage: str, version: str, params: Mapping[str, Any], input_keys: Mapping[str, str],
             files: Iterable[Path], memo: Path | None = None, code: str = "") -> str:
    """The cache key of one node evaluation (``memo``: where file digests are remembered; ``code``: the
    :func:`code_digest` of the stage's plugin)."""
    paths = sorted({Path(p).resolve() for p in files})
    blob = json.dumps(
        {"stage": stage, "version": version, "code": code, "params": params,
         "inputs": dict(sorted(input_keys.items())),
         "files": [[str(p), file_digest(p, memo)] for p in paths]},
        sort_keys=True, default=str,
    )
    return _hash(blob)


def node_key_of_output(key: str, port: str) -> str:
    """The key standing for an output that is not stored, from its node's key."""
    return _hash(f"output {port} of {key}")


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
