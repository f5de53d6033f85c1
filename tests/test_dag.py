"""framework/dag.py against networkx on random graphs: the same ancestors, cycles found exactly when there are
cycles, orders that respect every edge, and the lexicographical order networkx gives."""
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from btforge import dag

networkx = pytest.importorskip("networkx")  # the reference


def _graphs(draw_edges, n):
    ours, theirs = dag.DiGraph(), networkx.DiGraph()
    names = [f"n{i:02d}" for i in range(n)]
    ours.add_nodes_from(names)
    theirs.add_nodes_from(names)
    for a, b in draw_edges:
        ours.add_edge(names[a % n], names[b % n], ports=(a, b))
        theirs.add_edge(names[a % n], names[b % n], ports=(a, b))
    return ours, theirs


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 12), edges=st.lists(st.tuples(st.integers(0, 11), st.integers(0, 11)), max_size=30),
       acyclic=st.booleans())
def test_dag_agrees_with_networkx(n, edges, acyclic):
    if acyclic:  # edges only from a smaller to a larger index
        edges = [(min(a % n, b % n), max(a % n, b % n)) for a, b in edges if a % n != b % n]
    ours, theirs = _graphs(edges, n)
    assert list(ours) == list(theirs) and ours.number_of_edges() == theirs.number_of_edges()
    for node in theirs:
        assert ours.out_degree(node) == theirs.out_degree(node)
        assert set(ours.successors(node)) == set(theirs.successors(node))
        assert dag.ancestors(ours, node) == networkx.ancestors(theirs, node)
    is_dag = networkx.is_directed_acyclic_graph(theirs)
    assert dag.is_directed_acyclic_graph(ours) == is_dag
    if is_dag:
        assert dag.lexicographical_topological_sort(ours) == list(networkx.lexicographical_topological_sort(theirs))
        order = {node: i for i, node in enumerate(dag.topological_sort(ours))}
        assert all(order[a] < order[b] for a, b in theirs.edges)
    else:
        cycle = dag.find_cycle(ours)
        assert cycle and all(theirs.has_edge(a, b) for a, b in cycle)
        assert all(b == c for (_, b), (c, _) in zip(cycle, cycle[1:] + cycle[:1]))  # closed, in order


def test_no_cycle_is_an_exception():
    graph = dag.DiGraph()
    graph.add_edge("a", "b")
    try:
        dag.find_cycle(graph)
    except dag.NetworkXNoCycle:
        pass
    else:
        raise AssertionError("expected NetworkXNoCycle")
