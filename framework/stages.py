"""Declaring stages: typed ports, typed parameters with defaults and docs.

A stage is a plain function ``fn(ctx, **inputs, **params) -> dict[port, Buffer]`` wrapped by :func:`declare_stage`, which
records its ports and parameters so a graph can be checked before anything runs.  The function's NumPy-style
docstring is the documentation ``btforge stages`` prints.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import os
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

from .context import RunPaths, StageContext
from .errors import BtforgeInputError

# Parameter kinds and what they accept.  'path' is an existing input file (checked before a run, resolved
# against the graph file's folder); 'outpath' is where a stage writes (resolved against the run's --out).
PARAM_KINDS = ("str", "int", "float", "bool", "choice", "path", "outpath", "lights", "ints", "any")


@dataclasses.dataclass(frozen=True)
class Param:
    """A stage parameter.

    Parameters
    ----------
    name, kind, default, doc
        ``kind`` is one of ``PARAM_KINDS``; ``default`` of ``REQUIRED`` makes the parameter mandatory.
    choices
        Allowed values for kind ``choice``.
    low, high
        Inclusive bounds for ``int`` / ``float``.
    length
        Required length for kind ``ints`` (e.g. 2 for a size ``[H, W]``); None allows any length.
    """

    name: str
    kind: str
    default: Any
    doc: str
    choices: tuple[Any, ...] = ()
    low: float | None = None
    high: float | None = None
    length: int | None = None

    def __post_init__(self):
        if self.kind not in PARAM_KINDS:
            raise ValueError(f"Param {self.name!r}: kind must be one of {PARAM_KINDS}, got {self.kind!r}")
        if self.kind == "choice" and not self.choices:
            raise ValueError(f"Param {self.name!r}: a choice parameter needs choices")

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    def type_text(self) -> str:
        if self.kind == "choice":
            return "|".join(str(c) for c in self.choices)
        if self.kind == "lights":
            return "list of [x, y, z] or .lp path"
        if self.kind == "ints":
            return f"list of {self.length or 'N'} ints"
        if self.low is not None and self.high is not None:
            return f"{self.kind} in [{self.low}, {self.high}]"
        if self.low is not None:
            return f"{self.kind} >= {self.low}"
        if self.high is not None:
            return f"{self.kind} <= {self.high}"
        return self.kind

    def coerce(self, value: Any, where: str) -> Any:
        """Check ``value`` against this parameter's kind; return it normalised. ``where`` names node and param."""
        def bad(found: str, hint: str | None = None):
            return BtforgeInputError(where, f"expected {self.type_text()}, found {found}", hint)

        kind = self.kind
        if kind == "bool":
            if not isinstance(value, bool):
                raise bad(repr(value), "write true or false")
            return value
        if kind == "int":
            if isinstance(value, bool) or not isinstance(value, int):
                raise bad(repr(value))
            self._check_bounds(value, where)
            return value
        if kind == "float":
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise bad(repr(value))
            if math.isnan(value) or (math.isinf(value) and (self.low is not None or self.high is not None)):
                raise bad(repr(value), "give a finite number")  # NaN compares false with every bound
            self._check_bounds(float(value), where)
            return float(value)
        if kind == "choice":
            if value not in self.choices:
                from difflib import get_close_matches
                near = get_close_matches(str(value), [str(c) for c in self.choices], n=1)
                raise bad(repr(value), f"did you mean '{near[0]}'?" if near else None)
            return value
        if kind in ("str", "path", "outpath"):
            if not isinstance(value, (str, os.PathLike)) or str(value) == "":
                raise bad(repr(value))
            return str(value)
        if kind == "ints":
            if isinstance(value, int) and not isinstance(value, bool) and self.length:
                value = [value] * self.length
            if not isinstance(value, (list, tuple)) or not all(isinstance(v, int) and not isinstance(v, bool) for v in value):
                raise bad(repr(value))
            if self.length and len(value) != self.length:
                raise bad(f"{len(value)} values")
            for v in value:
                self._check_bounds(v, where)
            return tuple(value)
        if kind == "lights":
            if isinstance(value, (str, os.PathLike)):
                return str(value)
            if not isinstance(value, (list, tuple)) or not value or not all(
                isinstance(v, (list, tuple)) and len(v) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
                for v in value
            ):
                raise bad(repr(value)[:80], "give [[x, y, z], ...] or the path of a .lp file")
            return tuple(tuple(float(x) for x in v) for v in value)
        return value

    def _check_bounds(self, value: float, where: str) -> None:
        if (self.low is not None and value < self.low) or (self.high is not None and value > self.high):
            nearest = self.low if self.low is not None and value < self.low else self.high
            raise BtforgeInputError(where, f"expected {self.type_text()}, found {value}",
                                    f"use a value in range, e.g. {nearest} ({self.doc})")


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED: Any = _Required()


