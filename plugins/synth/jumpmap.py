"""Jump-map synthesis (Zelinka & Garland 2002, 2004): a fast random walk over the exemplar.

The analysis is shared with k-coherence synthesis: textons of the exemplar's appearance vectors (:mod:`.textons`)
and the neighbourhood search every synthesizer uses (:func:`.search.similar_texels`, fast or exact).
The walk runs on OpenCL (``jumpmap.cl``, one work-item along a Hilbert curve or in scanline order) with a twin
in plain Python and NumPy that gives identical results from the same random numbers.
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from btforge import Param
from btforge.backend import get_backend
from btforge.buffers import CoordMap
from btforge.errors import BtforgeInputError

from .feather import feathered, records_mix
from .features import texel_features
from .scan_order import coherent_fraction, hilbert_order, pad_textons
from .search import ContentCache, content_key, similar_texels
from .synthesizer import MAX_NEIGHBORHOOD, check_params, declare_synthesizer, refine_params, refined, search_param
from .textons import DEFAULT_TEXTONS, Textons, normalise_features, texton_analysis

KERNELS = Path(__file__).with_name("jumpmap.cl")

MAX_JUMPS = 16
JUMP_PROBABILITY = 0.02   #: default mean jump rate (measured with BALANCE: 0.01-0.05, README)
COVERAGE = 1.0            #: default in-degree balance exponent of the jump choices
BALANCE = True            #: default: the walk leaves over-used exemplar cells (see the stage's 'balance')
BALANCE_CELL = 8          #: exemplar texels per side of a cell whose use the balanced jumps count
#: The default 'overuse' (a cell holding more than that x its fair share, plus one cell, is over-used): automatic
#: (:func:`automatic_overuse`), half the copies the output makes of each exemplar texel, at least 1.  Leaving cells at their fair share (1) brings RealRTI item2's grass in at 192 x 192
#: (SWD 3.02 -> 1.27 x the shuffled blocks), but where a 256 x 256 output copies a 128 x 128 exemplar four times it
#: breaks stones apart (0.92 -> 2.17); 2 keeps them (1.48, seeds 0-3) and still brings the grass in (2.60 -> 1.28).
AUTOMATIC_OVERUSE = 0
#: Default refinement windows: 12 x 12, so the coarsest of the two coarse scales matches 48-texel pieces (a
#: quarter of a 192-texel exemplar) whole; with 8 x 8 windows long fibres and large areas came out in short pieces.
REFINE_WINDOW = 12
#: Default refinement rounds at the finest scale: three, and :data:`COARSE_ROUNDS` at each coarser one.
REFINE_ROUNDS = 3
#: Default refinement rounds at each coarser scale: five (the other synthesizers two at every scale).  The walk's map
#: starts further from the exemplar's statistics than the others' blocks, and with the stronger occurrence term
#: below each coarse round moves it on: on the cuneiform tablet three rounds left smeared areas (seams 1.31, SWD
#: 1.73 x the shuffled blocks), five do not.  Five rounds at the finest scale as well (version 13) lowered seam
#: visibility by 0.04 at most and SWD by 0.11 at most (the procedural fibres), but cost a quarter of the output's time.
COARSE_ROUNDS = 5
#: Default weight of the refinement's occurrence term, twice the others': the walk copies its favourite exemplar
#: areas over and over, and at weight 1 the refinement kept much of that (evenness 0.65 on the tablet, 0.74 on the
#: icon crop).
REFINE_OCCURRENCE = 2.0
#: Passes of the refinement's re-cut of straight seams, one more than the shared default of two: 12 x 12 windows
#: leave more window sides in straight runs of 12, and a pass finds the runs the previous cuts have shortened or
#: joined (the third pass takes the straight share from 2.0 % to 1.7 % on the procedural bumps and from 2.1 % to
#: 1.3 % on the icon crop; more change little and cost about 0.2 s each there).
RECUT_PASSES = 3
#: The refinement's contrast weight where the output has more than :data:`.synthesizer.AUTO_AREA` x the exemplar's
#: texels (up to that the shared 16 holds).  The walk keeps to some exemplar areas, and the rounds that spread its
#: copies favour the flatter windows there: SWD over the shuffled blocks missed on the tablet at 128 (1.81), on
#: item4 and item6 (2.46, 1.86) and swung with the seed on stones (0.98-1.55, seeds 0-3).  At 8, on the 21 crops of
#: the synthesis bench (seeds 0-1), SWD falls on 17 (stones 1.20 -> 0.53, the tablet at 128 1.81 -> 1.47), seams
#: rise by up to 0.14 (the SynthRTI relief 1.01 -> 1.15), and the targets missed go from 9 to 6 of 84; over seeds
#: 0-3 SWD on stones stays within 0.48-0.57.  At 4 the targets missed were 7, at 16 6 with SWD higher on 9 crops.
LARGE_CONTRAST = 8.0
#: Polish rounds (8 x 8 windows, neither term) after the 12 x 12 rounds: two, one more than the shared default.  The
#: second moves more of the cuts the large windows left to where the content agrees: on 40 crops of the synthesis
#: bench (seeds 0-1) seam visibility falls by 0.02-0.03 at the medians and rises on none by more than 0.01, SWD and
#: evenness stay within the seeds' spread, and the cobbles' seams at 128 come to the target (1.34 -> 1.30).  The
#: synthesis step takes about 15 % longer (Benchmarks).
POLISH_ROUNDS = 2
#: Bridging pieces offered per straight run and re-cut pass, one fewer than the others' three: the measures stay
#: within 0.03 (the held-out procedural exemplar, the icon crop) and the jump map's re-cut takes less time.
BRIDGE_TRIES = 2

# The four directions a candidate can come from: the neighbour's offset from the pixel, and the step that
# continues the neighbour's source to the pixel (a coherent copy).  Ties go to the earlier direction.
NEIGHBOUR = np.array([[0, -1], [-1, 0], [0, 1], [1, 0]], np.int64)   # left, up, right, down
STEP = -NEIGHBOUR
# The 3 x 3 window (without its centre) over which candidates are compared, row-major.
WINDOW = np.array([[dy, dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx], np.int64)


@dataclasses.dataclass(frozen=True)
class JumpMap:
    """Per exemplar texel: up to J jump targets, their choice probabilities, and the chance of jumping at all.

    ``targets`` ``[N, J]`` int32 flat texel indices (-1: none), ``cumulative`` ``[N, J]`` cumulative choice
    probabilities (1 at the last real target), ``probability`` ``[N]`` the chance that a walk arriving at the
    texel jumps; ``distance`` ``[N, J]`` the neighbourhood distances (inf where missing).
    """

    height: int
    width: int
    textons: Textons
    targets: np.ndarray
    distance: np.ndarray
    cumulative: np.ndarray
    probability: np.ndarray


_jump_maps = ContentCache(4)


def cached_jump_map(features: np.ndarray, **params) -> JumpMap:
    """:func:`build_jump_map`, kept per exemplar content and params: another seed or size skips the analysis."""
    key = content_key(features, extra=("jumpmap", sorted(params.items())))
    return _jump_maps.get_or_make(key, lambda: build_jump_map(features, **params))


def build_jump_map(features: np.ndarray, *, jumps: int = 3, jump_probability: float = JUMP_PROBABILITY,
                   neighborhood: int = 5, textons: int = DEFAULT_TEXTONS, search: str = "fast",
                   coverage: float = COVERAGE,
                   engine: str = "opencl") -> JumpMap:
    """Analyse ``[H, W, D]`` features into a :class:`JumpMap`.

    Jump targets are the texels with the most similar ``neighborhood`` windows, at least ``neighborhood // 2 + 1``
    texels away (Chebyshev) and one texel inside the exemplar's border (so a step in any direction after a jump
    stays inside).  Probabilities follow Zelinka & Garland (2002): target j of a texel has weight
    ``exp(-d_j / d_ref)`` (``d_j`` its neighbourhood distance, ``d_ref`` the median distance of the best targets
    over the exemplar), so weights fall with distance; the choice probabilities are the weights normalised per
    source texel.  The jump rate of a texel is ``jump_probability`` times its total weight over the mean total
    (clipped to 1): the mean rate is ``jump_probability``, a texel with close matches jumps more often, one
    without never.  With ``coverage`` > 0 a target's choice weight (not the rate) is also divided by its
    in-degree ** ``coverage`` (how many texels list it), so texels that many others jump to are not landed on
    more than the rest: the walk uses more of the exemplar.
    """
    # The stage's params are bounded already; these guard direct callers (no targets would break the walk).
    if not 1 <= jumps <= MAX_JUMPS:
        raise BtforgeInputError("jumpmap param 'jumps'", f"expected an int in [1, {MAX_JUMPS}], found {jumps}",
                                "use e.g. 3 jump targets per texel")
    if not 0.0 <= jump_probability <= 1.0:
        raise BtforgeInputError("jumpmap param 'jump_probability'",
                                f"expected a value in [0, 1], found {jump_probability}",
                                "use e.g. 0.1: the walk jumps at about one step in ten")
    h, w, _ = features.shape
    scaled = normalise_features(features)
    tx = texton_analysis(scaled, min(textons, h * w), engine=engine)
    allowed = np.zeros((h, w), bool)
    allowed[1:-1, 1:-1] = True
    targets, distance = similar_texels(scaled, neighborhood, jumps, exclude=neighborhood // 2,
                                       allowed=allowed, search=search, device=engine)
    real = targets >= 0
    best = distance[:, 0][real[:, 0]]
    d_ref = float(np.median(best)) if best.size else 0.0
    if not d_ref > 0:
        d_ref = float(distance[real].mean()) if real.any() and distance[real].mean() > 0 else 1.0
    with np.errstate(over="ignore", invalid="ignore"):
        weight = np.where(real, np.exp(-np.where(real, distance, 0.0).astype(np.float64) / d_ref), 0.0)
    total = weight.sum(axis=1)
    if coverage > 0:
        # the choice (not the rate) also evens out how often each texel is landed on: in-degree ** -coverage
        indegree = np.bincount(targets[real], minlength=h * w)
        weight = weight * np.where(real, np.maximum(indegree[np.where(real, targets, 0)], 1.0) ** -coverage, 0.0)
    choice_total = weight.sum(axis=1)
    safe_total = np.where(choice_total > 0, choice_total, 1.0)
    # missing targets get 2 (never reached by a uniform draw); the last real target closes at exactly 1
    cumulative = np.where(real, np.minimum(np.cumsum(weight, axis=1) / safe_total[:, None], 1.0), 2.0)
    last = np.maximum(real.sum(axis=1) - 1, 0)
    cumulative[np.arange(len(last)), last] = np.where(choice_total > 0, 1.0, 2.0)
    mean_total = float(total.mean()) if total.size else 0.0
    probability = np.clip(jump_probability * total / mean_total, 0.0, 1.0) if mean_total > 0 else np.zeros_like(total)
    return JumpMap(h, w, tx, targets, distance, np.ascontiguousarray(cumulative, np.float32),
                   probability.astype(np.float32))


def _over_share(use: np.ndarray, jm: JumpMap, done: int, overuse: int) -> np.ndarray:
    """Twin of ``over_share``: uses beyond ``overuse`` x the fair share of ``done`` pixels plus one cell's worth."""
    area = BALANCE_CELL * BALANCE_CELL
    return (use - area) * (jm.height * jm.width) > overuse * done * area


