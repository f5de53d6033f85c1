"""Every way of breaking a graph is caught before anything runs, with a message that names the place."""
import subprocess
import sys
from pathlib import Path

import pytest

from btforge import BtforgeInputError
from btforge.graph import check_graph, load_graph
from btforge.registry import default_registry

from conftest import FIXTURES

BAD_GRAPHS = sorted((FIXTURES / "graphs").glob("*.yaml"))


def expected_message(path: Path) -> str:
    first = path.read_text(encoding="latin-1").splitlines()[0]
    assert first.startswith("# expect: "), f"{path.name} must start with '# expect: ...'"
    return first[len("# expect: "):]


@pytest.mark.parametrize("path", BAD_GRAPHS, ids=[p.stem for p in BAD_GRAPHS])
def test_bad_graph_is_rejected_with_a_clear_message(path):
    with pytest.raises(BtforgeInputError) as info:
        check_graph(load_graph(path), default_registry())
    message = info.value.render()
    assert expected_message(path) in message
    assert path.name in message  # the file is named
    if path.stem not in ("not_yaml", "no_nodes", "cycle", "not_utf8"):
        assert "line " in message  # and the line


def test_every_problem_is_listed_at_once(tmp_path):
    graph = tmp_path / "two.yaml"
    graph.write_text("nodes:\n  a: {stage: nope}\n  b: {stage: ptm.fit, params: {variant: x}}\n")
    with pytest.raises(BtforgeInputError) as info:
        check_graph(load_graph(graph), default_registry())
    text = info.value.render()
    assert "3 problems" in text and "is not wired" in text and "unknown stage 'nope'" in text and "param 'variant'" in text


def test_set_override_must_name_a_node():
    with pytest.raises(BtforgeInputError, match="expected NODE.PARAM"):
        load_graph(FIXTURES / "graphs" / "unknown_param.yaml", {"nosuch.variant": "rgb"})


def test_an_overridden_param_is_blamed_on_its_set_not_the_file_line():
    spec = load_graph(FIXTURES / "graphs" / "out_of_range_param.yaml")
    node = next(n for n in spec.nodes.values() if n.param_lines)
    key = next(iter(node.param_lines))
    with pytest.raises(BtforgeInputError) as info:
        check_graph(load_graph(FIXTURES / "graphs" / "out_of_range_param.yaml", {f"{node.name}.{key}": "junk"}),
                    default_registry())
    assert f"--set {node.name}.{key}" in info.value.render() and "line" not in info.value.render().split(":")[0]


def test_cli_bad_set_value_is_a_clear_error():
    demo = Path(__file__).resolve().parents[1] / "graphs" / "demo.yaml"
    proc = subprocess.run([sys.executable, "-m", "btforge.cli", "validate", str(demo), "--set", "fit.variant=["],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "--set fit.variant=[" in proc.stderr and "not valid YAML" in proc.stderr


def test_cli_validate_exits_2_without_traceback():
    bad = FIXTURES / "graphs" / "cycle.yaml"
    proc = subprocess.run([sys.executable, "-m", "btforge.cli", "validate", str(bad)], capture_output=True, text=True)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "cycle" in proc.stderr


def test_cli_debug_shows_the_traceback():
    bad = FIXTURES / "graphs" / "cycle.yaml"
    proc = subprocess.run([sys.executable, "-m", "btforge.cli", "--debug", "validate", str(bad)],
                          capture_output=True, text=True)
    assert proc.returncode != 0 and "Traceback" in proc.stderr


def test_demo_graph_validates():
    repo = Path(__file__).resolve().parents[1]
    checked = check_graph(load_graph(repo / "graphs" / "demo.yaml"), default_registry())
    assert "fit" in checked.stages


SHIPPED_GRAPHS = sorted((Path(__file__).resolve().parents[1] / "graphs").glob("*.yaml"))


@pytest.mark.parametrize("path", SHIPPED_GRAPHS, ids=[p.stem for p in SHIPPED_GRAPHS])
def test_every_shipped_graph_validates(path):
    from conftest import SHARED_DATA
    if "shared/data" in path.read_text() and not SHARED_DATA.is_dir():
        pytest.skip("needs ../shared/data")
    checked = check_graph(load_graph(path), default_registry())
    assert checked.dag.number_of_nodes() >= 2
