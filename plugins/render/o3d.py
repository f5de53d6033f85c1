"""open3d, loaded when a render first needs it, without its plotting module.

``import open3d`` also imports ``open3d.visualization.draw_plotly``, which pulls in dash, plotly and IPython:
about a second of a fresh process that no btforge code uses.  :func:`open3d` puts a stand-in for that one module
in place first; its three functions load the real module if anyone ever calls them.
"""
from __future__ import annotations

import importlib
import sys
import types

_PLOTTING = "open3d.visualization.draw_plotly"
_PLOTTING_FUNCTIONS = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")


def _deferred(name: str):
    def call(*args, **kwargs):
        stand_in = sys.modules.get(_PLOTTING)
        if getattr(stand_in, "_btforge_stand_in", False):
            del sys.modules[_PLOTTING]
        return getattr(importlib.import_module(_PLOTTING), name)(*args, **kwargs)
    call.__name__ = name
    return call


def open3d() -> types.ModuleType:
    """The ``open3d`` module (imported on first call, its plotting module deferred)."""
    module = sys.modules.get("open3d")
    if module is not None:
        return module
    stand_in = types.ModuleType(_PLOTTING, "loaded on first use (see btforge.plugins.render.o3d)")
    stand_in._btforge_stand_in = True
    for name in _PLOTTING_FUNCTIONS:
        setattr(stand_in, name, _deferred(name))
    sys.modules.setdefault(_PLOTTING, stand_in)
    return importlib.import_module("open3d")
