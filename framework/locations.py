"""Where btforge keeps what outlives a run: node outputs, compiled kernels, device verdicts, spill files."""
from __future__ import annotations

import os
from pathlib import Path


def default_cache_root() -> Path:
    """``$BTFORGE_CACHE_DIR``, else ``btforge`` in the user's cache folder (``$XDG_CACHE_HOME`` or ``~/.cache``)."""
    root = os.environ.get("BTFORGE_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "btforge"
    )
    return Path(root)
