"""Straight seams re-cut by minimum cuts, as Graphcut Textures (Kwatra et al. 2003) re-cuts old seams.

The refinement's labelling (:mod:`.refine`) changes one texel at a time.  A seam that runs straight along the side
of a copied block stays where it is whenever every single-texel move costs more seam than it saves: typically
where it cuts across a stone or a colour area whose far side lies beyond one window.  The eye picks such straight
cuts out first.

Here every seam edge in a straight run of :data:`~.visibility.STRAIGHT_RUN` or more texels gets a band of
:data:`BAND` texels on either side, in which each texel may take the continuation of the source on either side of
the seam (the exemplar texels that lie, in the exemplar, where the band texel lies in the output).  Two expansion
moves follow (the first side's continuations, then the second's).  Each is a binary labelling, keep or take, of
least seam cost (zero between texels whose sources continue each other, else the squared appearance difference of
each texel and the other's exemplar neighbour), solved exactly by a minimum s-t cut (scipy's Dinic maximum flow).
The cut runs where the two sides agree: the mortar between stones, the soft edge of a colour area.  With
``bridges`` (tries per run), the runs left then get a third kind of proposal: other pieces of the exemplar that
join both sides (:mod:`.bridging`).  A move is kept only when it lowers the seam cost of the edges it touches.
Pinned texels keep their sources, and a band stops at them (its continuations do not reach across a pinned ring
into another tile of a mosaic).  Runs whose bands overlap are re-cut in separate groups (:func:`apart_groups`): one
proposal holds one continuation per texel, and the two seams of a sliver, a strip of a texel or two between two
pieces, would otherwise offer the sliver's own continuation where the piece beyond it should be offered.

A seam edge that lies in a straight run costs :data:`STRAIGHT_WEIGHT` x its appearance difference while it stays:
the eye follows a straight cut along its whole length, while a cut that wanders shows only where it crosses
something.  Without the weight the minimum cut keeps a straight seam wherever every other cut costs as much per
edge or a little more, however long the line it leaves.
"""
from __future__ import annotations

import numpy as np

from .bridging import ExemplarSpectrum, bridging_proposals
from .features import beside, edge_padded
from .visibility import STRAIGHT_RUN, in_long_runs, run_labels, seam_masks

#: Texels on either side of a straight seam that may take a continuation of either side.
BAND = 8
#: Rounds of re-cutting (each finds the straight runs again).
PASSES = 2
#: Largest total capacity of a cut's graph (scipy's maximum flow counts in 32-bit integers).
CAPACITY_BUDGET = 1.5e9
#: Finest resolution of a capacity, relative to the largest seam cost of the graph.
CAPACITY_STEPS = 1e6
#: Cost of a seam edge in a straight run while it stays, as a multiple of its appearance difference (module
#: docstring).  At 1.5 the straight seams' share of the seam edges falls by about half for every synthesizer, and
#: seam visibility rises by 0.04 at most; at 2.5 the Wang tiles' straight seams left grow more visible (Benchmarks,
#: "Straight seams weighed as the eye weighs them").
STRAIGHT_WEIGHT = 1.5


def recut_straight_seams(texels: np.ndarray, src: np.ndarray, wrap: bool, pinned: np.ndarray | None = None,
                         passes: int = PASSES, bridges: int = 0,
                         straight_weight: float = STRAIGHT_WEIGHT, band: int = BAND) -> np.ndarray:
    """``src [H, W]`` (flat exemplar indices into ``texels [eh, ew, d]``) with its straight seams re-cut (module
    docstring; ``bridges``: bridging patches also offered per run and pass, 0: none; ``straight_weight``: the
    cost of a straight seam edge that stays, per unit of its appearance difference; ``band``: the texels on
    either side of a run that may take a continuation); ``pinned [H, W]``
    (optional) texels keep their sources.  A pass after the first re-cuts only the runs near the texels the pass
    before changed."""
    eh, ew = texels.shape[:2]
    h, w = src.shape
    if min(h, w) < 2:
        return src
    pinned = np.zeros((h, w), bool) if pinned is None else pinned
    padded = edge_padded(texels)
    spectrum = ExemplarSpectrum(texels) if bridges else None
    active = np.ones((h, w), bool)
    for _ in range(passes):
        before = src
        edges = straight_edges(src, ew, wrap)
        weights = straight_weights(edges, straight_weight)
        for run_mask, axis in straight_runs(src, ew, wrap, pinned, active, edges):
            for group in apart_groups(run_mask, axis, wrap, band):
                for proposal in continuations(src, (eh, ew), wrap, group, axis, pinned, band):
                    src = expansion_move(texels, src, proposal, wrap, pinned, padded, weights)
        if bridges:
            edges = straight_edges(src, ew, wrap)
            weights = straight_weights(edges, straight_weight)
            runs = straight_runs(src, ew, wrap, pinned, active, edges)
            for proposal in bridging_proposals(spectrum, src, wrap, runs, pinned, bridges):
                src = expansion_move(texels, src, proposal, wrap, pinned, padded, weights)
        if np.array_equal(before, src):
            break
        active = _near(before != src, wrap, band)
    return src


