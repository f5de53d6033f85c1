"""What a running stage sees besides its inputs and parameters."""
from __future__ import annotations

import dataclasses
import os
import sys
import warnings
from pathlib import Path
from typing import Any

from .errors import BtforgeWarning


@dataclasses.dataclass(frozen=True)
class RunPaths:
    """Where relative paths resolve: inputs against the graph's folder, outputs against the run's output folder."""

    graph_dir: Path
    out_dir: Path
    # every output path a stage asked for, in order (the CLI lists those written during the run)
    requested: list[Path] = dataclasses.field(default_factory=list, compare=False, repr=False)

    def input(self, value: str) -> Path:
        p = Path(os.path.expanduser(value))
        return p if p.is_absolute() else self.graph_dir / p

    def output(self, value: str) -> Path:
        p = Path(os.path.expanduser(value))
        p = p if p.is_absolute() else self.out_dir / p
        self.requested.append(p)
        return p


@dataclasses.dataclass
class StageContext:
    """Per-node context: where paths resolve, and a place to leave notes for the run report.

    Attributes
    ----------
    node
        The graph node's name (used in messages).
    paths
        Resolves input paths against the graph's folder and output paths against the run's output folder.
    notes
        Facts the stage reports (condition numbers, counts, compression rates); they land in the run report.
    streamed
        The outputs (of those the stage declares ``streams``) the runner wants as stacks read band by band,
        because every node reading them runs per texel.
    band_arrays, band_index
        Set by the runner while it runs a stage band by band: the memory :meth:`output_array` lends the bands,
        and which band this is.
    """

    node: str
    paths: RunPaths = dataclasses.field(default_factory=lambda: RunPaths(Path.cwd(), Path.cwd()))
    notes: dict[str, Any] = dataclasses.field(default_factory=dict)
    quiet: bool = False
    streamed: frozenset[str] = frozenset()
    band_arrays: dict[Any, Any] | None = dataclasses.field(default=None, repr=False)
    band_index: int = 0

    def output_array(self, name: str, shape: tuple[int, ...], dtype) -> Any:
        """An uninitialised array to compute an output's values into (``name`` tells a stage's arrays apart).
        Run band by band, every other band gets the same memory, faulted in once (a new array of a few MB per band
        cost a page fault per 4 kB as the stage wrote it): the runner writes a band's outputs out while the next
        band runs, before the band after it.  Otherwise a new array."""
        import math

        import numpy as np
        if self.band_arrays is None:
            return np.empty(shape, dtype)
        size, dtype = math.prod(shape), np.dtype(dtype)
        key = (name, self.band_index % 2)
        memory = self.band_arrays.get(key)
        if memory is None or memory.size < size or memory.dtype != dtype:
            memory = self.band_arrays[key] = np.empty(size, dtype)
        memory.flags.writeable = True  # a buffer built on it two bands before froze it; that band was written out
        return memory[:size].reshape(shape)

    def note(self, key: str, value: Any) -> None:
        self.notes[key] = value

    def warn(self, message: str) -> None:
        """A warning that names the node; collected in the report and shown by the CLI."""
        self.notes.setdefault("warnings", []).append(message)
        warnings.warn(f"node '{self.node}': {message}", BtforgeWarning, stacklevel=2)

    def progress(self, message: str) -> None:
        if not self.quiet:
            print(f"    {self.node}: {message}", file=sys.stderr, flush=True)

    @property
    def backend(self):
        from .backend import get_backend
        return get_backend()
