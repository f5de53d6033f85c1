"""btforge: reflectance textures (RTI stacks, BTFs) as a graph of pluggable stages on OpenCL.

Python entry points::

    import btforge
    result = btforge.run("graphs/demo.yaml", only=["fit"])      # {node: {port: Buffer}}, plus .report
    fit = btforge.stage(name)                                    # call an installed stage directly
    model = fit(stack=my_stack, **params)["model"]
"""
from __future__ import annotations

from .buffers import Buffer, PerTexel, ReflectanceModel, SampleStack
from .errors import BtforgeError, BtforgeInputError, BtforgeWarning
from .hookspecs import hookimpl
from .runner import RunResult, run
from .stages import AUTO, REQUIRED, Expect, Fact, Param, Stage, declare_stage

__version__ = "0.1.0"


def stage(name: str) -> Stage:
    """The installed stage called ``name``, callable as ``stage(**inputs, **params) -> {port: Buffer}``."""
    from .registry import default_registry
    return default_registry().stage(name)


__all__ = [
    "Buffer", "PerTexel", "ReflectanceModel", "SampleStack", "BtforgeError", "BtforgeInputError",
    "BtforgeWarning", "hookimpl", "run", "RunResult", "Param", "REQUIRED", "Stage", "declare_stage", "stage",
    "Expect", "Fact", "AUTO",
]
