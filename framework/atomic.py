"""Atomic file output: a crash or Ctrl-C never leaves a half-written file that looks whole.

Everything btforge writes (stage outputs, cache entries, reports) goes to a temporary file in the destination
folder, is flushed and fsynced, and only then renamed over the final name (``os.replace`` is atomic on POSIX).
"""
from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import IO, Iterator


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# Reading the umask means setting it for a moment; done once at import, before any worker threads exist.
_UMASK = _read_umask()


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb", durable: bool = True) -> Iterator[IO]:
    """Open a temporary sibling of ``path`` for writing; it replaces ``path`` only if the block succeeds.

    ``durable=False`` skips the fsync: still atomic for every reader, but after a power cut the file may be
    torn - fine only where a checksum catches that (cache entries).
    """
    with atomic_output_path(path, durable) as tmp:
        with open(tmp, mode) as handle:
            yield handle


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_write(path, "wb") as handle:
        handle.write(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_write(path, "w") as handle:
        handle.write(text)


@contextlib.contextmanager
def atomic_output_path(path: str | os.PathLike, durable: bool = True) -> Iterator[Path]:
    """A temporary path for libraries that insist on writing by file name (OpenEXR); renamed on success.

    The temporary name keeps the final extension so format-sniffing writers pick the right encoder.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.part.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes private files; results get the usual permissions
    try:
        yield Path(tmp)
        if durable:
            with open(tmp, "rb") as handle:
                os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
