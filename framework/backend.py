"""The one owner of the OpenCL context, queue and compiled programs.

Kernels live as ``.cl`` files beside the plugin that uses them.  :func:`program` compiles a file once per
context (memoised on the file's content and build options), so a graph that calls the same stage a hundred
times builds its kernels once.  Each built binary is also kept on disk (``<cache root>/opencl``, keyed by
platform, device, driver and pyopencl versions, source and options), so a later process loads it instead of
building (2-10 ms instead of tens of milliseconds with PoCL's own cache warm, or seconds with it cold).  PoCL's
cache in ``POCL_CACHE_DIR`` points at a per-user directory unless the user already set it.

The device is the first that builds a tiny probe kernel among those ``BTFORGE_DEVICE`` or the CLI's ``--device``
selects (part of the platform name or version, device name or driver version, e.g. ``3.1`` or ``cuda``), in
btforge's order: CPU devices of PoCL first, newest LLVM first (see :mod:`btforge.devices`; ``btforge devices``
shows every device, whether it builds and which is chosen).
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # pyopencl is imported on first use; its names only annotate here
    import pyopencl as cl

from . import profile
from .atomic import atomic_write_bytes
from .devices import choose_device, hint_and_source, list_devices, matching_devices
from .locations import default_cache_root
from .numerics import texel_chunks  # noqa: F401  (its former home; plugins import it from btforge.numerics)

_lock = threading.RLock()
_backend: "Backend | None" = None
_device_hint: str | None = None  # the CLI's --device; None: BTFORGE_DEVICE or btforge's order decides


def single_threaded_blas():
    """A context in which NumPy's BLAS uses one thread, for host products between OpenCL kernel launches.

    PoCL runs kernels on every core, and an OpenBLAS that has run on several threads keeps them spinning for a
    while after each product, against PoCL's: the double SH fit of a 128^2 x 81 x 81 store took 12.7 s of CPU
    with 2 BLAS threads and 4.8 s with 1 (2-core machine).  Under load a threaded BLAS also waits for busy
    cores: a k-coherence analysis of a 192 x 192 exemplar took 29 s wall and 11 s CPU at load 6 with threads,
    6.5 s and 4.9 s without (a QR of 800 x 32: 120 ms against 0.7 ms).

    The BLAS libraries are looked up once (a scan of every library the process has loaded costs 5-20 ms, more
    than the products it is for) and again only after an extension module was imported, as a new BLAS (SciPy's)
    comes with one.
    """
    from threadpoolctl import ThreadpoolController
    extensions = _extension_modules()
    with _BLAS_LOCK:
        if _BLAS_CONTROLLER.get("extensions") != extensions:
            _BLAS_CONTROLLER.update(extensions=extensions, controller=ThreadpoolController())
        controller = _BLAS_CONTROLLER["controller"]
    return controller.limit(limits=1, user_api="blas")


_BLAS_CONTROLLER: dict = {}  # the libraries single_threaded_blas limits, and the extension modules loaded then
_BLAS_LOCK = threading.Lock()


def _extension_modules() -> int:
    """How many imported modules are compiled extensions (a native library comes into the process with one)."""
    return sum(1 for module in list(sys.modules.values())
               if str(getattr(module, "__file__", None) or "").endswith((".so", ".pyd")))


def _prepare_pocl_environment() -> None:
    os.environ.setdefault("POCL_CACHE_DIR", str(default_cache_root() / "pocl"))
    # The pip PoCL wheel registers itself through an ICD file pyopencl finds; nothing else to do here.


class Backend:
    """An OpenCL context with its queue and a memo of built programs."""

    def __init__(self, device_hint: str | None = None):
        start = time.perf_counter()
        _prepare_pocl_environment()
        import pyopencl as cl

        self.cl = cl
        self.choice = choose_device(cl, device_hint)
        self.device = self.choice.entry.device
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.context)
        self._programs: dict[tuple[str, str], "cl.Program"] = {}
        self._kernels: dict[tuple[str, str, str], "cl.Kernel"] = {}
        self.builds = 0  # how many programs this context built, from source or binary (tests check memoisation)
        self.binaries = default_cache_root() / "opencl"
        self._build_identity = self.choice.entry.identity
        profile.record_phase("device_start_s", time.perf_counter() - start)

    @property
    def description(self) -> str:
        entry = self.choice.entry
        return f"{entry.platform} / {entry.name}" + (f" (PoCL {entry.pocl})" if entry.pocl else "")

    def program(self, cl_file: str | os.PathLike, options: tuple[str, ...] = ()) -> "cl.Program":
        """The compiled program of ``cl_file``; built on first use in this context, then reused."""
        source = Path(cl_file).read_text()
        key = (hashlib.sha256(source.encode()).hexdigest(), " ".join(options))
        with _lock:
            prog = self._programs.get(key)
            if prog is None:
                start = time.perf_counter()
                prog, how = self._build(source, list(options))
                profile.record_build(Path(cl_file).name, " ".join(options), time.perf_counter() - start, how)
                self._programs[key] = prog
                self.builds += 1
            return prog

    def _build(self, source: str, options: list[str]) -> tuple["cl.Program", str]:
        """Build from the on-disk binary of an earlier process if there is one, else from source (and keep its
        binary).  Keyed like pyopencl's cache: platform, device, driver, pyopencl version, source and options;
        PoCL's own source cache still re-parses the source and costs tens of milliseconds per program."""
        digest = hashlib.blake2b(json.dumps([self._build_identity, source, options]).encode(), digest_size=20)
        path = self.binaries / f"{digest.hexdigest()}.bin"
        try:
            binary = path.read_bytes()
        except OSError:
            binary = None
        if binary:
            try:
                return self.cl.Program(self.context, [self.device], [binary]).build(options=options), "binary cache"
            except self.cl.Error:  # a binary the driver no longer accepts: build from source and replace it
                pass
        prog = self.cl.Program(self.context, source).build(options=options)
        try:
            (built,) = prog.get_info(self.cl.program_info.BINARIES)
            if built:
                atomic_write_bytes(path, bytes(built))
        except (OSError, ValueError, self.cl.Error):  # a read-only cache or a driver without binaries: still fine
            pass
        return prog, "source"

    def kernel(self, cl_file: str | os.PathLike, name: str, options: tuple[str, ...] = ()) -> "cl.Kernel":
        """The kernel ``name`` of ``cl_file``, built and retrieved once per context (kernel objects are reused)."""
        with _lock:
            key = (str(Path(cl_file).resolve()), name, " ".join(options))
            kern = self._kernels.get(key)
            if kern is None:
                kern = self.cl.Kernel(self.program(cl_file, options), name)
                self._kernels[key] = kern
            return kern

    def run(self, kernel: "cl.Kernel", global_size: tuple[int, ...], *args,
            local_size: tuple[int, ...] | None = None) -> None:
        """Set the arguments of ``kernel`` and enqueue it over ``global_size``; the work-group size is left to the
        device unless ``local_size`` is given (PoCL's CPU device keeps every work-item's private arrays of a
        work-group on one thread's stack, so a kernel with large private arrays needs small work-groups)."""
        kernel.set_args(*args)
        self.cl.enqueue_nd_range_kernel(self.queue, kernel, global_size, local_size)

    def host_input(self, array: np.ndarray):
        """A read-only device view of a C-contiguous host array, without a copy where the device shares host memory.

        On a CPU device (PoCL) this saves a full copy of large inputs such as a whole capture.
        """
        mf = self.cl.mem_flags
        return self.cl.Buffer(self.context, mf.READ_ONLY | mf.USE_HOST_PTR, hostbuf=np.ascontiguousarray(array))

    def host_output(self, array: np.ndarray):
        """A device buffer that writes straight into ``array``; call :meth:`finish_output` before reading it."""
        mf = self.cl.mem_flags
        return self.cl.Buffer(self.context, mf.WRITE_ONLY | mf.USE_HOST_PTR, hostbuf=array)

    def finish_output(self, buffer, array: np.ndarray) -> None:
        """Make the device's writes to a :meth:`host_output` buffer visible in ``array``."""
        mapped, _ = self.cl.enqueue_map_buffer(self.queue, buffer, self.cl.map_flags.READ, 0, array.shape, array.dtype)
        if mapped.__array_interface__["data"][0] != array.__array_interface__["data"][0]:
            array[...] = mapped  # the device kept its own copy; bring the results over
        mapped.base.release()
        self.queue.finish()

    def to_device(self, array: np.ndarray):
        mf = self.cl.mem_flags
        return self.cl.Buffer(self.context, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=np.ascontiguousarray(array))

    def empty(self, nbytes: int):
        return self.cl.Buffer(self.context, self.cl.mem_flags.WRITE_ONLY, size=max(int(nbytes), 1))

    def from_device(self, buffer, shape, dtype) -> np.ndarray:
        out = np.empty(shape, dtype=dtype)
        self.cl.enqueue_copy(self.queue, out, buffer)
        return out


def get_backend() -> Backend:
    """The process-wide backend, created on first use (so a device skipped on the way is warned about inside the
    node that first needs the device, and shows in its report)."""
    global _backend
    with _lock:
        if _backend is None:
            _backend = Backend(_device_hint)
        return _backend


def select_device(hint: str | None) -> None:
    """Use the device ``hint`` selects from now on (the backend is created on first use).  A hint that matches no
    device is an error at once; whether a matching device builds is found out when the backend starts."""
    global _backend, _device_hint
    import pyopencl as cl
    with _lock:
        _prepare_pocl_environment()
        hint, source = hint_and_source(hint)
        matching_devices(list_devices(cl), hint, source)
        _device_hint, _backend = hint, None
