"""Launching the synthesizers' kernels over fixed-shape work-groups."""
from __future__ import annotations

LOCAL = 8  # fixed work-group size: PoCL builds a work-group function per local size, so never let it vary


def round_up(n: int, to: int = LOCAL) -> int:
    """``n`` rounded up to a whole number of work-groups (at least one)."""
    return max(to, -(-int(n) // to) * to)


def launch(backend, kernel, size: tuple[int, ...], *args) -> None:
    """Enqueue over ``size`` rounded up to whole work-groups of a fixed shape (the kernels check their bounds)."""
    kernel.set_args(*args)
    local = (1,) * (len(size) - 1) + (LOCAL,)
    glob = tuple(max(1, s) for s in size[:-1]) + (round_up(size[-1]),)
    backend.cl.enqueue_nd_range_kernel(backend.queue, kernel, glob, local)
