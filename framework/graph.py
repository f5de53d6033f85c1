"""Node graphs: plain YAML data, checked completely before anything runs.

A graph file is a mapping ``nodes: {name: {stage, params, inputs}}``; an input is wired as ``node.port``.
:func:`load_graph` parses it (keeping line numbers for messages), and :func:`check_graph` validates stages,
parameters, ports, port types, cycles and input files against the registry, collecting every problem it finds
into one :class:`BtforgeInputError`.  The checked graph is a ``DiGraph`` (``framework/dag.py``) whose edges
carry the ports.
"""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Mapping

from . import dag as nx  # networkx's names, without its import cost
import yaml

from .errors import BtforgeInputError, collect_warnings
from .registry import Registry, did_you_mean
from .stages import AUTO, Fact, RunPaths, Stage

NODE_KEYS = ("stage", "params", "inputs")


class _LineDict(dict):
    """A mapping that remembers the source line of each key."""

    lines: dict[str, int]


class _LineLoader(yaml.SafeLoader):
    pass


def _construct_mapping(loader: _LineLoader, node: yaml.MappingNode) -> _LineDict:
    loader.flatten_mapping(node)
    out = _LineDict()
    out.lines = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if key in out.lines:  # plain YAML keeps the last one silently: a node or param would vanish unseen
            raise yaml.constructor.ConstructorError(
                problem=f"duplicate key '{key}' (first given on line {out.lines[key]})",
                problem_mark=key_node.start_mark)
        out[key] = loader.construct_object(value_node, deep=True)
        out.lines[key] = key_node.start_mark.line + 1
    return out


_LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


@dataclasses.dataclass(frozen=True)
class NodeSpec:
    name: str
    stage: str
    params: Mapping[str, Any]
    inputs: Mapping[str, tuple[str, str]]
    line: int | None = None
    param_lines: Mapping[str, int] = dataclasses.field(default_factory=dict)
    input_lines: Mapping[str, int] = dataclasses.field(default_factory=dict)
    overridden: frozenset[str] = frozenset()  # params given by --set, not by the file

    def param_where(self, spec: "GraphSpec", key: str) -> str:
        """Where param ``key`` was given: its line in the file, or the ``--set`` that overrode it."""
        if key in self.overridden:
            return f"--set {self.name}.{key}"
        return spec.where(self.name, self.param_lines.get(key, self.line)) + f", param '{key}'"


@dataclasses.dataclass(frozen=True)
class GraphSpec:
    """A parsed graph (not yet checked): its nodes and where its relative paths resolve."""

    nodes: Mapping[str, NodeSpec]
    source: str
    graph_dir: Path

    def where(self, node: str | None = None, line: int | None = None) -> str:
        text = self.source
        if line:
            text += f", line {line}"
        if node:
            text += f", node '{node}'"
        return text


def load_graph(graph: str | os.PathLike | Mapping[str, Any], overrides: Mapping[str, Any] | None = None) -> GraphSpec:
    """Parse a graph file (or an already-loaded mapping) and apply ``--set NODE.PARAM=VALUE`` overrides."""
    if isinstance(graph, Mapping):
        data, source, graph_dir = graph, "<graph>", Path.cwd()
    else:
        path = Path(graph)
        data, source, graph_dir = _read_yaml(path), str(path), path.resolve().parent

    if not isinstance(data, Mapping) or not isinstance(data.get("nodes"), Mapping) or not data["nodes"]:
        raise BtforgeInputError(source, "expected a mapping with a non-empty 'nodes:' mapping at the top",
                                "see graphs/demo.yaml for the layout")
    unknown_top = [k for k in data if k not in ("nodes", "description")]
    if unknown_top:
        raise BtforgeInputError(source, f"unknown top-level key '{unknown_top[0]}'", "only 'nodes' and 'description' are allowed")
    node_lines = getattr(data["nodes"], "lines", {})
    nodes = {name: _parse_node(name, body, source, node_lines.get(name)) for name, body in data["nodes"].items()}
    _apply_overrides(nodes, overrides or {})
    return GraphSpec(nodes=nodes, source=source, graph_dir=graph_dir)


def _read_yaml(path: Path) -> Any:
    """The YAML of a graph file, its mappings remembering their keys' lines."""
    if not path.is_file():
        raise BtforgeInputError(str(path), "graph file not found", "check the path")
    try:
        return yaml.load(path.read_text(encoding="utf-8"), Loader=_LineLoader)
    except UnicodeDecodeError as exc:
        raise BtforgeInputError(str(path), f"is not UTF-8 text (byte {exc.start}: {exc.reason})",
                                "save the graph file as UTF-8") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}, line {mark.line + 1}" if mark else str(path)
        raise BtforgeInputError(where, f"is not valid YAML: {getattr(exc, 'problem', exc)}") from None


