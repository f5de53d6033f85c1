"""Functions a reader takes in at once: no function in framework/ or plugins/ runs over 100 lines of code.

A docstring is not counted: a stage's docstring is its entry in the stage reference (docs/stages.md), read there,
and long because it documents every output key; the code below it is what a reader must hold at once.

The aim is about 60 lines (a screen); 100 is the hard limit a test can hold. ALLOWED lists the functions still
above it, with their current length: each may only shrink, and leaves the list once it is under the limit.
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 100
ALLOWED = {  # "path:function" -> its length when listed; being split into named steps
}


def function_lengths():
    """{"path:qualified.name": lines} of every function and method (decorators not counted)."""
    found = {}
    for folder in ("framework", "plugins"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
            _walk(tree, str(path.relative_to(ROOT)), "", found)
    return found


def _walk(node, path, prefix, found):
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            name = f"{prefix}{child.name}"
            if not isinstance(child, ast.ClassDef):
                found[f"{path}:{name}"] = child.end_lineno - child.lineno + 1 - _docstring_lines(child)
            _walk(child, path, name + ".", found)
        else:
            _walk(child, path, prefix, found)


def _docstring_lines(function) -> int:
    first = function.body[0]
    if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
        return first.end_lineno - first.lineno + 1
    return 0


def test_no_function_runs_over_the_limit():
    lengths = function_lengths()
    too_long = {name: n for name, n in lengths.items() if n > LIMIT and name not in ALLOWED}
    assert not too_long, (f"functions over {LIMIT} lines (split them into named steps): "
                          + ", ".join(f"{name} ({n})" for name, n in sorted(too_long.items())))


def test_allowed_functions_only_shrink():
    lengths = function_lengths()
    grown = {name: (lengths[name], n) for name, n in ALLOWED.items() if lengths.get(name, 0) > n}
    assert not grown, f"allow-listed functions grew (now, listed): {grown}"
    done = [name for name in ALLOWED if lengths.get(name, 0) <= LIMIT]
    assert not done, f"no longer over {LIMIT} lines, take them off ALLOWED: {done}"


def test_the_walk_finds_nested_functions_and_methods():
    found = {}
    _walk(ast.parse("class A:\n    def f(self):\n        def g():\n            pass\n"), "x.py", "", found)
    assert found == {"x.py:A.f": 3, "x.py:A.f.g": 2}


def test_a_docstring_is_not_counted():
    found = {}
    _walk(ast.parse('def f():\n    """One.\n\n    Two.\n    """\n    return 1\n'), "x.py", "", found)
    assert found == {"x.py:f": 2}
