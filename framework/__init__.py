"""btforge: reflectance textures (RTI stacks, BTFs) as a graph of pluggable stages on OpenCL.

Python entry points::

    import btforge
    result = btforge.run("graphs/demo.yaml", only=["fit"])      # {node: {port: Buffer}}, plus .report
    fit = btforge.stage(name)                                    # call an installed stage directly
    model = fit(stack=my_stack, **params)["model"]
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# The public names and the modules that define them.  They are imported when first used, so `import btforge.cli`
# loads neither NumPy nor the engine: the command line sets its process up before they load (btforge.cli).
_PUBLIC = {
    "buffers": ("Buffer", "PerTexel", "ReflectanceModel", "SampleStack"),
    "errors": ("BtforgeError", "BtforgeInputError", "BtforgeWarning"),
    "hookspecs": ("hookimpl",),
    "runner": ("RunResult", "run"),
    "stages": ("AUTO", "REQUIRED", "Expect", "Fact", "Param", "Stage", "declare_stage"),
}
_HOME = {name: module for module, names in _PUBLIC.items() for name in names}

if TYPE_CHECKING:  # what static tools see; at run time __getattr__ imports these
    from .buffers import Buffer, PerTexel, ReflectanceModel, SampleStack
    from .errors import BtforgeError, BtforgeInputError, BtforgeWarning
    from .hookspecs import hookimpl
    from .runner import RunResult, run
    from .stages import AUTO, REQUIRED, Expect, Fact, Param, Stage, declare_stage


def __getattr__(name: str):
    """A public name, or a submodule (``btforge.streaming``), imported on first use."""
    if name in _HOME:
        value = getattr(importlib.import_module(f".{_HOME[name]}", __name__), name)
    elif not name.startswith("__"):
        try:
            value = importlib.import_module(f".{name}", __name__)
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":  # the submodule exists but an import inside it failed
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value  # later look-ups no longer come here
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_HOME})


def stage(name: str) -> "Stage":
    """The installed stage called ``name``, callable as ``stage(**inputs, **params) -> {port: Buffer}``."""
    from .registry import default_registry
    return default_registry().stage(name)


__all__ = [
    "Buffer", "PerTexel", "ReflectanceModel", "SampleStack", "BtforgeError", "BtforgeInputError",
    "BtforgeWarning", "hookimpl", "run", "RunResult", "Param", "REQUIRED", "Stage", "declare_stage", "stage",
    "Expect", "Fact", "AUTO",
]