def _parse_node(name: Any, body: Any, source: str, line: int | None) -> NodeSpec:
    """One node's stage, params and wired inputs, with the lines they were given on."""
    where = f"{source}{f', line {line}' if line else ''}, node '{name}'"
    if not isinstance(name, str) or not name or "." in name:
        raise BtforgeInputError(where, "node names must be non-empty strings without dots",
                                "rename the node (dots separate node and port in wiring)")
    if not isinstance(body, Mapping):
        raise BtforgeInputError(where, f"expected a mapping with 'stage', 'params', 'inputs', found {type(body).__name__}")
    extra = [k for k in body if k not in NODE_KEYS]
    if extra:
        raise BtforgeInputError(where, f"unknown key '{extra[0]}'", did_you_mean(str(extra[0]), NODE_KEYS))
    if not isinstance(body.get("stage"), str):
        raise BtforgeInputError(where, "expected 'stage: NAME'", "add the stage this node runs, see `btforge stages`")
    params = body.get("params") or {}
    inputs = body.get("inputs") or {}
    for key, value in (("params", params), ("inputs", inputs)):
        if not isinstance(value, Mapping):
            raise BtforgeInputError(where, f"expected '{key}' to be a mapping, found {type(value).__name__}")
    wired: dict[str, tuple[str, str]] = {}
    for port, ref in inputs.items():
        if not isinstance(ref, str) or ref.count(".") != 1 or not all(ref.split(".")):
            iline = getattr(inputs, "lines", {}).get(port)
            raise BtforgeInputError(f"{source}{f', line {iline}' if iline else ''}, node '{name}', input '{port}'",
                                    f"expected 'node.port', found {ref!r}", "wire inputs as e.g. 'fit.model'")
        src, src_port = ref.split(".")
        wired[port] = (src, src_port)
    return NodeSpec(name=name, stage=body["stage"], params=dict(params), inputs=wired, line=line,
                    param_lines=dict(getattr(params, "lines", {})), input_lines=dict(getattr(inputs, "lines", {})))


def _apply_overrides(nodes: dict[str, NodeSpec], overrides: Mapping[str, Any]) -> None:
    """``--set NODE.PARAM=VALUE``: the value replaces the file's, and messages name the ``--set``."""
    for key, value in overrides.items():
        node, _, param = key.partition(".")
        if node not in nodes or not param:
            raise BtforgeInputError(f"--set {key}", f"expected NODE.PARAM with a node of the graph, found '{key}'",
                                    did_you_mean(node, nodes))
        spec = nodes[node]
        nodes[node] = dataclasses.replace(spec, params={**spec.params, param: value},
                                          overridden=spec.overridden | {param})


@dataclasses.dataclass(frozen=True)
class CheckedGraph:
    """A graph that passed every check: typed stages, coerced params, and the dependency DiGraph."""

    spec: GraphSpec
    stages: Mapping[str, Stage]
    params: Mapping[str, Mapping[str, Any]]
    dag: nx.DiGraph
    files: Mapping[str, tuple[Path, ...]] = dataclasses.field(default_factory=dict)  # what each node reads
    warnings: Mapping[str, list[str]] = dataclasses.field(default_factory=dict)  # raised while its files were read
    notes: Mapping[str, Mapping[str, str]] = dataclasses.field(default_factory=dict)  # 'auto' params narrowed, why

    def needed_for(self, targets: list[str] | None) -> list[str]:
        """Nodes to evaluate, in dependency order, to produce ``targets`` (default: every sink node)."""
        if not targets:
            targets = [n for n in self.dag if self.dag.out_degree(n) == 0]
        needed: set[str] = set()
        for t in targets:
            if t not in self.dag:
                raise BtforgeInputError(f"--only {t}", "is not a node of the graph", did_you_mean(t, self.dag))
            needed |= nx.ancestors(self.dag, t) | {t}
        return [n for n in nx.lexicographical_topological_sort(self.dag) if n in needed]


