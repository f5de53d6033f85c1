"""Jump-map synthesis (Zelinka & Garland 2002): a fast random walk over the exemplar.

The analysis is shared with k-coherence synthesis: textons of the exemplar's appearance vectors (:mod:`.textons`)
and the neighbourhood search every synthesizer uses (:func:`.search.similar_texels`, fast or exact).
The walk runs on OpenCL (``jumpmap.cl``, one launch per anti-diagonal wavefront) with a NumPy twin that gives
identical results from the same random numbers.
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
from .device import LOCAL, round_up
from .scan_order import coherent_fraction, output_neighbours, pad_textons, wavefronts
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


def _pick(jm: JumpMap, texel: np.ndarray, u: np.ndarray, usage: np.ndarray | None, escape: np.ndarray | None,
          done: int, overuse: int) -> np.ndarray:
    """The jump target of each ``texel`` chosen by uniform ``u`` (-1 where the texel has none); with ``usage``
    (per exemplar cell) the first least-used of its targets from the drawn one on, cyclically (``pick_target``)."""
    n_jump = jm.targets.shape[1]
    j = (u[:, None] >= jm.cumulative[texel]).sum(axis=1)
    j = np.minimum(j, n_jump - 1)
    drawn = jm.targets[texel, j]
    if usage is None:
        return drawn
    order = (j[:, None] + np.arange(n_jump)[None]) % n_jump
    cand = jm.targets[texel[:, None], order]
    use = np.where(cand >= 0, usage[_cell_of(np.maximum(cand, 0), jm.width)], np.int64(1) << 40)
    pick = np.argmin(use, axis=1)
    rows = np.arange(len(texel))
    best = cand[rows, pick]
    over = _over_share(use[rows, pick], jm, done, overuse)
    return np.where(drawn >= 0, np.where(over, escape, best), drawn)


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


def walk(jm: JumpMap, size: tuple[int, int], *, wrap: bool = False, seed: int = 0, balance: bool = BALANCE,
         overuse: int = AUTOMATIC_OVERUSE, engine: str = "opencl") -> tuple[np.ndarray, dict]:
    """Synthesize ``[H, W, 2]`` int32 coordinates with the jump-map walk; returns them and counts (with the
    ``overuse`` used: :func:`automatic_overuse` where it is :data:`AUTOMATIC_OVERUSE`).

    Order: anti-diagonal wavefronts ``x + 2 y = t``.  Every pixel of a wavefront only needs pixels of earlier
    wavefronts (left, upper-left, upper, upper-right; with ``wrap`` also whatever is already done across the
    seams), so a wavefront is one launch (one vectorised step in the twin); without wrap the result is that of
    scanline order.  Each done 4-neighbour offers a candidate: its source continued by one texel towards the pixel
    (a coherent copy), replaced with the texel's jump probability by one of its jump targets, or forced to jump
    when the copy would leave the exemplar.  The candidate whose 3 x 3 neighbourhood differs least from the
    done neighbours (texton distances) wins.
    """
    ho, wo = int(size[0]), int(size[1])
    if overuse == AUTOMATIC_OVERUSE:
        overuse = automatic_overuse((jm.height, jm.width), (ho, wo))
    rng = np.random.default_rng(seed)
    uniform = rng.random((ho * wo, 4, 2), dtype=np.float32)
    fallback = rng.integers(0, jm.height * jm.width, ho * wo).astype(np.int32)
    # balance's escapes: random texels one inside the border, like jump targets (so a step stays inside)
    escape = ((rng.integers(1, max(2, jm.height - 1), ho * wo)) * jm.width
              + rng.integers(1, max(2, jm.width - 1), ho * wo)).astype(np.int32)
    if engine == "numpy":
        src, flags = walk_numpy(jm, ho, wo, wrap, uniform, fallback, balance, escape, overuse)
    else:
        src, flags = walk_opencl(jm, ho, wo, wrap, uniform, fallback, balance, escape, overuse)
    coords = np.stack(np.divmod(src.reshape(ho, wo), jm.width), axis=-1).astype(np.int32)
    return coords, {"jumps_taken": int((flags & 1).sum()), "forced_jumps": int((flags >> 1 & 1).sum()),
                    "overuse": int(overuse)}


def walk_opencl(jm: JumpMap, ho: int, wo: int, wrap: bool, uniform: np.ndarray, fallback: np.ndarray,
                balance: bool, escape: np.ndarray, overuse: int):
    """The walk on OpenCL (``jm_walk``, one launch per wavefront): flat sources and per-pixel jump flags."""
    backend = get_backend()
    jumps = jm.targets.shape[1]
    options = (f"-DJUMPS={jumps}", f"-DOVERUSE={int(overuse)}")
    kernel = backend.kernel(KERNELS, "jm_walk", options)
    count = backend.kernel(KERNELS, "jm_count", options)
    escape_dev = backend.to_device(escape)
    cl = backend.cl
    cw = -(-jm.width // BALANCE_CELL)
    usage_dev = backend.to_device(np.zeros(-(-jm.height // BALANCE_CELL) * cw, np.int32))
    src_dev = cl.Buffer(backend.context, cl.mem_flags.READ_WRITE, size=4 * ho * wo)
    flags_dev = cl.Buffer(backend.context, cl.mem_flags.READ_WRITE, size=ho * wo)
    # the device buffers must outlive the launches: set_args does not keep them alive
    inputs = [backend.to_device(a) for a in (
        uniform, fallback, np.ascontiguousarray(jm.targets, np.int32), jm.cumulative, jm.probability,
        jm.textons.labels.ravel().astype(np.int32), pad_textons(jm.textons.labels, 1), jm.textons.table)]
    uniform_dev, fallback_dev, targets_dev, cumulative_dev, probability_dev, tex_dev, tex_pad_dev, table_dev = inputs
    kernel.set_args(src_dev, flags_dev, np.int32(ho), np.int32(wo), np.int32(wrap), np.int32(0), np.int32(0),
                    np.int32(0), uniform_dev, fallback_dev, targets_dev, cumulative_dev, probability_dev, tex_dev,
                    tex_pad_dev, np.int32(jm.height), np.int32(jm.width), table_dev, np.int32(jm.textons.count),
                    np.int32(balance), usage_dev, np.int32(BALANCE_CELL), np.int32(cw), escape_dev, np.int32(0))
    count.set_args(src_dev, usage_dev, np.int32(wo), np.int32(0), np.int32(0), np.int32(0), np.int32(jm.width),
                   np.int32(BALANCE_CELL), np.int32(cw))
    done = 0
    for t, y0, ny in wavefronts(2, ho, wo):
        kernel.set_arg(5, np.int32(t))
        kernel.set_arg(6, np.int32(y0))
        kernel.set_arg(7, np.int32(ny))
        kernel.set_arg(24, np.int32(done))
        cl.enqueue_nd_range_kernel(backend.queue, kernel, (round_up(ny),), (LOCAL,))
        done += ny
        if balance:
            count.set_arg(3, np.int32(t))
            count.set_arg(4, np.int32(y0))
            count.set_arg(5, np.int32(ny))
            cl.enqueue_nd_range_kernel(backend.queue, count, (round_up(ny),), (LOCAL,))
    src = backend.from_device(src_dev, (ho * wo,), np.int32)
    flags = backend.from_device(flags_dev, (ho * wo,), np.uint8)
    del inputs, usage_dev, escape_dev
    return src, flags


def _output_neighbour(qy: np.ndarray, qx: np.ndarray, ho: int, wo: int, wrap: bool):
    """Flat index of output pixels (qy, qx) and whether they exist (see :func:`~.kcoherence.output_neighbours`)."""
    qy, qx, inside = output_neighbours(qy, qx, ho, wo, wrap)
    return qy * wo + qx, inside


def walk_numpy(jm: JumpMap, ho: int, wo: int, wrap: bool, uniform: np.ndarray, fallback: np.ndarray,
               balance: bool, escape: np.ndarray, overuse: int):
    """Twin of ``jm_walk``, vectorised over each wavefront: flat sources and per-pixel jump flags."""
    he, we = jm.height, jm.width
    tex = jm.textons.labels.ravel()
    tex_pad = pad_textons(jm.textons.labels, 1)
    table = jm.textons.table
    has_jump = jm.targets[:, 0] >= 0
    src = np.zeros(ho * wo, np.int64)
    flags = np.zeros(ho * wo, np.uint8)
    done = np.zeros(ho * wo, bool)
    usage = np.zeros(-(-he // BALANCE_CELL) * -(-we // BALANCE_CELL), np.int64) if balance else None
    n_done = 0
    for t, y0, ny in wavefronts(2, ho, wo):
        ys = np.arange(y0, y0 + ny)
        xs = t - 2 * ys
        p = ys * wo + xs
        n = len(p)
        cand = np.full((n, 4), -1, np.int64)
        jumped = np.zeros((n, 4), bool)
        forced = np.zeros((n, 4), bool)
        for d in range(4):
            q, inside = _output_neighbour(ys + NEIGHBOUR[d, 0], xs + NEIGHBOUR[d, 1], ho, wo, wrap)
            ok = inside & done[q]
            s = src[q]
            sy, sx = s // we + STEP[d, 0], s % we + STEP[d, 1]
            out = (sy < 0) | (sy >= he) | (sx < 0) | (sx >= we)
            u = uniform[p, d]
            # coherent copy, or a jump from the copied texel
            c = np.clip(sy, 0, he - 1) * we + np.clip(sx, 0, we - 1)
            jump = ~out & has_jump[c] & (u[:, 0] < jm.probability[c])
            if balance:  # an over-used cell is left by a jump whatever the draw
                jump |= ~out & has_jump[c] & _over_share(usage[_cell_of(c, we)], jm, n_done, overuse)
            c = np.where(jump, _pick(jm, c, u[:, 1], usage, escape[p], n_done, overuse), c)
            # forced: the copy leaves the exemplar, so jump from the source and step from the target
            f_target = _pick(jm, s, u[:, 1], usage, escape[p], n_done, overuse)
            f_ok = f_target >= 0
            fy = np.where(f_ok, f_target // we + STEP[d, 0], np.clip(sy, 0, he - 1))
            fx = np.where(f_ok, f_target % we + STEP[d, 1], np.clip(sx, 0, we - 1))
            c = np.where(out, fy * we + fx, c)
            cand[:, d] = np.where(ok, c, -1)
            jumped[:, d] = ok & (jump | (out & f_ok))
            forced[:, d] = ok & out
        # compare every candidate's 3 x 3 neighbourhood with the done neighbours
        valid = cand >= 0
        safe = np.where(valid, cand, 0)
        cy, cx = safe // we + 1, safe % we + 1
        cost = np.zeros((n, 4), np.float32)
        for oy, ox in WINDOW:
            q, inside = _output_neighbour(ys + oy, xs + ox, ho, wo, wrap)
            use = inside & done[q]
            term = table[tex_pad[cy + oy, cx + ox], tex[src[q]][:, None]]
            cost += np.where(use[:, None], term, np.float32(0))
        key = np.where(valid, cost, np.float32(np.inf))
        pick = np.argmin(key, axis=1)
        pick = np.where(np.isfinite(key.min(axis=1)), pick, np.argmax(valid, axis=1))
        rows = np.arange(n)
        some = valid.any(axis=1)
        src[p] = np.where(some, cand[rows, pick], fallback[p])
        flags[p] = np.where(some, jumped[rows, pick] * 1 + forced[rows, pick] * 2, 0)
        done[p] = True
        n_done += n
        if balance:
            np.add.at(usage, _cell_of(src[p], we), 1)
    return src.astype(np.int32), flags


@declare_synthesizer(
    "synth.jumpmap", deprecated_names=("jumpmap",),
    version="26",  # 26: linear exemplars (stacks, linear fits of light only) compared as a screen shows them, at 25 probe lights sRGB-encoded, 16 principal components; 25: sRGB PTM, SH and HSH exemplars feathered too, their records mixed as display values; 24: linear lrgb exemplars feathered too, through the rgb PTM of the same functions; 23: seams cross-faded over 1 texel on blendable exemplars (param feather); 22: param seam_weight (1 by default: the outputs are those of version 21); 21: two polish rounds by default (polish 2: seams lower on nearly every crop); 20: the refinement's contrast term at 8 by default where the output has more than 1.5 x the exemplar's texels (contrast -1); 19: one polish round by default (polish 1: seams lower on every crop measured); 18: the re-cut weighs a straight seam edge that stays 1.5 x its appearance difference (about half the straight seams); 17: param polish (final rounds of 8 x 8 windows without the occurrence and contrast terms, 0 by default); 16: the refinement's contrast term on by default where the exemplar is about as large as the output (contrast -1: automatic); 15: overuse automatic by default (half the copies per exemplar texel, at least 1; was 4); 14: 5 rounds at the coarse scales, 3 at the finest; 13: 5 rounds, occurrence 2, bridging pieces over straight seams; 12: 3 rounds of 12 x 12 refinement windows, further re-cut passes; 11: straight seams re-cut by minimum cuts, the refinement's candidate distances summed in a fixed order (OpenCL kernels); 10: refinement on by default (refine 2), coarse scales first; 9: refinement with an approximate window search; 3: fast self-join by graph nominees + coherence propagation; 4: in-degree balanced choices (coverage 1) and rate 0.05 by default; 5: usage-aware walk (balance) and rate 0.02; 6: the self-join seeded by a kd-tree; 7: the shared refinement; 8: refinement by a coherent vote, off by default (refine 0)
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
              "that one is over-used (use counted after every wavefront); false: Zelinka & Garland's walk"),
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
            coverage, balance, overuse, refine, occurrence, contrast, scales, window, coarse_refine, polish,
            seam_weight, feather):
    """Synthesize a larger texture with a jump map (Zelinka & Garland 2002); outputs a coordinate map.

    Analysis: for every exemplar texel, ``jumps`` texels with similar neighbourhoods (the shared search over
    the appearance vectors' windows, ``search`` fast or exact; texels near the texel itself are left out) with
    probabilities as in Zelinka & Garland: weights ``exp(-d / d_ref)`` falling with the neighbourhood distance
    ``d`` (``d_ref``: the exemplar's median best-target distance), normalised per source texel, and divided by
    each target's in-degree ** ``coverage`` so that much-listed texels are not over-used.  The jump rate
    (``jump_probability`` on average) is scaled per texel by its total weight: close matches jump more often.
    Synthesis: each output pixel continues the source of its left or upper neighbour by one texel
    (a coherent copy); with a probability that is higher where good jumps exist it jumps to one of that
    texel's targets instead, and it must jump where the copy would leave the exemplar.  Of the candidates
    from the left and upper neighbours (and, with ``wrap``, the right and lower ones across the seam) the one
    whose 3 x 3 neighbourhood matches the pixels already synthesized best is taken.  Pixels are visited in
    anti-diagonal wavefronts ``x + 2 y = t``, one OpenCL launch each (scanline-equivalent without wrap).

    **Balance** (``balance``, on by default): the plain walk drifts right and down and gets caught in pockets
    whose forced jumps land in the pocket again (on a 64 x 64 crop, one 8 x 8 cell held 27 x its fair share).
    With balance the walk counts the output's use of every 8 x 8 exemplar cell after each wavefront; a copy
    from an over-used cell (more than ``overuse`` x its fair share of the pixels so far, plus one cell's worth)
    jumps whatever the draw, a jump goes to the least-used of the texel's targets, and where even that cell is
    over-used to a random texel.  By default ``overuse`` is half the output's copies of each exemplar texel, at
    least 1 (:func:`automatic_overuse`): a walk that must pass through every cell several times needs room in
    each before it is sent on, or its pieces break into short runs.  The defaults (rate 0.02, coverage 1,
    balance) scored best of those measured (README, Benchmarks).

    With ``wrap`` the output's last column and row continue into its first ones, so the result tiles.  There is
    no correction pass: the closing row and column must agree with both sides, so the seam has fewer exact
    coherent copies than the interior (the closing row more visibly than the closing column); use
    ``synth.kcoherence`` when seams matter most.

    **Refinement** (``refine`` and ``coarse_refine`` rounds, ``occurrence`` weight, ``scales``, ``window``;
    :mod:`.refine`): the walk's map finally goes through the shared texture optimisation: five rounds at each of
    two coarser scales, then three at the finest, with 12 x 12 windows and an occurrence weight of 2 (the other
    synthesizers: two rounds of 8 x 8 windows at every scale, weight 1).  The walk copies short diagonal runs,
    which the eye reads as streaks, and favours some exemplar areas.  The coarse rounds replace the runs with
    whole areas of the exemplar and, with the occurrence term, spread the copies over it; the fine rounds cut
    the seams along the content (seam visibility 1.12 instead of 2.74 on the held-out procedural exemplar).  The
    larger windows span 48 texels at the coarsest scale, so long fibres and large areas are kept whole instead of
    cut into 32-texel pieces.  Their sides leave more straight seams of 12 texels, so the re-cut of straight
    seams runs :data:`RECUT_PASSES` passes instead of two, with bridging pieces as for the others.  Before it, a
    ``polish`` (two rounds by default) of 8 x 8 windows without the occurrence and contrast terms moves the cuts
    the 12 x 12 windows left to where the content agrees (the demo's coarse stucco: seams 1.33 -> 1.20 with one).
    The contrast term (``contrast``) weighs 16 where the output has at most 1.5 x the exemplar's texels, as for the
    others, and :data:`LARGE_CONTRAST` (8) where it has more: the rounds that spread the walk's copies otherwise
    drift towards the flatter windows of the areas it keeps to.  ``refine: 0`` gives Zelinka & Garland's walk alone.

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
    coords, counts = walk(jm, size, wrap=wrap, seed=seed, balance=balance, overuse=overuse)
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
                     contrast=contrast, large_weight=LARGE_CONTRAST, polish=polish, seam_weight=seam_weight)
    return {"coords": feathered(coords, feather, records_mix(exemplar), features)}


STAGES = [jumpmap]