@dataclasses.dataclass(frozen=True)
class Fact:
    """Something a precheck learnt about one of its node's outputs before anything runs, returned among the files
    it reads: e.g. ``Fact("stack", "views", 81, "btf.lvp")`` for a stack whose light file lists 81 views."""

    port: str
    name: str
    value: Any
    source: str = ""


@dataclasses.dataclass(frozen=True)
class Expect:
    """What a stage needs of a fact about a buffer wired into one of its inputs (``declare_stage(expects=...)``):
    the graph check reports a known fact of another value, with ``hint``, before anything runs."""

    name: str
    value: Any
    hint: str = ""


AUTO = "auto"  # a choice param's value meaning "the stage decides when it runs" (see ``facts_from_params``)


@dataclasses.dataclass(frozen=True)
class Stage:
    """A registered stage: its function plus everything needed to check a graph without running it."""

    name: str
    fn: Callable[..., Mapping[str, Any]]
    inputs: Mapping[str, str]
    outputs: Mapping[str, str]
    params: tuple[Param, ...]
    version: str = "1"
    optional_inputs: frozenset[str] = frozenset()
    side_effects: bool = False
    precheck: Callable[[Mapping[str, Any], "RunPaths"], Iterable[Path] | None] | None = None
    plugin: str = ""
    dynamic_inputs: Callable[[Mapping[str, Any], "RunPaths"], Mapping[str, str]] | None = None
    role: str = ""
    sweep: tuple[Mapping[str, Any], ...] = ()
    cache_outputs: bool = True
    per_texel: bool | Callable[[Mapping[str, Any]], bool] = False
    expects: Mapping[str, Expect] = dataclasses.field(default_factory=dict)
    keeps_facts: Mapping[str, str] = dataclasses.field(default_factory=dict)
    facts_from_params: Mapping[str, Mapping[str, str]] = dataclasses.field(default_factory=dict)
    settle: Callable[[Mapping[str, Any], Mapping[str, Any]], Mapping[str, Any]] | None = None
    streams: frozenset[str] = frozenset()
    device: bool = False
    deprecated_names: tuple[str, ...] = ()

    def is_per_texel(self, params: Mapping[str, Any]) -> bool:
        """Whether, with these params (once :attr:`settle` has decided what depends on the whole input), each
        texel's output depends only on that texel's input, so the stage can run on bands of texels - in this
        process band by band, or on a cluster - and the bands be joined."""
        return bool(self.per_texel(params) if callable(self.per_texel) else self.per_texel)

    def settled(self, inputs: Mapping[str, Any], params: Mapping[str, Any]) -> dict[str, Any]:
        """``params`` with every choice that needs the whole input (``space: auto``) decided on ``inputs``."""
        return dict(self.settle(inputs, params) if self.settle is not None else params)

    @property
    def doc(self) -> str:
        return inspect.cleandoc(self.fn.__doc__ or "")

    @property
    def summary(self) -> str:
        return self.doc.splitlines()[0] if self.doc else ""

    def input_ports(self, params: Mapping[str, Any] | None = None, paths: "RunPaths | None" = None) -> dict[str, str]:
        """The node's input ports: the declared ones plus those its parameters call for (``dynamic_inputs``)."""
        ports = dict(self.inputs)
        if self.dynamic_inputs is not None and params is not None:
            ports.update(self.dynamic_inputs(params, paths or RunPaths(Path.cwd(), Path.cwd())))
        return ports

    def param(self, name: str) -> Param | None:
        return next((p for p in self.params if p.name == name), None)

    def __call__(self, *args, **kwargs):
        """Call the stage directly (for plugin authors' tests): ``stage(ctx=None, **inputs, **params)``.

        Missing parameters take their defaults and a default :class:`~btforge.context.StageContext` is made when
        ``ctx`` is not given.  Inputs must be buffers of the declared types.
        """
        ctx = kwargs.pop("ctx", None) or (args[0] if args else None) or StageContext(node=self.name)
        values = {}
        for p in self.params:
            if p.name in kwargs:
                values[p.name] = p.coerce(kwargs.pop(p.name), f"stage '{self.name}', param '{p.name}'")
            elif p.required:
                raise BtforgeInputError(f"stage '{self.name}'", f"param '{p.name}' is required")
            else:
                values[p.name] = p.default
        return self.fn(ctx, **kwargs, **values)