def _resolve_output_types(spec: GraphSpec, stages: Mapping[str, Stage], dag: nx.DiGraph) -> dict[str, dict[str, str]]:
    """Each node's output types; an output declared ``"=port"`` has the type of what is wired into ``port``
    (a crop or a coordinate-map replay returns the type it was given)."""
    resolved: dict[str, dict[str, str]] = {}
    for name in nx.topological_sort(dag):
        st = stages.get(name)
        if st is None:
            continue
        wired = spec.nodes[name].inputs
        types = {}
        for port, declared in st.outputs.items():
            if declared.startswith("="):
                src, src_port = wired.get(declared[1:], (None, None))
                declared = resolved.get(src, {}).get(src_port, st.inputs[declared[1:]])
            types[port] = declared
        resolved[name] = types
    return resolved


def check_graph(spec: GraphSpec, registry: Registry, out_dir: Path | None = None) -> CheckedGraph:
    """Validate everything that can be validated without running a stage; raise one error listing all problems.

    The checks run as passes over the whole graph, each collecting its problems and carrying on: stage names,
    parameters and input files, the wiring of ports, cycles and port types, the stages' prechecks (run for every
    node whose own params are sound, whatever else failed), and the facts prechecks learnt about the buffers
    that flow along the edges.
    """
    check = _GraphCheck(spec, registry, RunPaths(spec.graph_dir, out_dir or Path.cwd()))
    check.resolve_stages()
    check.coerce_params()
    check.wire_ports()
    check.check_types()
    check.run_prechecks()
    check.compare_facts()
    return check.result()


