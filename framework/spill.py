"""Arrays larger than a process should hold: kept in a file, their pages handed back as soon as they are used.

A fit of a store-backed stack writes its result band by band; held in memory, the result alone can pass the
memory a user has (double SH 25 x 25 of a 256^2 BTF is 491 MB of coefficients).  :func:`spilled_empty` makes the
result a memory map of an unlinked file (removed by the OS when the last reference goes), and :func:`release`
drops a written or read part from the process's resident memory: the data stays in the file, and is read back on
the next access.  :func:`pages` walks any array in parts of a few MB and releases each part of a spilled array
after use, so checking, hashing and writing one never makes it resident.  For an ordinary array both are plain
iteration and no-ops.

The file is a memory file (``memfd``) while this process's spills together stay under a quarter of the memory
the system (or the process's cgroup) has available, else a file under the cache root.  Either way the data lives
outside the process (in the OS's shared memory or its file cache); a memory file skips the file system, which
spends several times the system time on taking in the pages (ext4 on this machine: 0.14-0.43 s of system time
for a 154 MB capture against 0.06 s), while a large spill goes to the disk file, whose pages the OS can write
out when memory runs short.
"""
from __future__ import annotations

import math
import mmap
import os
import tempfile
import threading
import weakref
from typing import Any, Iterator, Sequence

import numpy as np

PAGE_BYTES = 32 << 20
READ_BYTES = 4 << 20  # parts read from a spill file: small, since each is a copy


MEMORY_FILE_SHARE = 0.25  # spills held in memory files stay under this share of the available memory


def spilled_empty(shape: Sequence[int], dtype) -> np.ndarray:
    """An uninitialised array of ``shape`` backed by an unlinked file (see the module docs)."""
    shape, dtype = tuple(int(s) for s in shape), np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    if nbytes == 0:
        return np.empty(shape, dtype)
    handle, in_memory = _spill_file(nbytes)
    handle.truncate(nbytes)
    array = np.memmap(handle, dtype, "r+", 0, shape)
    key = id(array.base)
    _files[key] = handle  # for plain reads and writes of its parts (_file_part), as long as the array lives
    _memory_file_bytes[0] += nbytes if in_memory else 0
    weakref.finalize(array, _forget, key, nbytes if in_memory else 0)
    return array


def _spill_file(nbytes: int):
    """``(file, in memory)``: a memory file when this process's memory files stay under their share of the
    available memory, else an unlinked file under the cache root."""
    if hasattr(os, "memfd_create") and \
            _memory_file_bytes[0] + nbytes <= MEMORY_FILE_SHARE * _available_memory_bytes():
        try:
            return os.fdopen(os.memfd_create("btforge-spill", os.MFD_CLOEXEC), "w+b"), True
        except OSError:  # no memory files here (an old kernel, a sandbox): the disk file below
            pass
    from .locations import default_cache_root
    root = default_cache_root()
    root.mkdir(parents=True, exist_ok=True)
    return tempfile.TemporaryFile(prefix="spill-", dir=root), False


_CGROUP_FILES = (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),  # cgroup v2
                 ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "/sys/fs/cgroup/memory/memory.usage_in_bytes"))


def _available_memory_bytes() -> int:
    """Memory the system has available (``MemAvailable``), less where the process's cgroup (as a container sees
    it) allows less; 0 when it cannot be told, which keeps every spill on the disk."""
    try:
        with open("/proc/meminfo") as meminfo:
            available = next(int(line.split()[1]) * 1024 for line in meminfo if line.startswith("MemAvailable:"))
    except (OSError, StopIteration, ValueError, IndexError):
        return 0
    for limit_file, usage_file in _CGROUP_FILES:
        try:
            with open(limit_file) as limit, open(usage_file) as usage:
                allowed = limit.read().strip()
                if allowed != "max":
                    available = min(available, int(allowed) - int(usage.read()))
        except (OSError, ValueError):
            continue  # no such cgroup file: the system's figure holds
    return max(0, available)


def _forget(key: int, memory_bytes: int) -> None:
    handle = _files.pop(key, None)
    _memory_file_bytes[0] -= memory_bytes
    if handle is not None:  # the array is gone: its file's pages are freed in a thread, off the caller's path
        try:
            threading.Thread(target=_discard, args=(os.dup(handle.fileno()),), name="btforge-spill-free",
                             daemon=True).start()
        except (OSError, RuntimeError):  # no descriptor or thread to spare: the pages go when the file closes
            pass