def _cell_of(texel: np.ndarray, width: int) -> np.ndarray:
    return (texel // width) // BALANCE_CELL * -(-width // BALANCE_CELL) + (texel % width) // BALANCE_CELL


def automatic_overuse(exemplar_size: tuple[int, int], size: tuple[int, int]) -> int:
    """The ``overuse`` of :data:`AUTOMATIC_OVERUSE`: half the output's copies of each exemplar texel (its area
    over the exemplar's), rounded, at least 1.  The more often the walk must pass through every cell, the more
    room a cell needs before the walk is sent away from it, or the walk's pieces break into short runs."""
    copies = (size[0] * size[1]) / max(1, exemplar_size[0] * exemplar_size[1])
    return max(1, int(round(copies / 2)))


#: The orders the walk can visit the output's pixels in (param ``order``).
ORDERS = ("hilbert", "scanline")
#: Default visiting order: along a Hilbert curve (Zelinka & Garland 2004).  In scanline order every coherent run
#: continues down and to the right and jumps break it off there, so the walk copies short diagonal streaks; along the
#: curve a pixel's done neighbours lie on several sides, and the runs grow into patches.  On RealRTI item5 at 192 x
#: 192 the walk alone then holds the pale ground as well as the dark coat (SWD over the shuffled blocks 2.40 ->
#: 0.83, seams 1.74 -> 1.55, seed 0), and the refinement keeps it (2.71 -> 0.53 at seeds 0-1, Benchmarks).
ORDER = "hilbert"


def visiting_order(order: str, ho: int, wo: int) -> np.ndarray:
    """Flat output indices in the order the walk visits them (``order``: one of :data:`ORDERS`)."""
    if order == "hilbert":
        return hilbert_order(ho, wo)
    if order == "scanline":
        return np.arange(ho * wo, dtype=np.int32)
    raise BtforgeInputError("jumpmap param 'order'", f"expected one of {', '.join(ORDERS)}, found {order!r}",
                            "use order: hilbert (the default) or scanline (Zelinka & Garland's 2002 walk)")


def walk(jm: JumpMap, size: tuple[int, int], *, wrap: bool = False, seed: int = 0, balance: bool = BALANCE,
         overuse: int = AUTOMATIC_OVERUSE, order: str = ORDER, engine: str = "opencl") -> tuple[np.ndarray, dict]:
    """Synthesize ``[H, W, 2]`` int32 coordinates with the jump-map walk; returns them and counts (with the
    ``overuse`` used: :func:`automatic_overuse` where it is :data:`AUTOMATIC_OVERUSE`).

    The pixels are visited one by one in ``order`` (:func:`visiting_order`).  Each done 4-neighbour offers a
    candidate: its source continued by one texel towards the pixel (a coherent copy), replaced with the texel's
    jump probability by one of its jump targets, or forced to jump when the copy would leave the exemplar.  The
    candidate whose 3 x 3 neighbourhood differs least from the done neighbours (texton distances) wins.  With
    ``wrap`` the neighbours across the output's edges count too.
    """
    ho, wo = int(size[0]), int(size[1])
    if overuse == AUTOMATIC_OVERUSE:
        overuse = automatic_overuse((jm.height, jm.width), (ho, wo))
    visits = visiting_order(order, ho, wo)
    rng = np.random.default_rng(seed)
    uniform = rng.random((ho * wo, 4, 2), dtype=np.float32)
    fallback = rng.integers(0, jm.height * jm.width, ho * wo).astype(np.int32)
    # balance's escapes: random texels one inside the border, like jump targets (so a step stays inside)
    escape = ((rng.integers(1, max(2, jm.height - 1), ho * wo)) * jm.width
              + rng.integers(1, max(2, jm.width - 1), ho * wo)).astype(np.int32)
    run = walk_numpy if engine == "numpy" else walk_opencl
    src, flags = run(jm, ho, wo, wrap, visits, uniform, fallback, balance, escape, overuse)
    coords = np.stack(np.divmod(src.reshape(ho, wo), jm.width), axis=-1).astype(np.int32)
    return coords, {"jumps_taken": int((flags & 1).sum()), "forced_jumps": int((flags >> 1 & 1).sum()),
                    "overuse": int(overuse)}


def walk_opencl(jm: JumpMap, ho: int, wo: int, wrap: bool, visits: np.ndarray, uniform: np.ndarray,
                fallback: np.ndarray, balance: bool, escape: np.ndarray, overuse: int):
    """The walk on OpenCL (``jm_walk``, one work-item): flat sources and per-pixel jump flags."""
    backend = get_backend()
    options = (f"-DJUMPS={jm.targets.shape[1]}", f"-DOVERUSE={int(overuse)}")
    kernel = backend.kernel(KERNELS, "jm_walk", options)
    cl = backend.cl
    cw = -(-jm.width // BALANCE_CELL)
    src_dev = cl.Buffer(backend.context, cl.mem_flags.READ_WRITE, size=4 * ho * wo)
    flags_dev = cl.Buffer(backend.context, cl.mem_flags.READ_WRITE, size=ho * wo)
    # the device buffers are kept until the results are read back
    inputs = [backend.to_device(a) for a in (
        np.zeros(ho * wo, np.uint8), visits, uniform, fallback, np.ascontiguousarray(jm.targets, np.int32),
        jm.cumulative, jm.probability, jm.textons.labels.ravel().astype(np.int32), pad_textons(jm.textons.labels, 1),
        jm.textons.table, np.zeros(-(-jm.height // BALANCE_CELL) * cw, np.int32), escape)]
    done_dev, order_dev, uniform_dev, fallback_dev, targets_dev, cumulative_dev, probability_dev, tex_dev, \
        tex_pad_dev, table_dev, usage_dev, escape_dev = inputs
    kernel(backend.queue, (1,), None, src_dev, flags_dev, done_dev, order_dev, np.int32(len(visits)), np.int32(ho),
           np.int32(wo), np.int32(wrap), uniform_dev, fallback_dev, targets_dev, cumulative_dev, probability_dev,
           tex_dev, tex_pad_dev, np.int32(jm.height), np.int32(jm.width), table_dev, np.int32(jm.textons.count),
           np.int32(balance), usage_dev, np.int32(BALANCE_CELL), np.int32(cw), escape_dev)
    src = backend.from_device(src_dev, (ho * wo,), np.int32)
    flags = backend.from_device(flags_dev, (ho * wo,), np.uint8)
    del inputs
    return src, flags


class _Walk:
    """The state of :func:`walk_numpy`: the exemplar's tables as Python lists (scalar access is the walk's whole
    cost), the output so far and the use of every exemplar cell."""

    def __init__(self, jm: JumpMap, ho: int, wo: int, wrap: bool, uniform, balance: bool, escape, overuse: int):
        self.jm, self.ho, self.wo, self.wrap, self.balance, self.overuse = jm, ho, wo, wrap, balance, overuse
        self.he, self.we = jm.height, jm.width
        self.targets = jm.targets.tolist()
        self.cumulative = jm.cumulative.tolist()
        self.probability = jm.probability.tolist()
        self.tex = jm.textons.labels.ravel().tolist()
        self.tex_pad = pad_textons(jm.textons.labels, 1)
        self.table = jm.textons.table
        self.uniform, self.escape = uniform, escape
        self.src = [-1] * (ho * wo)
        self.usage = [0] * (-(-self.he // BALANCE_CELL) * -(-self.we // BALANCE_CELL))

    def neighbour(self, qy: int, qx: int) -> int:
        """Flat index of output pixel (qy, qx) if it is done (wrapped around a tiling output), else -1."""
        if self.wrap:
            qy, qx = qy % self.ho, qx % self.wo
        elif not (0 <= qy < self.ho and 0 <= qx < self.wo):
            return -1
        q = qy * self.wo + qx
        return q if self.src[q] >= 0 else -1

    def cell_use(self, texel: int) -> int:
        return self.usage[int(_cell_of(np.int64(texel), self.we))]

    def over(self, use: int, done: int) -> bool:
        return bool(_over_share(np.int64(use), self.jm, done, self.overuse))

    def pick(self, texel: int, u: float, escape: int, done: int) -> int:
        """Twin of ``pick_target``."""
        targets, cumulative = self.targets[texel], self.cumulative[texel]
        j = min(sum(u >= c for c in cumulative), len(targets) - 1)
        best = targets[j]
        if not self.balance or best < 0:
            return best
        best_use = self.cell_use(best)
        for i in range(1, len(targets)):
            c = targets[(j + i) % len(targets)]
            if c >= 0 and self.cell_use(c) < best_use:
                best, best_use = c, self.cell_use(c)
        return escape if self.over(best_use, done) else best

    def candidate(self, d: int, y: int, x: int, p: int, done: int) -> tuple[int, int]:
        """Twin of ``candidate``: the candidate from direction d and its flag."""
        q = self.neighbour(y + int(NEIGHBOUR[d, 0]), x + int(NEIGHBOUR[d, 1]))
        if q < 0:
            return -1, 0
        s, we, he = self.src[q], self.we, self.he
        sy, sx = s // we + int(STEP[d, 0]), s % we + int(STEP[d, 1])
        u0, u1 = (float(v) for v in self.uniform[p, d])
        escape = int(self.escape[p])
        if 0 <= sy < he and 0 <= sx < we:
            c = sy * we + sx
            if self.targets[c][0] >= 0 and (u0 < self.probability[c]
                                            or (self.balance and self.over(self.cell_use(c), done))):
                return self.pick(c, u1, escape, done), 1
            return c, 0
        f = self.pick(s, u1, escape, done)
        if f >= 0:
            return (f // we + int(STEP[d, 0])) * we + f % we + int(STEP[d, 1]), 3
        return min(max(sy, 0), he - 1) * we + min(max(sx, 0), we - 1), 2

    def best(self, cand: list[int], y: int, x: int) -> int:
        """Twin of ``best_candidate``: float32 sums over the window in row-major order."""
        cost = [np.float32(0)] * 4
        for oy, ox in WINDOW.tolist():
            q = self.neighbour(y + oy, x + ox)
            if q < 0:
                continue
            tq = self.tex[self.src[q]]
            for d, c in enumerate(cand):
                if c >= 0:
                    cost[d] = cost[d] + self.table[self.tex_pad[c // self.we + 1 + oy, c % self.we + 1 + ox], tq]
        best = -1
        for d, c in enumerate(cand):
            if c >= 0 and (best < 0 or cost[d] < cost[best]):
                best = d
        return best


def walk_numpy(jm: JumpMap, ho: int, wo: int, wrap: bool, visits: np.ndarray, uniform: np.ndarray,
               fallback: np.ndarray, balance: bool, escape: np.ndarray, overuse: int):
    """Twin of ``jm_walk``, one pixel at a time in the same order: flat sources and per-pixel jump flags."""
    state = _Walk(jm, ho, wo, wrap, uniform, balance, escape, overuse)
    flags = np.zeros(ho * wo, np.uint8)
    for done, p in enumerate(visits.tolist()):
        y, x = divmod(p, wo)
        picks = [state.candidate(d, y, x, p, done) for d in range(4)]
        cand = [c for c, _ in picks]
        best = state.best(cand, y, x)
        state.src[p] = int(fallback[p]) if best < 0 else cand[best]
        flags[p] = 0 if best < 0 else picks[best][1]
        if balance:
            state.usage[int(_cell_of(np.int64(state.src[p]), jm.width))] += 1
    return np.array(state.src, np.int32), flags


@declare_synthesizer(
    "synth.jumpmap", deprecated_names=("jumpmap",),
    version="30",  # 30: the refinement's balance term on by default where the output has at most 1.5 x the exemplar's texels (param appearance_balance, -1: automatic, 16 there); 29: straight seams whose re-cut bands overlap are re-cut in separate groups, so a sliver's far piece is offered across it; 28: seams cross-faded over 3 texels on either side (feather 3, was 1); 27: the walk follows a Hilbert curve by default (param order; scanline before); 26: linear exemplars (stacks, linear fits of light only) compared as a screen shows them, at 25 probe lights sRGB-encoded, 16 principal components; 25: sRGB PTM, SH and HSH exemplars feathered too, their records mixed as display values; 24: linear lrgb exemplars feathered too, through the rgb PTM of the same functions; 23: seams cross-faded over 1 texel on blendable exemplars (param feather); 22: param seam_weight (1 by default: the outputs are those of version 21); 21: two polish rounds by default (polish 2: seams lower on nearly every crop); 20: the refinement's contrast term at 8 by default where the output has more than 1.5 x the exemplar's texels (contrast -1); 19: one polish round by default (polish 1: seams lower on every crop measured); 18: the re-cut weighs a straight seam edge that stays 1.5 x its appearance difference (about half the straight seams); 17: param polish (final rounds of 8 x 8 windows without the occurrence and contrast terms, 0 by default); 16: the refinement's contrast term on by default where the exemplar is about as large as the output (contrast -1: automatic); 15: overuse automatic by default (half the copies per exemplar texel, at least 1; was 4); 14: 5 rounds at the coarse scales, 3 at the finest; 13: 5 rounds, occurrence 2, bridging pieces over straight seams; 12: 3 rounds of 12 x 12 refinement windows, further re-cut passes; 11: straight seams re-cut by minimum cuts, the refinement's candidate distances summed in a fixed order (OpenCL kernels); 10: refinement on by default (refine 2), coarse scales first; 9: refinement with an approximate window search; 3: fast self-join by graph nominees + coherence propagation; 4: in-degree balanced choices (coverage 1) and rate 0.05 by default; 5: usage-aware walk (balance) and rate 0.02; 6: the self-join seeded by a kd-tree; 7: the shared refinement; 8: refinement by a coherent vote, off by default (refine 0)
    seed_doc="random seed of the walk; the same seed gives the same result",
    params=[
        Param("jumps", "int", 3, "jump targets per exemplar texel", low=1, high=MAX_JUMPS),
        Param("jump_probability", "float", JUMP_PROBABILITY,
              "mean chance per step that the walk jumps instead of copying",
              low=0.0, high=1.0),
        Param("neighborhood", "int", 5, "odd window size of the neighbourhoods compared to find jump targets",
              low=3, high=MAX_NEIGHBORHOOD),
        Param("textons", "int", DEFAULT_TEXTONS, "texton (k-means cluster) count of the analysis", low=1, high=2048),
        search_param(),
        Param("coverage", "float", COVERAGE, "exponent of the in-degree balance of jump choices: a target's choice "
              "weight is divided by (how many texels jump to it) ** coverage (0: off)", low=0.0, high=2.0),
        Param("balance", "bool", BALANCE, "usage-aware walk: a copy from an exemplar cell (8 x 8 texels) the "
              "output already holds more than overuse x its fair share of (plus one cell's worth) jumps whatever the "
              "draw; a jump goes to the target whose cell is used least so far, or to a random texel when even "
              "that one is over-used (use counted after every pixel); false: Zelinka & Garland's walk"),
        Param("order", "choice", ORDER, "the order the walk visits the output's pixels in: hilbert (along a Hilbert "
              "curve, Zelinka & Garland 2004: patches) or scanline (Zelinka & Garland 2002: diagonal streaks)",
              choices=ORDERS),
        Param("overuse", "int", AUTOMATIC_OVERUSE, "with balance, the share (x the fair share) of an exemplar cell the "
              "output may hold before the walk leaves it (0: half the output's copies of each exemplar texel, at "
              "least 1: 1 for a 256 x 256 output from 192 x 192, 2 from 128 x 128); 1 spreads the walk over "
              "exemplar areas no neighbourhood leads to (RealRTI item2's grass at 192 x 192: SWD 3.02 -> 1.27 x "
              "the shuffled blocks) but breaks up stones where each texel is copied four times (128 x 128: 0.92 -> "
              "2.17; at 2: 1.48)", low=0, high=64),
        *refine_params(refine=REFINE_ROUNDS, occurrence=REFINE_OCCURRENCE, window=REFINE_WINDOW,
                       coarse_refine=COARSE_ROUNDS, large_weight=LARGE_CONTRAST, polish=POLISH_ROUNDS),
    ],
)
def jumpmap(ctx, exemplar, *, size, wrap, seed, jumps, jump_probability, neighborhood, textons, search,
            coverage, balance, order, overuse, refine, occurrence, contrast, appearance_balance, scales, window,
            coarse_refine, polish, seam_weight, feather):
    """Synthesize a larger texture with a jump map (Zelinka & Garland 2002); outputs a coordinate map.

    Analysis: for every exemplar texel, ``jumps`` texels with similar neighbourhoods (the shared search over
    the appearance vectors' windows, ``search`` fast or exact; texels near the texel itself are left out) with
    probabilities as in Zelinka & Garland: weights ``exp(-d / d_ref)`` falling with the neighbourhood distance
    ``d`` (``d_ref``: the exemplar's median best-target distance), normalised per source texel, and divided by
    each target's in-degree ** ``coverage`` so that much-listed texels are not over-used.  The jump rate
    (``jump_probability`` on average) is scaled per texel by its total weight: close matches jump more often.
    Synthesis: the output's pixels are visited one by one in ``order``.  Each continues the source of an already
    synthesized 4-neighbour by one texel (a coherent copy); with a probability that is higher where good jumps
    exist it jumps to one of that texel's targets instead, and it must jump where the copy would leave the
    exemplar.  Of the candidates from the done neighbours (with ``wrap`` also across the output's edges) the one
    whose 3 x 3 neighbourhood matches the pixels already synthesized best is taken.  Zelinka & Garland (2002)
    visit the pixels in scanline order (``order: scanline``): every copy then continues down and to the right,
    jumps break the runs off there, and the walk copies short diagonal streaks.  By default (``hilbert``) it
    follows a Hilbert curve, as in their 2004 paper: a pixel's done neighbours lie on several sides, so the copied
    pieces grow into patches (on the procedural exemplar at 64 -> 128 texels their 20 largest are 1.6 x as long
    as wide at the median instead of 3.9 x), and the walk keeps more of an exemplar with parts of different kinds
    (RealRTI item5 at 192 x 192: SWD over the shuffled blocks 2.40 -> 0.83 before the refinement).  The walk runs
    as one OpenCL work-item, since every pixel needs those before it.

    **Balance** (``balance``, on by default): the plain walk gets caught in pockets whose jumps land in the
    pocket again (on a 64 x 64 crop, one 8 x 8 cell held 27 x its fair share).
    With balance the walk counts the output's use of every 8 x 8 exemplar cell after each pixel; a copy
    from an over-used cell (more than ``overuse`` x its fair share of the pixels so far, plus one cell's worth)
    jumps whatever the draw, a jump goes to the least-used of the texel's targets, and where even that cell is
    over-used to a random texel.  By default ``overuse`` is half the output's copies of each exemplar texel, at
    least 1 (:func:`automatic_overuse`): a walk that must pass through every cell several times needs room in
    each before it is sent on, or its pieces break into short runs.  The defaults (rate 0.02, coverage 1,
    balance) scored best of those measured (README, Benchmarks).

    With ``wrap`` the output's last column and row continue into its first ones, so the result tiles.  There is
    no correction pass: the pixels beside an edge that are visited after those across it must agree with both
    sides, so the seam has fewer exact coherent copies than the interior; use ``synth.kcoherence`` when seams
    matter most.

    **Refinement** (``refine`` and ``coarse_refine`` rounds, ``occurrence`` weight, ``scales``, ``window``;
    :mod:`.refine`): the walk's map finally goes through the shared texture optimisation: five rounds at each of
    two coarser scales, then three at the finest, with 12 x 12 windows and an occurrence weight of 2 (the other
    synthesizers: two rounds of 8 x 8 windows at every scale, weight 1).  The walk's pieces have ragged edges
    (and, in scanline order, are diagonal streaks) and favour some exemplar areas.  The coarse rounds replace
    them with whole areas of the exemplar and, with the occurrence term, spread the copies over it; the fine rounds cut
    the seams along the content (seam visibility 1.12 instead of 2.74 on the held-out procedural exemplar, scanline order).  The
    larger windows span 48 texels at the coarsest scale, so long fibres and large areas are kept whole instead of
    cut into 32-texel pieces.  Their sides leave more straight seams of 12 texels, so the re-cut of straight
    seams runs :data:`RECUT_PASSES` passes instead of two, with bridging pieces as for the others.  Before it, a
    ``polish`` (two rounds by default) of 8 x 8 windows without the occurrence and contrast terms moves the cuts
    the 12 x 12 windows left to where the content agrees (the demo's coarse stucco: seams 1.33 -> 1.20 with one).
    The contrast term (``contrast``) weighs 16 where the output has at most 1.5 x the exemplar's texels, as for the
    others, and :data:`LARGE_CONTRAST` (8) where it has more: the rounds that spread the walk's copies otherwise
    drift towards the flatter windows of the areas it keeps to.  Where the output has at most 1.5 x the exemplar's
    texels, the balance term (``appearance_balance``) charges windows of appearance classes the output holds beyond
    their share of the exemplar (the tablet at 320: SWD over the shuffled blocks 1.51 -> 1.10).  ``refine: 0`` gives
    Zelinka & Garland's walk alone.

    Outputs
    -------
    coords : CoordMap
        ``[H, W, 2]`` (row, column) into the exemplar; replay it on any per-texel buffer with ``synth.materialize``.

    Notes
    -----
    textons, overuse (the share used), jump_targets (texels with at least one target), jumps_taken, forced_jumps,
    coherent_fraction, seconds_analysis, seconds_synthesis.
    """
    size = tuple(int(v) for v in size)
    check_params("synth.jumpmap", (exemplar.height, exemplar.width), size=size, neighborhood=neighborhood)
    if min(exemplar.height, exemplar.width) < neighborhood:
        raise BtforgeInputError("jumpmap 'exemplar'", f"expected at least {neighborhood} x {neighborhood} texels "
                                f"(the neighbourhood), found {exemplar.height} x {exemplar.width}",
                                "use a larger exemplar or a smaller neighborhood")
    start = time.perf_counter()
    features = texel_features(exemplar)
    jm = cached_jump_map(features, jumps=jumps, jump_probability=jump_probability,
                        neighborhood=neighborhood, textons=textons, search=search, coverage=coverage)
    analysed = time.perf_counter()
    coords, counts = walk(jm, size, wrap=wrap, seed=seed, balance=balance, overuse=overuse, order=order)
    ctx.note("overuse", counts["overuse"])
    ctx.note("textons", jm.textons.count)
    ctx.note("jump_targets", int((jm.targets[:, 0] >= 0).sum()))
    ctx.note("jumps_taken", counts["jumps_taken"])
    ctx.note("forced_jumps", counts["forced_jumps"])
    ctx.note("coherent_fraction", round(coherent_fraction(coords, wrap), 4))
    ctx.note("seconds_analysis", round(analysed - start, 3))
    ctx.note("seconds_synthesis", round(time.perf_counter() - analysed, 3))
    coords = CoordMap(coords, (exemplar.height, exemplar.width), wrap=wrap)
    coords = refined(ctx, features, coords, refine=refine, occurrence=occurrence, scales=scales, seed=seed,
                     window=window, recut_passes=RECUT_PASSES, coarse_refine=coarse_refine, bridges=BRIDGE_TRIES,
                     contrast=contrast, large_weight=LARGE_CONTRAST, polish=polish, seam_weight=seam_weight,
                     balance=appearance_balance)
    return {"coords": feathered(coords, feather, records_mix(exemplar), features)}


STAGES = [jumpmap]