class _GraphCheck:
    """The state the passes of :func:`check_graph` share: what each pass found, and the problems so far."""

    def __init__(self, spec: GraphSpec, registry: Registry, paths: RunPaths):
        self.spec, self.registry, self.paths = spec, registry, paths
        self.problems: list[str] = []
        self.stages: dict[str, Stage] = {}
        self.params: dict[str, dict[str, Any]] = {}
        self.params_ok: set[str] = set()  # nodes whose own params and files passed: their prechecks can run
        self.dag = nx.DiGraph()
        self.dag.add_nodes_from(spec.nodes)
        self.node_ports: dict[str, dict[str, str]] = {}
        self.typed_edges: list[tuple[str, str, str, str, str]] = []  # (where, src, src_port, node, port)
        self.files: dict[str, tuple[Path, ...]] = {}
        self.warnings: dict[str, list[str]] = {}
        self.facts: dict[tuple[str, str], dict[str, Fact]] = {}  # (node, output port) -> what its precheck learnt
        self.notes: dict[str, dict[str, str]] = {}  # node -> {'PARAM (auto)': what the check narrowed it to, why}

    def problem(self, where: str, text: str, hint: str | None = None) -> None:
        self.problems.append(f"{where}: {text}" + (f" ({hint})" if hint else ""))

    def resolve_stages(self) -> None:
        """Each node's stage, by its name or by a deprecated name (which warns, naming the new one)."""
        for name, node in self.spec.nodes.items():
            with collect_warnings() as caught:
                stage = self.registry.find_stage(node.stage, where=self.spec.where(name, node.line))
            if caught:
                self.warnings.setdefault(name, []).extend(caught)
            if stage is not None:
                self.stages[name] = stage
            else:
                self.problem(self.spec.where(name, node.line), f"unknown stage '{node.stage}'",
                             did_you_mean(node.stage, self.registry.stages))

    def coerce_params(self) -> None:
        """Every param known, of its kind and in range; required ones given; input files present."""
        for name, st in self.stages.items():
            node = self.spec.nodes[name]
            before = len(self.problems)
            values: dict[str, Any] = {}
            for key, raw in node.params.items():
                param = st.param(key)
                where = node.param_where(self.spec, key)
                if param is None:
                    self.problem(where, f"stage '{st.name}' has no such parameter",
                                 did_you_mean(key, [p.name for p in st.params]))
                    continue
                try:
                    values[key] = param.coerce(raw, where)
                except BtforgeInputError as exc:
                    self.problems.append(exc.one_line())
            for p in st.params:
                if p.name not in values and p.name not in node.params:
                    if p.required:
                        self.problem(self.spec.where(name, node.line),
                                     f"missing required param '{p.name}' ({p.type_text()}: {p.doc})")
                    else:
                        values[p.name] = p.default
            for p, value in _file_params(st, values):
                if not self.paths.input(value).exists():
                    what = "light file" if p.kind == "lights" else "input file"
                    self.problem(node.param_where(self.spec, p.name), f"{what} not found: {self.paths.input(value)}",
                                 "paths are relative to the graph file's folder")
            self.params[name] = values
            if len(self.problems) == before:
                self.params_ok.add(name)

    def wire_ports(self) -> None:
        """Every wired input names a port of the stage and an output of an existing node; every port is wired."""
        for name, st in self.stages.items():
            node = self.spec.nodes[name]
            try:
                ports = st.input_ports(self.params[name], self.paths)
            except BtforgeInputError as exc:
                self.problems.append(exc.located(self.spec.where(name, node.line)).one_line())
                continue
            for port, type_name in ports.items():
                if port not in st.inputs and type_name not in self.registry.types:
                    self.problem(self.spec.where(name, node.line), f"stage '{st.name}' asks for input port '{port}' "
                                 f"of unknown buffer type '{type_name}'",
                                 "a bug in the plugin: its dynamic_inputs must name known types")
            for port, (src, src_port) in node.inputs.items():
                self._wire(name, st, ports, port, src, src_port)
            self.node_ports[name] = ports
            for port in ports:
                if port not in node.inputs and port not in st.optional_inputs:
                    self.problem(self.spec.where(name, node.line), f"input port '{port}' ({ports[port]}) is not wired",
                                 f"add 'inputs: {{{port}: NODE.PORT}}'")

    def _wire(self, name: str, st: Stage, ports: Mapping[str, str], port: str, src: str, src_port: str) -> None:
        node = self.spec.nodes[name]
        where = self.spec.where(name, node.input_lines.get(port, node.line)) + f", input '{port}'"
        if port not in ports:
            self.problem(where, f"stage '{st.name}' has no input port '{port}'", did_you_mean(port, ports))
            return
        if src not in self.spec.nodes:
            self.problem(where, f"wired to unknown node '{src}'", did_you_mean(src, self.spec.nodes))
            return
        self.dag.add_edge(src, name, ports=(src_port, port))
        src_stage = self.stages.get(src)
        if src_stage is None:
            return
        if src_port not in src_stage.outputs:
            self.problem(where, f"node '{src}' ({src_stage.name}) has no output port '{src_port}'",
                         did_you_mean(src_port, src_stage.outputs))
            return
        self.typed_edges.append((where, src, src_port, name, port))

    def check_types(self) -> None:
        """No cycles (printed as ``a -> b -> a``); each wired output of a type the input port accepts."""
        try:
            cycle = nx.find_cycle(self.dag)
        except nx.NetworkXNoCycle:
            cycle = None
        if cycle:
            loop = " -> ".join([e[0] for e in cycle] + [cycle[0][0]])
            self.problem(self.spec.source, f"the graph has a cycle: {loop}", "a node cannot depend on its own output")
            return
        output_types = _resolve_output_types(self.spec, self.stages, self.dag)
        for where, src, src_port, name, port in self.typed_edges:
            have, want = output_types[src][src_port], self.node_ports[name][port]
            if not self.registry.accepts(want, have):
                self.problem(where, f"expects {want}, but '{src}.{src_port}' gives {have}",
                             "wire an output of the expected type")

    def run_prechecks(self) -> None:
        """What each stage can check in its inputs without running; the files it will read and the facts it
        learnt about its outputs (warnings raised meanwhile are kept for the report)."""
        for name in (n for n in self.stages if n in self.params_ok):
            st = self.stages[name]
            read = [self.paths.input(value) for p, value in _file_params(st, self.params[name])]
            if st.precheck is not None:
                with collect_warnings() as caught:
                    try:
                        for item in st.precheck(self.params[name], self.paths) or ():
                            if isinstance(item, Fact):
                                self.facts.setdefault((name, item.port), {})[item.name] = item
                            else:
                                read.append(item)
                    except BtforgeInputError as exc:
                        self.problems.append(exc.located(self.spec.where(name, self.spec.nodes[name].line)).one_line())
                if caught:
                    self.warnings.setdefault(name, []).extend(caught)
            self.files[name] = tuple(read)

    def compare_facts(self) -> None:
        """Facts flow along the edges (``keeps_facts``, ``"=port"`` outputs); a param left at ``auto`` that decides
        a fact a consumer expects is narrowed to the expected value; a stage's ``expects`` is compared with the
        fact of what is wired into the port, where one is known."""
        self.facts_of_params()
        _pass_facts_on(self.spec, self.stages, self.dag, self.facts)
        self.narrow_auto_params()
        for where, src, src_port, name, port in self.typed_edges:
            expect = self.stages[name].expects.get(port)
            fact = self.facts.get((src, src_port), {}).get(expect.name) if expect else None
            if fact is not None and fact.value != expect.value:
                source = f" (from {fact.source})" if fact.source else ""
                self.problem(where, f"{self.stages[name].name} expects {expect.name}: {expect.value}, found "
                             f"{fact.value} in '{src}.{src_port}'{source}",
                             expect.hint.replace("NODE.PORT", f"{src}.{src_port}") or None)

    def facts_of_params(self) -> None:
        """The facts params decide (``facts_from_params``), where the param is not left to the stage (``auto``);
        facts of the stage's precheck take precedence."""
        for name, st in self.stages.items():
            for port, facts in st.facts_from_params.items():
                for fact, param in facts.items():
                    value = self.params.get(name, {}).get(param, AUTO)
                    if value != AUTO:
                        where = self.spec.nodes[name].param_where(self.spec, param)
                        self.facts.setdefault((name, port), {}).setdefault(fact, Fact(port, fact, value, where))

    def narrow_auto_params(self) -> None:
        """For each input that expects a fact not yet known, the ``auto`` param upstream that will decide it (through
        nodes that keep facts) is narrowed to the expected value, when that is one of the param's choices: the node
        then makes only the choice its consumer can take."""
        for _where, src, src_port, name, port in self.typed_edges:
            expect = self.stages[name].expects.get(port)
            if expect is None or expect.name in self.facts.get((src, src_port), {}):
                continue
            origin = self._auto_origin(src, src_port, expect.name)
            if origin is None:
                continue
            node, out_port, param = origin
            if expect.value not in (self.stages[node].param(param).choices or ()):
                continue
            self.params[node] = {**self.params[node], param: expect.value}
            why = f"{expect.value}, as node '{name}' ({self.stages[name].name}) takes {expect.name} {expect.value} only"
            self.notes.setdefault(node, {})[f"{param} ({AUTO})"] = why
            self.facts.setdefault((node, out_port), {})[expect.name] = Fact(
                out_port, expect.name, expect.value, f"{self.spec.nodes[node].param_where(self.spec, param)}: {AUTO} "
                f"narrowed to {why}")
            _pass_facts_on(self.spec, self.stages, self.dag, self.facts)

    def _auto_origin(self, node: str, port: str, fact: str) -> tuple[str, str, str] | None:
        """(node, output port, param) of the ``auto`` param that will decide ``fact`` of ``node.port``, following the
        outputs that keep an input's facts upstream; None when no such param decides it."""
        seen: set[tuple[str, str]] = set()
        while (node, port) not in seen and node in self.stages:
            seen.add((node, port))
            st = self.stages[node]
            param = st.facts_from_params.get(port, {}).get(fact)
            if param is not None:
                return (node, port, param) if self.params.get(node, {}).get(param) == AUTO else None
            kept_from = _kept_facts(st).get(port)
            wired = self.spec.nodes[node].inputs.get(kept_from) if kept_from else None
            if wired is None:
                return None
            node, port = wired
        return None

    def result(self) -> CheckedGraph:
        if self.problems:
            if len(self.problems) == 1:
                raise BtforgeInputError("", self.problems[0])
            raise BtforgeInputError(self.spec.source, f"{len(self.problems)} problems:\n  - " + "\n  - ".join(self.problems))
        return CheckedGraph(spec=self.spec, stages=self.stages, params=self.params, dag=self.dag, files=self.files,
                            warnings=self.warnings, notes=self.notes)