def declare_stage(
    name: str,
    *,
    inputs: Mapping[str, str] | None = None,
    outputs: Mapping[str, str] | None = None,
    params: Sequence[Param] = (),
    version: str = "1",
    optional_inputs: Sequence[str] = (),
    side_effects: bool = False,
    precheck: Callable | None = None,
    dynamic_inputs: Callable | None = None,
    role: str = "",
    sweep: Sequence[Mapping[str, Any]] = (),
    cache_outputs: bool = True,
    per_texel: bool | Callable[[Mapping[str, Any]], bool] = False,
    expects: Mapping[str, Expect] | None = None,
    keeps_facts: Mapping[str, str] | None = None,
    facts_from_params: Mapping[str, Mapping[str, str]] | None = None,
    settle: Callable | None = None,
    streams: Sequence[str] = (),
    device: bool = False,
    deprecated_names: Sequence[str] = (),
) -> Callable[[Callable], Stage]:
    """Decorator that turns ``fn(ctx, **inputs, **params)`` into a :class:`Stage`.

    ``version`` is part of every cache key, beside the digest of the plugin's code (which changes by itself when
    a source or ``.cl`` file does): bump it to invalidate old results when nothing in the plugin changed.
    ``role`` says what the stage is for, so benches and tools find stages by what they do rather than by name:
    ``"fit"`` for representation fits (``stack: SampleStack -> model: ReflectanceModel``), ``"synthesizer"``
    for synthesizers that output a ``CoordMap``.  ``sweep`` lists the parameter settings a bench compares
    (e.g. ``[{"lobes": 1}, {"lobes": 2}]``); without it a bench measures the defaults.
    ``side_effects`` marks stages that write files; they run whenever they are needed, never from the cache.
    ``cache_outputs=False`` marks stages whose outputs cost more to store than to recompute (reading a capture:
    storing it would copy it, uncompressed, into the cache): they are keyed but not stored, and run only when a
    node reading their outputs is not in the cache itself.
    ``precheck(params, paths)`` may inspect input files named by parameters and raise ``BtforgeInputError``;
    it runs during validation, before any stage does.  It returns the further files the stage will read (the
    images a light file lists, a scene's meshes): their contents join the node's cache key, so editing one
    re-runs the node.  Files named directly by ``path``/``lights`` params are included without it.  Among the
    files a precheck may return :class:`Fact` items about its outputs (a stack's view count read from its
    header); ``expects={port: Expect(name, value, hint)}`` on a stage makes the graph check compare the fact of
    the buffer wired into ``port``, where one is known, and report a mismatch naming the node and port.
    ``keeps_facts={output: input}`` says an output has the facts of the buffer wired into ``input`` (a stage
    that changes samples but not the views or lights, such as an exposure correction); outputs typed
    ``"=port"`` keep those of ``port`` without it.  Facts of the stage's own precheck take precedence.
    ``facts_from_params={output: {fact: param}}`` says a fact of an output is the value of a param (a fit's
    ``space`` is the ``space`` of its model).  A param left at ``"auto"`` (:data:`AUTO`) is decided when the
    stage runs; where a consumer ``expects`` one of the param's choices of that fact, the graph check narrows
    ``auto`` to it (the node's params then say so, and the run report notes why), so the stage never makes a
    choice its consumer cannot take.  A value the param was given explicitly is compared like any other fact.
    An output typed ``"=port"`` has the type of whatever is wired into input ``port`` (a stage that crops or
    remaps any per-texel buffer returns the type it was given).
    ``dynamic_inputs(params, paths) -> {port: type}`` adds input ports that depend on parameters (a renderer
    has one port per material its scene names); the function then takes them as ``**kwargs``.
    ``per_texel`` (or ``per_texel(params) -> bool``) declares that each texel's outputs depend only on that
    texel's inputs, so the runner may run the stage on bands of texels - streamed in this process, or as tasks
    on a cluster - and join the results.  ``settle(inputs, params) -> params`` decides, once on the whole input,
    the choices that depend on all texels (``space: auto`` judged on a grid of texels); ``per_texel`` then
    speaks of the params as the graph gives them, with ``settle`` run first.
    ``streams=(port, ...)`` names outputs the stage can hand over as a stack read band by band
    (``stack.chunked``) instead of whole: the runner asks for it (``ctx.streamed``) when every node reading the
    port runs per texel, so no node ever needs it whole.
    ``device=True`` says the stage runs OpenCL kernels: the runner starts the device in the background as soon as
    it knows such a node will run, so the device's start overlaps the nodes before it (reading a capture).
    ``deprecated_names`` are old names of a renamed stage: graphs and ``btforge.stage()`` calls using one still
    get this stage, with a warning naming the new name; ``btforge stages`` lists the new name only.
    """

    def wrap(fn: Callable) -> Stage:
        declared = set(inputs or {}) | {p.name for p in params}
        sig = inspect.signature(fn)
        accepted = {n for n, p in list(sig.parameters.items())[1:] if p.kind != p.VAR_KEYWORD}
        takes_kwargs = any(p.kind == p.VAR_KEYWORD for p in sig.parameters.values())
        if dynamic_inputs is not None and not takes_kwargs:
            raise TypeError(f"stage {name!r}: a stage with dynamic_inputs must accept **kwargs")
        if declared != accepted:
            raise TypeError(f"stage {name!r}: function takes {sorted(accepted)}, declared {sorted(declared)}")
        for port, facts in (facts_from_params or {}).items():
            unknown = [param for param in facts.values() if param not in {p.name for p in params}]
            if port not in (outputs or {}) or unknown:
                raise TypeError(f"stage {name!r}: facts_from_params names output {port!r} and params {sorted(facts.values())}; "
                                f"declared outputs {sorted(outputs or {})}, params {sorted(p.name for p in params)}")
        return Stage(
            name=name, fn=fn, inputs=dict(inputs or {}), outputs=dict(outputs or {}), params=tuple(params),
            version=version, optional_inputs=frozenset(optional_inputs), side_effects=side_effects,
            precheck=precheck, plugin=fn.__module__, dynamic_inputs=dynamic_inputs, role=role,
            sweep=tuple(dict(entry) for entry in sweep), cache_outputs=cache_outputs, per_texel=per_texel,
            expects=dict(expects or {}), keeps_facts=dict(keeps_facts or {}),
            facts_from_params={port: dict(facts) for port, facts in (facts_from_params or {}).items()}, settle=settle,
            streams=frozenset(streams), device=device, deprecated_names=tuple(deprecated_names),
        )

    return wrap