def _discard(descriptor: int) -> None:
    """Free a dead spill's data (freeing a 154 MB memory file takes 0.05-0.1 s of system time)."""
    try:
        os.ftruncate(descriptor, 0)
    except OSError:
        pass
    finally:
        os.close(descriptor)


_memory_file_bytes = [0]  # bytes of this process's live spills held in memory files
_files: dict[int, Any] = {}  # id of a spilled array's mapping -> its file


def _file_part(array: np.ndarray):
    """``(file, offset)`` of a C-contiguous part of a spilled array (its file and where its first byte lies), or
    None.  Moving such a part with plain reads and writes never maps its pages into the process: touching the
    mapping would make resident not only the part but whatever the kernel maps around each fault (on this
    machine half of a capture for a band of 27 rows of it)."""
    found = _shared_map(array) if isinstance(array, np.ndarray) and array.flags.c_contiguous else None
    handle = _files.get(id(found[0])) if found else None
    return (handle, array.ctypes.data - found[1]) if handle is not None else None


def write_items(array: np.ndarray, first: int, data: np.ndarray) -> None:
    """Write ``data`` into C-contiguous ``array`` as its items ``first, first + 1, ...`` in C order, an item being
    one ``data[0]`` (e.g. images ``[n, H, W, C]`` into a stack ``[V, L, H, W, C]``, counting views x lights); a
    spilled array's file is written with plain writes (see :func:`_file_part`)."""
    item = data[0].size if len(data) else 1
    found = _file_part(array)
    if found is None:
        flat = array.reshape(-1)  # a view: the array is C-contiguous
        flat[first * item:(first + len(data)) * item] = data.reshape(-1)
        return
    handle, offset = found
    view = memoryview(np.ascontiguousarray(data, array.dtype)).cast("B")
    offset += first * item * array.itemsize
    while view.nbytes:
        written = os.pwrite(handle.fileno(), view, offset)
        view, offset = view[written:], offset + written


def _read_into(handle, offset: int, out: np.ndarray) -> np.ndarray:
    if os.preadv(handle.fileno(), [out.reshape(-1).view(np.uint8)], offset) != out.nbytes:
        raise OSError(f"short read from a spill file at byte {offset}")
    return out


def read_block(array: np.ndarray, axis: int, part: slice, out: np.ndarray | None = None) -> np.ndarray:
    """``array[..., part, ...]`` (``part`` a step-1 slice along ``axis``) as a new in-memory array, or into ``out``
    (a C-contiguous buffer of at least that many items and the array's dtype, returned reshaped: a buffer used
    for every block of a walk is faulted into memory once, not once per block); a spilled array's block is read
    from its file with plain reads, one per contiguous run (see :func:`_file_part`)."""
    start, stop, _ = part.indices(array.shape[axis])
    shape = array.shape[:axis] + (max(0, stop - start),) + array.shape[axis + 1:]
    if out is not None:
        if out.dtype != array.dtype or not out.flags.c_contiguous or out.size < math.prod(shape):
            raise ValueError(f"read_block: a buffer of {out.size} {out.dtype} cannot take a block {shape} of "
                             f"{array.dtype}")
        out = out.reshape(-1)[:math.prod(shape)].reshape(shape)
    found = _file_part(array)
    if found is None:
        block = array[(slice(None),) * axis + (slice(start, stop),)]
        if out is None:
            return np.ascontiguousarray(block)
        np.copyto(out, block)
        return out
    handle, offset = found
    outer = int(np.prod(array.shape[:axis]))
    inner = int(np.prod(array.shape[axis + 1:])) * array.itemsize
    out = np.empty(shape, array.dtype) if out is None else out
    runs = out.reshape(outer, -1)
    for index in range(outer):
        _read_into(handle, offset + (index * array.shape[axis] + start) * inner, runs[index])
    return out


def _shared_map(array: np.ndarray) -> tuple[mmap.mmap, int] | None:
    """The shared file mapping a view looks into and the address where the mapping starts, if it is one."""
    root = array
    while isinstance(root.base, np.ndarray):
        root = root.base
    if not (isinstance(root, np.memmap) and isinstance(root.base, mmap.mmap) and root.mode in ("r+", "w+", "r")):
        return None  # private (copy-on-write) maps would lose what was written: never released
    return root.base, root.ctypes.data - (root.offset - root.offset // mmap.ALLOCATIONGRANULARITY
                                          * mmap.ALLOCATIONGRANULARITY)


try:
    from numpy.lib.array_utils import byte_bounds as _byte_bounds
except ImportError:  # NumPy < 2
    _byte_bounds = np.byte_bounds


