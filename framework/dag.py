"""The dependency graph of a checked graph: a small directed graph and the few algorithms the checks use.

networkx did this before, and importing it cost a quarter of a fresh ``btforge run``'s start-up CPU (about
0.1-0.2 s, more than pyopencl) for five algorithms on graphs of tens of nodes.  The names are networkx's
(``DiGraph``, ``ancestors``, ``topological_sort``, ``lexicographical_topological_sort``, ``find_cycle``,
``is_directed_acyclic_graph``, ``NetworkXNoCycle``), so code written against it reads the same.
"""
from __future__ import annotations

import heapq
from typing import Any, Hashable, Iterable, Iterator


class NetworkXNoCycle(Exception):
    """:func:`find_cycle` found no cycle."""


class NetworkXUnfeasible(Exception):
    """A topological order was asked of a graph with a cycle."""


class DiGraph:
    """Nodes (in insertion order) and directed edges with a dict of attributes each."""

    def __init__(self) -> None:
        self._succ: dict[Hashable, dict[Hashable, dict[str, Any]]] = {}
        self._pred: dict[Hashable, dict[Hashable, dict[str, Any]]] = {}

    def add_node(self, node: Hashable) -> None:
        self._succ.setdefault(node, {})
        self._pred.setdefault(node, {})

    def add_nodes_from(self, nodes: Iterable[Hashable]) -> None:
        for node in nodes:
            self.add_node(node)

    def add_edge(self, source: Hashable, target: Hashable, **attributes: Any) -> None:
        self.add_node(source)
        self.add_node(target)
        data = self._succ[source].setdefault(target, {})
        data.update(attributes)
        self._pred[target][source] = data

    def __iter__(self) -> Iterator[Hashable]:
        return iter(self._succ)

    def __contains__(self, node: object) -> bool:
        return node in self._succ

    def __len__(self) -> int:
        return len(self._succ)

    def successors(self, node: Hashable) -> Iterator[Hashable]:
        return iter(self._succ[node])

    def predecessors(self, node: Hashable) -> Iterator[Hashable]:
        return iter(self._pred[node])

    def out_degree(self, node: Hashable) -> int:
        return len(self._succ[node])

    def in_degree(self, node: Hashable) -> int:
        return len(self._pred[node])

    def number_of_nodes(self) -> int:
        return len(self._succ)

    def number_of_edges(self) -> int:
        return sum(len(targets) for targets in self._succ.values())

    def edge_data(self, source: Hashable, target: Hashable) -> dict[str, Any]:
        return self._succ[source][target]


def ancestors(graph: DiGraph, node: Hashable) -> set[Hashable]:
    """Every node with a path to ``node`` (not ``node`` itself)."""
    found: set[Hashable] = set()
    todo = list(graph.predecessors(node))
    while todo:
        current = todo.pop()
        if current not in found:
            found.add(current)
            todo.extend(graph.predecessors(current))
    found.discard(node)
    return found


def lexicographical_topological_sort(graph: DiGraph) -> list[Hashable]:
    """A dependency order that takes, among the nodes whose inputs are all placed, the smallest first."""
    waiting = {node: graph.in_degree(node) for node in graph}
    ready = [node for node, count in waiting.items() if count == 0]
    heapq.heapify(ready)
    order = []
    while ready:
        node = heapq.heappop(ready)
        order.append(node)
        for target in graph.successors(node):
            waiting[target] -= 1
            if waiting[target] == 0:
                heapq.heappush(ready, target)
    if len(order) != len(graph):
        raise NetworkXUnfeasible("the graph has a cycle: no dependency order exists")
    return order


def topological_sort(graph: DiGraph) -> list[Hashable]:
    """A dependency order: every node after all nodes it depends on."""
    waiting = {node: graph.in_degree(node) for node in graph}
    ready = [node for node, count in waiting.items() if count == 0]
    order = []
    while ready:
        node = ready.pop(0)
        order.append(node)
        for target in graph.successors(node):
            waiting[target] -= 1
            if waiting[target] == 0:
                ready.append(target)
    if len(order) != len(graph):
        raise NetworkXUnfeasible("the graph has a cycle: no dependency order exists")
    return order


def find_cycle(graph: DiGraph) -> list[tuple[Hashable, Hashable]]:
    """The edges of one cycle, in order along it (a depth-first search from the nodes in insertion order);
    :class:`NetworkXNoCycle` when there is none."""
    state: dict[Hashable, int] = {}  # 1: on the current path, 2: finished
    for root in graph:
        if root in state:
            continue
        path, stack = [root], [iter(graph.successors(root))]
        state[root] = 1
        while stack:
            target = next(stack[-1], None)
            if target is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(target) == 1:  # back to a node on the path: the cycle is the path from there
                loop = path[path.index(target):] + [target]
                return list(zip(loop, loop[1:]))
            elif target not in state:
                state[target] = 1
                path.append(target)
                stack.append(iter(graph.successors(target)))
    raise NetworkXNoCycle("no cycle found")


def is_directed_acyclic_graph(graph: DiGraph) -> bool:
    try:
        find_cycle(graph)
    except NetworkXNoCycle:
        return True
    return False