def _near(changed: np.ndarray, wrap: bool, band: int) -> np.ndarray:
    """The texels within reach of a changed one: a run further away meets the same sources and the same
    proposals as in the pass before, and the same cut would come out of it again."""
    from scipy.ndimage import maximum_filter
    return maximum_filter(changed, size=2 * (band + 2) + 1, mode="wrap" if wrap else "constant")


def straight_runs(src: np.ndarray, ew: int, wrap: bool, pinned: np.ndarray, active: np.ndarray | None = None,
                  edges: tuple[np.ndarray, np.ndarray] | None = None) -> list[tuple[np.ndarray, int]]:
    """``(mask, axis)`` per direction: the seam edges in straight runs (``axis`` 0: ``across_columns`` edges in
    vertical runs; 1: ``across_rows`` edges in horizontal runs), leaving out edges between two pinned texels and,
    with ``active``, the runs that touch no active texel.  A run's length counts its pinned edges too, as the
    straight-seam measure does: a run that crosses a pinned ring (a cut across a Wang tile border) is as straight
    to the eye as one that does not, though only its free parts can be re-cut.  ``edges``: :func:`straight_edges`
    of ``src`` where already found."""
    vertical, horizontal = straight_edges(src, ew, wrap) if edges is None else edges
    runs = [(vertical & ~(pinned & np.roll(pinned, -1, axis=1)), 0),
            (horizontal & ~(pinned & np.roll(pinned, -1, axis=0)), 1)]
    return runs if active is None else [(_touching(mask, axis, active), axis) for mask, axis in runs]


def straight_edges(src: np.ndarray, ew: int, wrap: bool) -> tuple[np.ndarray, np.ndarray]:
    """The ``across_columns`` seam edges of ``src`` in vertical runs and its ``across_rows`` seam edges in
    horizontal runs of :data:`~.visibility.STRAIGHT_RUN` or more."""
    rows, cols = np.divmod(src, ew)
    across_columns, across_rows = seam_masks(rows, cols, wrap)
    return in_long_runs(across_columns, 0, STRAIGHT_RUN), in_long_runs(across_rows, 1, STRAIGHT_RUN)


