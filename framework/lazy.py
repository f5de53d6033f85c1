"""Modules imported on first use, so loading a plugin costs nothing for a graph that never calls it.

Every installed plugin is loaded at start-up (its stages must be listed and checked), but scipy's submodules alone
take 0.2-0.6 s to import, which a run that uses none of them should not pay.  ``ndimage = lazy_module(
"scipy.ndimage")`` at the top of a plugin module reads like an import and imports on the first attribute access.
"""
from __future__ import annotations

import importlib
import sys
import types


class _LazyModule(types.ModuleType):
    def __getattr__(self, attribute: str):
        module = importlib.import_module(self.__name__)
        self.__dict__.update(module.__dict__)  # later look-ups no longer come here
        return getattr(module, attribute)


def lazy_module(name: str) -> types.ModuleType:
    """The module ``name``, imported when one of its attributes is first read (at once if already imported)."""
    loaded = sys.modules.get(name)
    return loaded if loaded is not None else _LazyModule(name)