def release(array: np.ndarray) -> None:
    """Drop the pages of ``array`` (a part of a spilled array) from resident memory; no-op for other arrays."""
    found = _shared_map(array) if isinstance(array, np.ndarray) and array.size else None
    if found is None:
        return
    mapping, start = found
    low, high = _byte_bounds(array)
    first = (low - start) // mmap.PAGESIZE * mmap.PAGESIZE
    last = min(len(mapping), -(-(high - start) // mmap.PAGESIZE) * mmap.PAGESIZE)
    if last > first:
        mapping.madvise(mmap.MADV_DONTNEED, first, last - first)


def is_spilled(array: np.ndarray) -> bool:
    return isinstance(array, np.ndarray) and _shared_map(array) is not None


def pages(array: np.ndarray, page_bytes: int = PAGE_BYTES) -> Iterator[np.ndarray]:
    """``array`` in consecutive parts of at most about ``page_bytes`` (flat for a C-contiguous array, else along
    axis 0), to read: a part of a spilled array is read from its file (C-contiguous; each part is then valid
    until the caller asks for the next) or released when the caller asks for the next."""
    if array.ndim == 0 or array.size == 0:
        yield array
        return
    parts = array.reshape(-1) if array.flags.c_contiguous else array
    found = _file_part(parts)
    if found is not None:  # read from the file into one small buffer: the pages are never mapped
        page_bytes = min(page_bytes, READ_BYTES)
    step = max(1, page_bytes // max(1, parts[:1].nbytes))
    buffer = np.empty(parts[:step].shape, parts.dtype) if found is not None else None
    for start in range(0, parts.shape[0], step):
        part = parts[start:start + step]
        if found is not None:
            yield _read_into(found[0], found[1] + start * parts.itemsize, buffer[:len(part)])
            continue
        yield part
        release(part)


def finite_range(array: np.ndarray) -> bool:
    """Whether every value of a float array is finite, read page by page (min and max see every NaN and Inf)."""
    return all(np.isfinite(part.min()) and np.isfinite(part.max()) for part in pages(array))


def write_npy(handle, array: np.ndarray) -> None:
    """``array`` as a ``.npy`` file (NumPy's format, what ``np.save`` writes) to a binary file object, page by page."""
    header = np.lib.format.header_data_from_array_1_0(array)
    try:
        np.lib.format.write_array_header_1_0(handle, header)
    except ValueError:  # a header too long for format 1.0 (huge structured dtypes)
        np.lib.format.write_array_header_2_0(handle, header)
    if not array.flags.c_contiguous and array.flags.f_contiguous:
        array = array.T  # header says fortran_order: the bytes are the transpose's, in C order
    if array.dtype.hasobject:
        raise ValueError("write_npy writes numeric arrays only (no pickled objects)")
    for part in pages(np.ascontiguousarray(array)) if array.size else ():
        handle.write(memoryview(np.ascontiguousarray(part).reshape(-1).view(np.uint8)))


def read_npy(handle, size: int, what: str) -> np.ndarray:
    """The array of a ``.npy`` stream of ``size`` bytes (a file object at its start), its header checked before
    anything is allocated: numeric dtype, non-negative shape, and a data size equal to what the stream holds.
    A damaged stream is a :class:`~btforge.errors.BtforgeInputError` naming ``what``."""
    from tokenize import TokenError

    from .errors import BtforgeInputError
    damaged = "the file is damaged or truncated; write it again"
    try:
        version = np.lib.format.read_magic(handle)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in read_header:
            raise ValueError(f"unsupported .npy version {version}")
        shape, fortran_order, dtype = read_header[version](handle)
    except (ValueError, SyntaxError, TokenError, TypeError, EOFError) as exc:
        raise BtforgeInputError(what, f"is not a readable .npy array ({exc})", damaged) from None
    if dtype.hasobject or any(not isinstance(d, int) or d < 0 for d in shape):
        raise BtforgeInputError(what, f"expected a numeric array, found dtype {dtype} and shape {shape}", damaged)
    count = math.prod(shape)
    header_bytes = handle.tell()
    if count * dtype.itemsize != size - header_bytes:
        raise BtforgeInputError(what, f"its header says {shape} {dtype} ({count * dtype.itemsize} bytes), the data "
                                f"holds {size - header_bytes} bytes", damaged)
    out = np.empty(count, dtype)
    view, filled = memoryview(out.view(np.uint8).reshape(-1)), 0
    while filled < len(view):
        got = handle.readinto(view[filled:])
        if not got:
            raise BtforgeInputError(what, f"ends after {filled} of {len(view)} data bytes", damaged)
        filled += got
    return out.reshape(shape[::-1]).T if fortran_order else out.reshape(shape)