def straight_weights(edges: tuple[np.ndarray, np.ndarray], weight: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Per texel (flat), what the seam edge to its right and the one below it cost, per unit of appearance
    difference, while they stay: ``weight`` on the ``edges`` of :func:`straight_edges`, 1 elsewhere (None where
    ``weight`` is 1)."""
    if weight == 1:
        return None
    return tuple(np.where(mask, weight, 1.0).ravel() for mask in edges)


def apart_groups(run_mask: np.ndarray, axis: int, wrap: bool, band: int = BAND) -> list[np.ndarray]:
    """The runs of ``run_mask`` (along ``axis``) split into groups whose bands do not overlap: within a group no two
    runs lie within ``2 * band`` texels of each other across their direction where they overlap along it.  In one
    proposal a band texel holds one run's continuation; where the bands of two runs overlap the later run's would
    replace the earlier one's.  The two seams of a sliver (a strip of a texel or two between two pieces, as k-coherence
    leaves them) are such a pair: the piece on the first side was then never offered across the sliver."""
    labels, n = run_labels(run_mask, axis)
    if n <= 1:
        return [run_mask] if n else []
    across_size = run_mask.shape[1 - axis]
    from scipy.ndimage import find_objects
    found = find_objects(labels)
    groups: list[list[int]] = []
    placed: list[list[tuple[int, int, int]]] = []   # per group: (across, first, stop) of its runs
    for index, box in enumerate(found, start=1):
        along, across = box[axis], box[1 - axis].start
        mine = (across, along.start, along.stop)
        for members, spans in zip(groups, placed):
            if not any(_bands_meet(mine, other, across_size, wrap, band) for other in spans):
                members.append(index)
                spans.append(mine)
                break
        else:
            groups.append([index])
            placed.append([mine])
    return [np.isin(labels, members) for members in groups]


def _bands_meet(one: tuple[int, int, int], other: tuple[int, int, int], across_size: int, wrap: bool,
                band: int) -> bool:
    """Whether the bands (``band`` texels on either side) of two runs ``(across, first, stop)`` overlap."""
    gap = abs(one[0] - other[0])
    if wrap:
        gap = min(gap, across_size - gap)
    return gap <= 2 * band and one[1] < other[2] and other[1] < one[2]


def _touching(run_mask: np.ndarray, axis: int, active: np.ndarray) -> np.ndarray:
    """The whole runs of ``run_mask`` (along ``axis``) with at least one edge on an ``active`` texel."""
    labels, n = run_labels(run_mask, axis)
    hit = np.zeros(n + 1, bool)
    hit[labels[run_mask & active]] = True
    hit[0] = False
    return hit[labels]


def continuations(src: np.ndarray, source_size: tuple[int, int], wrap: bool, run_mask: np.ndarray, axis: int,
                  pinned: np.ndarray, band: int = BAND) -> tuple[np.ndarray, np.ndarray]:
    """Per output texel, the continuation (flat exemplar index, -1: none) of the first and of the second side's
    source of the seam edges in ``run_mask`` whose band (``band`` texels on either side) holds it (a band ends at
    the output's border without ``wrap``, at the exemplar's border and at a pinned texel)."""
    eh, ew = source_size
    h, w = src.shape
    step = np.array([0, 1]) if axis == 0 else np.array([1, 0])
    first = np.argwhere(run_mask)
    out = []
    for side in (0, 1):
        origin = (first + side * step) % (h, w)
        source = np.stack(np.divmod(src[origin[:, 0], origin[:, 1]], ew), axis=1)
        proposal = np.full((h, w), -1, np.int64)
        for direction, offsets in ((-1, range(0, band)), (1, range(1, band + 1))):
            alive = np.ones(len(first), bool)
            for k in offsets:
                delta = direction * k * step
                at = first + delta
                if wrap:
                    at %= (h, w)
                else:
                    alive &= (at[:, 0] >= 0) & (at[:, 0] < h) & (at[:, 1] >= 0) & (at[:, 1] < w)
                    at = np.clip(at, 0, (h - 1, w - 1))
                alive &= ~pinned[at[:, 0], at[:, 1]]
                there = source + delta - side * step
                ok = alive & (there[:, 0] >= 0) & (there[:, 0] < eh) & (there[:, 1] >= 0) & (there[:, 1] < ew)
                proposal[at[ok, 0], at[ok, 1]] = there[ok, 0] * ew + there[ok, 1]
        out.append(proposal)
    return out[0], out[1]


def seam_cost(flat: np.ndarray, padded: np.ndarray, source_size: tuple[int, int], a: np.ndarray, b: np.ndarray,
              dy: int, dx: int) -> np.ndarray:
    """Seam cost of source ``a`` at an output texel and ``b`` at its neighbour ``(dy, dx)`` away: zero where ``b``
    continues ``a``, else half the squared appearance differences of each texel and the other's exemplar
    neighbour on that side (edge-clamped at the exemplar's border; ``padded``: :func:`.features.edge_padded`)."""
    return _pair_cost(_side(flat, padded, source_size, a, dy, dx), _side(flat, padded, source_size, b, -dy, -dx),
                      source_size[1], dy, dx)


def _side(flat, padded, source_size, labels, dy, dx):
    """``labels`` with their appearance and their exemplar neighbours ``(dy, dx)`` away: one side of a seam."""
    rows, cols = np.divmod(labels, source_size[1])
    return labels, flat[labels], beside(padded, source_size, rows, cols, dy, dx)


def _pair_cost(first, second, ew: int, dy: int, dx: int) -> np.ndarray:
    """:func:`seam_cost` from the two sides :func:`_side` gathered."""
    (a, a_self, a_beside), (b, b_self, b_beside) = first, second
    cost = 0.5 * (((a_beside - b_self) ** 2).sum(axis=-1) + ((b_beside - a_self) ** 2).sum(axis=-1))
    continues = (b - a == dy * ew + dx) & (b % ew - a % ew == dx)
    return np.where(continues, 0.0, cost)


def expansion_move(texels: np.ndarray, labels: np.ndarray, proposal: np.ndarray, wrap: bool,
                   pinned: np.ndarray, padded: np.ndarray | None = None,
                   keep_weights: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """``labels`` after the best binary choice, per texel, between its label and its ``proposal`` (-1: none):
    the minimum cut of the seam costs, kept only if it lowers them (``padded``: the exemplar's
    :func:`.features.edge_padded`, made here if not given).  ``keep_weights`` (optional, :func:`straight_weights`):
    per texel, the factor on the seam cost of its right and of its lower edge while both texels keep their labels."""
    eh, ew, d = texels.shape
    h, w = labels.shape
    flat = texels.reshape(-1, d)
    padded = edge_padded(texels) if padded is None else padded
    current, offered = labels.ravel(), proposal.ravel()
    free = (offered >= 0) & (offered != current) & ~pinned.ravel()
    if not free.any():
        return labels
    taken = np.where(free, offered, current)
    terms = [_edge_terms(flat, padded, (eh, ew), current, taken, free, s, t, dy, dx,
                         None if keep_weights is None else keep_weights[dy])
             for s, t, dy, dx in _edges(h, w, wrap)]
    s, t, keep_keep, keep_take, take_keep, take_take = (np.concatenate(parts) for parts in zip(*terms))
    choice = _min_cut(h * w, free, s, t, keep_keep, keep_take, take_keep, take_take)
    chosen = np.where(choice, taken, current)
    cost_now = keep_keep.sum()
    cost_then = np.where(choice[s], np.where(choice[t], take_take, take_keep),
                         np.where(choice[t], keep_take, keep_keep)).sum()
    return chosen.reshape(h, w) if cost_then < cost_now else labels


def _edges(h: int, w: int, wrap: bool):
    """``(s, t, dy, dx)`` for the right and the lower neighbour pairs (flat indices; wrap-around pairs with
    ``wrap``; none of a texel with itself)."""
    index = np.arange(h * w).reshape(h, w)
    for dy, dx in ((0, 1), (1, 0)):
        if wrap and (h, w)[1 - dy] > 1:
            yield index.ravel(), np.roll(index, (-dy, -dx), axis=(0, 1)).ravel(), dy, dx
        else:
            yield index[:h - dy, :w - dx].ravel(), index[dy:, dx:].ravel(), dy, dx


def _edge_terms(flat, padded, source_size, current, taken, free, s, t, dy, dx, keep_weight=None):
    """The edges touching a free texel, with their four seam costs (keep/take at ``s``, keep/take at ``t``; the
    keep/keep cost times ``keep_weight`` at ``s`` where given); each side is gathered once per label and shared
    by the two costs that use it."""
    touched = free[s] | free[t]
    s, t = s[touched], t[touched]
    first = [_side(flat, padded, source_size, labels[s], dy, dx) for labels in (current, taken)]
    second = [_side(flat, padded, source_size, labels[t], -dy, -dx) for labels in (current, taken)]
    keep_keep, keep_take, take_keep, take_take = (_pair_cost(a, b, source_size[1], dy, dx)
                                                  for a in first for b in second)
    if keep_weight is not None:
        keep_keep = keep_weight[s] * keep_keep
    return s, t, keep_keep, keep_take, take_keep, take_take


def _min_cut(n: int, free: np.ndarray, s, t, keep_keep, keep_take, take_keep, take_take) -> np.ndarray:
    """Per texel, whether it takes its proposal in the least-cost labelling of the pairwise costs (only free
    texels may; ``take_take`` lowered where needed to make the costs submodular), by a minimum s-t cut over the
    free texels, an edge to a fixed texel counting as a cost of the free one's choice."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow
    take_take = np.minimum(take_take, keep_take + take_keep - keep_keep)
    both, only_s, only_t = free[s] & free[t], free[s] & ~free[t], ~free[s] & free[t]
    # E(x_s, x_t) = kk + (tk - kk) x_s + (tt - tk) x_t + (kt + tk - kk - tt) (1 - x_s) x_t, with x = 1: take
    unary = (np.bincount(s[both | only_s], (take_keep - keep_keep)[both | only_s], n)
             + np.bincount(t[both], (take_take - take_keep)[both], n)
             + np.bincount(t[only_t], (keep_take - keep_keep)[only_t], n))
    nodes = np.flatnonzero(free)
    local = np.full(n, -1)
    local[nodes] = np.arange(len(nodes))
    unary = unary[nodes]
    pair = (keep_take + take_keep - keep_keep - take_take)[both]
    scale = CAPACITY_STEPS / max(float(np.abs(unary).max()), float(pair.max(initial=0)), 1e-30)
    scale *= min(1.0, CAPACITY_BUDGET / max((np.abs(unary).sum() + pair.sum()) * scale, 1.0))
    m = len(nodes)
    source, sink = m, m + 1
    ends_s, ends_t = local[s[both]], local[t[both]]
    capacity = np.concatenate([np.maximum(unary, 0), np.maximum(-unary, 0), pair, np.zeros(len(pair))])
    graph = csr_matrix((np.round(capacity * scale).astype(np.int32),
                        (np.concatenate([np.full(m, source), np.arange(m), ends_s, ends_t]),
                         np.concatenate([np.arange(m), np.full(m, sink), ends_t, ends_s]))), shape=(m + 2, m + 2))
    graph.sum_duplicates()
    flow = maximum_flow(graph, source, sink, method="dinic").flow
    residual = (graph - flow).tocsr()
    residual.data = (residual.data > 0).astype(np.int8)
    residual.eliminate_zeros()
    # the smallest sink side (the texels that still reach the sink): where keeping costs no more, a texel keeps
    reaching_sink = breadth_first_order(residual.T.tocsr(), sink, directed=True, return_predecessors=False)
    takes = np.zeros(n, bool)
    takes[nodes[reaching_sink[reaching_sink < m]]] = True
    return takes
