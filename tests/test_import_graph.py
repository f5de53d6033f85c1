"""The import graph has layers: framework/ imports no plugin, plugin families do not import each other in a
circle, and neither do the modules inside framework/ or inside a family.

Imports are read from the sources (also those inside functions, which run later but still tie two modules
together). A package's ``__init__`` re-exporting its modules is not counted as a cycle. INTERNAL_CYCLES_ALLOWED
names families whose internal cycles are still being untangled.
"""
import ast
from pathlib import Path

import networkx as nx

ROOT = Path(__file__).resolve().parents[1]
INTERNAL_CYCLES_ALLOWED = {"synth"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    parts = ["btforge", *parts[1:]] if parts[0] == "framework" else ["btforge", *parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_imports() -> nx.DiGraph:
    """Module -> the btforge modules it imports (``from pkg import name`` counts as ``pkg.name`` when that is a
    module, else as ``pkg``)."""
    modules = {}
    for folder in ("framework", "plugins"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            modules[_module_name(path)] = path
    graph = nx.DiGraph()
    graph.add_nodes_from(modules)
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            for target in _targets(node, package):
                if target in modules and target != name:
                    graph.add_edge(name, target)
    return graph


def _targets(node, package: str) -> list[str]:
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    if not isinstance(node, ast.ImportFrom):
        return []
    if node.level:
        base = package.split(".")[:len(package.split(".")) - node.level + 1]
        module = ".".join(base + ([node.module] if node.module else []))
    else:
        module = node.module or ""
    return [module] + [f"{module}.{alias.name}" for alias in node.names]


def _family(module: str) -> str:
    parts = module.split(".")
    return parts[2] if len(parts) > 2 and parts[1] == "plugins" else "framework"


def _is_package_init(graph: nx.DiGraph, module: str) -> bool:
    return any(other.startswith(module + ".") for other in graph)


def test_framework_imports_no_plugin():
    graph = module_imports()
    found = sorted(f"{a} imports {b}" for a, b in graph.edges
                   if _family(a) == "framework" and _family(b) != "framework")
    assert not found, "the engine must not know any plugin:\n" + "\n".join(found)


def test_plugin_families_do_not_import_each_other_in_a_circle():
    graph = module_imports()
    families = nx.DiGraph()
    for a, b in graph.edges:
        if _family(a) != _family(b):
            families.add_edge(_family(a), _family(b), via=f"{a} -> {b}")
    cycles = list(nx.simple_cycles(families))
    assert not cycles, "families importing each other:\n" + "\n".join(
        " -> ".join(c + [c[0]]) + "  (" + "; ".join(families.edges[a, b]["via"] for a, b in zip(c, c[1:] + c[:1]))
        + ")" for c in cycles)


def test_no_module_cycles_inside_framework_or_a_family():
    graph = module_imports()
    inner = nx.DiGraph((a, b) for a, b in graph.edges
                       if _family(a) == _family(b) and _family(a) not in INTERNAL_CYCLES_ALLOWED
                       and not _is_package_init(graph, a) and not _is_package_init(graph, b))
    cycles = sorted(" -> ".join(c + [c[0]]) for c in nx.simple_cycles(inner))
    assert not cycles, "modules importing each other (move what both need into a lower module):\n" + "\n".join(cycles)


def test_the_reader_sees_imports_inside_functions_and_relative_ones():
    tree = ast.parse("def f():\n    from .b import c\n    import btforge.plugins.x\n")
    found = [t for node in ast.walk(tree) for t in _targets(node, "btforge.plugins.a")]
    assert "btforge.plugins.a.b" in found and "btforge.plugins.a.b.c" in found and "btforge.plugins.x" in found