def _pass_facts_on(spec: GraphSpec, stages: Mapping[str, Stage], dag: nx.DiGraph,
                   facts: dict[tuple[str, str], dict[str, Fact]]) -> None:
    """Give outputs that keep their input's facts (``keeps_facts``, ``"=port"`` outputs) the facts of what is wired
    into that input, in graph order, under the node's own; a graph with a cycle has no order and passes none."""
    if not nx.is_directed_acyclic_graph(dag):
        return
    for name in nx.topological_sort(dag):
        st = stages.get(name)
        if st is None:
            continue
        for out_port, in_port in _kept_facts(st).items():
            src = spec.nodes[name].inputs.get(in_port)
            inherited = facts.get(tuple(src), {}) if src else {}
            if inherited:
                facts[(name, out_port)] = {**inherited, **facts.get((name, out_port), {})}


def _kept_facts(st: Stage) -> dict[str, str]:
    """{output: input} of the outputs that keep the facts of what is wired into an input."""
    kept = {port: declared[1:] for port, declared in st.outputs.items() if declared.startswith("=")}
    kept.update(st.keeps_facts)
    return kept


def _file_params(st: Stage, values: Mapping[str, Any]):
    """(param, value) of the params naming a file the stage reads."""
    return [(p, values[p.name]) for p in st.params if p.kind in ("path", "lights") and isinstance(values.get(p.name), str)]
