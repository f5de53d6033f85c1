"""Declaring a synthesizer: one helper gives every synthesizer the same port types, shared params and role.

A synthesizer takes an ``exemplar`` port of any per-texel buffer (a stack or any model: it is compared through
its appearance features) and outputs a ``coords`` :class:`~btforge.buffers.CoordMap`.  It shares the params
``size``, ``wrap`` and ``seed``, and declares ``role="synthesizer"``, which is how ``btforge bench synthesis``
finds it (a third-party plugin's synthesizer is benched without editing btforge)::

    @declare_synthesizer("mysynth", params=[Param("k", "int", 4, "...")])
    def mysynth(ctx, exemplar, *, size, wrap, seed, k):
        ...
        return {"coords": CoordMap(coords, (exemplar.height, exemplar.width), wrap=wrap)}
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from btforge import Param, declare_stage
from btforge.errors import BtforgeInputError

from .bridging import TRIES as BRIDGE_TRIES
from .feather import FEATHER, FEATHER_STEP, MAX_FEATHER
from .recut import PASSES as RECUT_PASSES
from .refine import APPEARANCE_CLASSES, POLISH_WINDOW, SEAM_WEIGHT
from .scan_order import level_sizes

MAX_K = 16
MAX_NEIGHBORHOOD = 9
SEARCHES = ("fast", "exact", "coherent")


def shared_params(*, size=(256, 256), seed_doc: str = "random seed: the same seed gives the same result") -> list[Param]:
    """The params every synthesizer has: output ``size``, ``wrap`` (tile seamlessly) and ``seed``."""
    return [Param("size", "ints", tuple(size), "output size [H, W] in texels", low=1, length=2),
            Param("wrap", "bool", False, "make the result tile seamlessly (periodic output boundary)"),
            Param("seed", "int", 0, seed_doc)]


def search_param() -> Param:
    """The ``search`` param of synthesizers whose analysis runs the shared neighbourhood search (:mod:`.search`)."""
    return Param("search", "choice", "fast", "exemplar neighbourhood search: fast (kd-tree seeds, then "
                 "coherence steps at full dimension on OpenCL; recall 0.91-0.98 at 192 x 192, 0.96 at 512 x 512), exact "
                 "(OpenCL brute force) or coherent (the same steps from random seeds; recall 0.96 at 192 x 192)",
                 choices=SEARCHES)


#: Default texture-optimisation rounds of the refinement (``synth.quilt`` and ``synth.kcoherence``; the jump map
#: declares 0).
REFINE = 2
#: Default weight of the refinement's occurrence term: at 1 an overused window costs as much as a random one, which
#: cuts seams where the plain optimisation would keep copying the same well-matched windows.
OCCURRENCE = 1.0
#: Default coarser scales the refinement goes through first: at 2 its 8 x 8 windows also span 16 and 32 texels, so
#: areas and copied blocks larger than a fine window are matched and cut as a whole (square patchworks of colour
#: areas are gone; seams drop on every exemplar measured).
SCALES = 2
#: The ``contrast`` and ``appearance_balance`` params' default: chosen per run by :func:`automatic_weight`.
AUTO = -1.0
#: The contrast weight an automatic ``contrast`` takes (k-coherence, the jump map; quilting declares 8) where the
#: exemplar is about as large as the output ...
AUTO_CONTRAST = 16.0
#: ... that is, where the output has at most this many times the exemplar's texels.  There the occurrence term lets
#: the optimisation leave exemplar areas out, and under a squared distance it leaves out the textured ones: at 256 x
#: 256 from 256 x 256 and 224 x 224, SWD over the shuffled blocks missed on the procedural exemplar (1.62-2.34) and
#: stones (1.84-2.62) for k-coherence or the jump map; with the term they pass (0.68-1.31).  Where the output is
#: larger (256 from 192: 1.78 x) every exemplar area must be used anyway, and for quilting the term traded one missed
#: target for another on 21 crops (Benchmarks), so there it is off unless a synthesizer declares a weight of its own
#: (k-coherence, with a second polish round: :data:`.kcoherence.LARGE_CONTRAST`; the jump map, whose walk drifts
#: more: :data:`.jumpmap.LARGE_CONTRAST`).
AUTO_AREA = 1.5
#: The balance weight an automatic ``appearance_balance`` takes where the exemplar is about as large as the output
#: (:data:`AUTO_AREA`), the weight the Wang tiles refine their set with; above that it is off.
#: There an output holds each exemplar area about once, and the rounds still drift towards the commonest appearance
#: (the contrast term stops a flatter window replacing a textured one, not a common one replacing a rare one).  On
#: 13 crops of 224-320 texels (seeds 0-1) SWD over the shuffled blocks falls on 33 of 39 outputs (k-coherence on
#: item2 at 256 1.56 -> 1.12 and the tablet 1.55 -> 1.35, the jump map on the tablet at 320 1.51 -> 1.10, which then
#: pass), seams move by -0.04 to +0.05.  Where the output is larger, the occurrence term already spreads it over
#: every area, and on the bumps (192 x 192) the term left k-coherence's straight seams over their target
#: (Benchmarks).
AUTO_BALANCE = 16.0
#: Default side in texels of the refinement's windows (a synthesizer may declare its own ``window`` param).
WINDOW = 8
#: Default final rounds of 8 x 8 windows without the occurrence and contrast terms (``polish``): one.  The terms
#: (and the jump map's 12 x 12 windows) settle which exemplar areas are used but leave some cuts where windows met;
#: the polish round moves them to where the content agrees.  With the re-cut's straight weight the straight seams
#: it leaves stay under 2 % of the seam edges wherever they were (without the weight they passed 2 % on two crops).
#: On 32 crops (Benchmarks) it lowers seam visibility on nearly every one (the jump map on all, a coarse plaster
#: 1.33 -> 1.20; quilting and k-coherence by less, their windows being 8 already) and moves SWD by 0.08 at most.
POLISH = 1


def refine_params(*, refine: int = REFINE, occurrence: float = OCCURRENCE, scales: int = SCALES,
                  window: int | None = None, coarse_refine: int | None = None, polish: int = POLISH,
                  auto_weight: float = AUTO_CONTRAST, large_weight: float = 0.0,
                  balance_weight: float = AUTO_BALANCE, seam_weight: float = SEAM_WEIGHT, feather: int = FEATHER,
                  feather_step: float = FEATHER_STEP) -> list[Param]:
    """The params of the shared refinement (:mod:`.refine`): ``refine`` rounds, the ``occurrence`` weight and the
    coarser ``scales`` refined first; with ``window`` also a ``window`` param (the windows' side, by default
    :data:`WINDOW` without the param), with ``coarse_refine`` also a ``coarse_refine`` param (the rounds at each
    coarser scale, by default as many as ``refine`` without the param); ``polish``: the default of the ``polish``
    param (final rounds of :data:`.refine.POLISH_WINDOW` windows without the terms);
    ``auto_weight``, ``large_weight``: the contrast weights the automatic ``contrast`` takes where the exemplar is
    about as large as the output and where the output is larger (:func:`automatic_weight`); ``balance_weight``: the
    weight the automatic ``appearance_balance`` takes where the exemplar is about as large as the output (off where
    the output is larger); ``seam_weight``: the
    default of the ``seam_weight`` param (the vote's seam cost against the windows' match cost); ``feather``,
    ``feather_step``: the default of the ``feather`` param and the threshold it feathers at (:func:`feather_param`)."""
    extra = [] if window is None else [
        Param("window", "int", window, "side in texels of the refinement's windows, at every scale: larger windows "
              "keep larger pieces of the exemplar whole (longer fibres, whole colour areas) and reach further at "
              "the coarse scales", low=4, high=32)]
    if coarse_refine is not None:
        extra.append(Param("coarse_refine", "int", coarse_refine, "rounds of the refinement at each coarser scale "
                           "(the finest runs 'refine' rounds): the coarse rounds set which exemplar areas are used "
                           "and how often, the fine ones cut the seams; cheap, since a coarse scale has a quarter "
                           "of the texels of the next", low=0, high=20))
    extra.append(Param("polish", "int", polish, "final rounds of the refinement at full resolution with "
                       f"{POLISH_WINDOW} x {POLISH_WINDOW} windows matched for their fit alone (no occurrence or "
                       "contrast term): the cuts the earlier rounds left where windows met move to where the content "
                       "agrees, while the exemplar areas used stay (0: none)", low=0, high=10))
    extra.append(seam_weight_param(seam_weight))
    extra.append(feather_param(feather, feather_step))
    side = WINDOW if window is None else window
    shown = f"{side} x {side}" if window is None else f"'window' x 'window' ({side} x {side} by default)"
    return [Param("refine", "int", refine, "rounds of texture optimisation the map goes through at the end: "
                  f"overlapping {shown} windows matched to the exemplar (with the occurrence term), whole windows kept "
                  "where they match best and cut where the appearance agrees, then corrections; seams follow the "
                  "content and every exemplar region gets used (0: off)",
                  low=0, high=20),
            Param("occurrence", "float", occurrence, "weight of the refinement's occurrence term: an exemplar window "
                  "whose texels are already used k times their fair share costs occurrence x (k - 1) x the mean "
                  "squared distance of two random windows (0: plain texture optimisation)", low=0.0),
            Param("contrast", "float", AUTO, "weight of the refinement's contrast term: an exemplar window with less "
                  "variation than the output window it would replace costs contrast x the shortfall, so the "
                  "optimisation does not drift towards the exemplar's flat areas; negative (the default): "
                  f"{auto_weight:g} where the output has at most {AUTO_AREA:g} x the exemplar's texels (an exemplar "
                  f"about as large as the output, where the drift shows), else {large_weight:g}; 0: off",
                  low=-1.0, high=1000.0),
            Param("appearance_balance", "float", AUTO, "weight of the refinement's balance term: an exemplar window "
                  f"of appearance classes ({APPEARANCE_CLASSES} k-means classes of the exemplar's texels) the output "
                  "already holds beyond their share of the exemplar costs more, so the optimisation does not drift "
                  "towards the exemplar's commonest areas and leave its sparser ones out; negative (the default): "
                  f"{balance_weight:g} where the output has at most {AUTO_AREA:g} x the exemplar's texels, else 0 "
                  "(a larger output uses every area anyway); 0: off", low=-1.0, high=1000.0),
            Param("scales", "int", scales, "coarser scales the refinement runs at first, each at half the resolution "
                  "of the next (2 x 2 averaged exemplar), while exemplar and output stay at least four windows "
                  f"({4 * side} texels{'' if window is None else ' by default'}) across there: structures larger "
                  "than a window (colour areas, the sides of copied blocks) are matched and cut as a whole (0: the "
                  "full resolution only)", low=0, high=6), *extra]


def seam_weight_param(default: float) -> Param:
    """The ``seam_weight`` param of a synthesizer that runs the shared refinement (its default ``default``)."""
    return Param("seam_weight", "float", default, "weight of the seam cost in the refinement's vote, against the "
                 "windows' match cost: heavier, the vote cuts where the two sides continue each other more closely "
                 "(less visible seams; the patch statistics may drift a little further from the exemplar's); 0: "
                 "the windows' match alone", low=0.0, high=1000.0)


def feather_param(default: int, step: float | str = FEATHER_STEP) -> Param:
    """The ``feather`` param of a synthesizer whose map's seams may be cross-faded (:mod:`.feather`) where their
    step is over ``step`` x the exemplar's own steps around them (a number, or the words for a factor that
    depends on the exemplar)."""
    factor = f"{step:g}" if isinstance(step, (int, float)) else step
    return Param("feather", "int", default, "the widest band, in texels on either side of a seam, that cross-fades "
                 "from one side's content to the other's, through the map's blend layer, where the step across the "
                 f"seam is over {factor} x the exemplar's own steps around its two sources: a cut between smooth areas "
                 "reads as a ramp, not a step; the band is this wide where the exemplar is flat around the two "
                 "sources and narrows to 1 where its steps there reach its mean step (grain is not blurred); on "
                 "exemplars whose records mix (a stack, PTM, SH and HSH coefficients; an lrgb PTM "
                 "replays as the rgb PTM of its functions where it blends; sRGB coefficients mix display values), "
                 "the others (Lafortune lobes, neural codes) keep a plain map (0: off)", low=0, high=MAX_FEATHER)


def automatic_weight(weight: float, output_shape, exemplar_shape, near_weight: float,
                     large_weight: float = 0.0) -> float:
    """A refinement term's weight: ``weight`` where it is >= 0, else ``near_weight`` where the output has at most
    :data:`AUTO_AREA` x the exemplar's texels (the exemplar about as large as the output) and ``large_weight`` where
    it has more (the automatic ``contrast`` and ``appearance_balance``)."""
    if weight >= 0:
        return weight
    return near_weight if area_ratio(output_shape, exemplar_shape) <= AUTO_AREA else large_weight


#: The copy budget (quilting's blocks, the pieces of k-coherence's start) where the output has at most
#: :data:`BUDGET_AREA` x the exemplar's texels (256 x 256 from 192 x 192: 1.78 x): 0.5.  With the one copy always allowed, 1.5 let a 192 x 192 crop's easiest area be copied 3.7 times, and
#: quilting's outputs of the paintings and of off-centre real crops were mostly their smoothest part (item5: brown
#: and black, little of its pale ground; SWD over the shuffled blocks 2.39, item1 2.09, the SynthRTI relief at (0,
#: 128) 2.35).  At 0.5 (1.9 copies at most) they are 0.50, 0.64 and 1.19 over seeds 0-1; over the 21 crops of 192 x
#: 192 the targets missed go from 4 to 1 (the bumps' straight seams stay), and at 1 item1, item5 and fibres miss
#: SWD (Benchmarks).
SMALL_OUTPUT_BUDGET = 0.5
#: ... the ratio of output to exemplar texels up to which :data:`SMALL_OUTPUT_BUDGET` holds.  A budget ``b`` under 1
#: stays above the running fair share only while that share is at most ``1 / (1 - b)`` copies (2 at 0.5); beyond,
#: every block is over it, the least-used alone are eligible, and the output of a grainy exemplar many times larger
#: lost its patch statistics (the fibres at 128: 1.09 -> 1.41).
BUDGET_AREA = 1.0 / (1.0 - SMALL_OUTPUT_BUDGET)


def auto_budget(budget: float, output_shape, exemplar_shape, large_budget: float) -> float:
    """``budget`` where it is >= 0, else :data:`SMALL_OUTPUT_BUDGET` where the output has at most
    :data:`BUDGET_AREA` x the exemplar's texels and ``large_budget`` (the synthesizer's own) where it has more."""
    if budget >= 0:
        return budget
    return SMALL_OUTPUT_BUDGET if area_ratio(output_shape, exemplar_shape) <= BUDGET_AREA else large_budget


def within_copy_budget(usage: np.ndarray, copied: int, exemplar_texels: int, area: int,
                       budget: float) -> np.ndarray | None:
    """Per candidate piece, whether its exemplar area (``area`` texels, ``usage`` of them copied so far) is copied at
    most ``budget`` x its fair share (the ``copied`` texels so far spread evenly over the exemplar's
    ``exemplar_texels``) plus one copy of the piece; None when ``budget`` is 0.  The least-used pieces are always
    within it: below a budget of 1 every piece can be over it, and a choice must still be made.

    A choice by seam or overlap cost alone favours the pieces that continue each other best, the plain ground of an
    exemplar, and its sparse features never appear; the budget moves the choice on once the ground has had its
    share (the occurrence idea of Kaspar et al. 2015, applied as the pieces are laid)."""
    if budget <= 0:
        return None
    fair = area * copied / exemplar_texels
    return usage <= max(budget * fair + area, usage.min())


def area_ratio(output_shape, exemplar_shape) -> float:
    """How many times the exemplar's texels the output has (``shape``: rows, columns first)."""
    return (output_shape[0] * output_shape[1]) / (exemplar_shape[0] * exemplar_shape[1])


def refined(ctx, features, coords, *, refine: int, occurrence: float, scales: int, seed: int,
            window: int = WINDOW, recut_passes: int = RECUT_PASSES, bridges: int = BRIDGE_TRIES,
            coarse_refine: int | None = None, contrast: float = AUTO, auto_weight: float = AUTO_CONTRAST,
            large_weight: float = 0.0, polish: int = POLISH, seam_weight: float = SEAM_WEIGHT,
            balance: float = AUTO, balance_weight: float = AUTO_BALANCE, coarse_keep: float = 0.0):
    """``coords`` through the shared refinement (:func:`.refine.refine_map`, ``window`` x ``window`` windows,
    ``coarse_refine`` rounds at the coarser scales (by default ``refine``), its re-cut of straight seams
    ``recut_passes`` passes, with ``bridges`` bridging patches per run and pass; a negative ``contrast`` chosen by
    :func:`automatic_weight` with ``auto_weight`` and ``large_weight``; ``polish`` final rounds (:data:`POLISH` by default) of
    :data:`.refine.POLISH_WINDOW` windows without the terms); ``seam_weight``: the vote's seam cost weight; a negative
    ``balance`` chosen by :func:`automatic_weight` with ``balance_weight`` (0 on larger outputs); ``coarse_keep``:
    the share of the exemplar's appearance variance a coarser scale must keep to be refined (0: always); with its
    time, contrast and balance weights noted."""
    import time

    from .refine import refine_map
    shapes = coords.coords.shape[:2], features.shape[:2]
    contrast = automatic_weight(contrast, *shapes, auto_weight, large_weight)
    balance = automatic_weight(balance, *shapes, balance_weight)
    ctx.note("contrast", contrast)
    ctx.note("appearance_balance", balance)
    start = time.perf_counter()
    out = refine_map(features, coords, iterations=refine, occurrence=occurrence, seed=seed, scales=scales,
                     patch=window, recut_passes=recut_passes, bridges=bridges, coarse_iterations=coarse_refine,
                     contrast=contrast, polish=polish, seam_weight=seam_weight, balance=balance,
                     coarse_keep=coarse_keep)
    ctx.note("seconds_refinement", round(time.perf_counter() - start, 3))
    return out


def declare_synthesizer(name: str, *, params: Sequence[Param] = (), version: str = "1",
                        seed_doc: str | None = None, deprecated_names: Sequence[str] = ()) -> Callable:
    """:func:`~btforge.declare_stage` for a synthesizer: ``exemplar`` (PerTexel) in, ``coords`` (CoordMap) out,
    the :func:`shared_params` first, then ``params``, and ``role="synthesizer"``."""
    shared = shared_params(**({"seed_doc": seed_doc} if seed_doc else {}))
    return declare_stage(name, inputs={"exemplar": "PerTexel"}, outputs={"coords": "CoordMap"},
                         params=[*shared, *params], version=version, role="synthesizer",
                         deprecated_names=deprecated_names)


def check_params(stage: str, exemplar_size: tuple[int, int], *, size, neighborhood: int, k: int | None = None,
                 levels: int | None = None) -> None:
    """Raise :class:`BtforgeInputError` naming the parameter when a synthesis parameter cannot be used."""
    if neighborhood < 3 or neighborhood % 2 == 0 or neighborhood > MAX_NEIGHBORHOOD:
        raise BtforgeInputError(f"{stage} param 'neighborhood'",
                                f"expected an odd window size in [3, {MAX_NEIGHBORHOOD}], found {neighborhood}",
                                "use 3, 5, 7 or 9")
    if k is not None and not 1 <= k <= MAX_K:
        raise BtforgeInputError(f"{stage} param 'k'", f"expected an int in [1, {MAX_K}], found {k}",
                                "use e.g. 6: the coherent source and 5 similar texels")
    if len(size) != 2 or min(size) < 1:
        raise BtforgeInputError(f"{stage} param 'size'", f"expected [H, W] with both at least 1, found {list(size)}",
                                "give the output size as two positive ints, e.g. [256, 256]")
    if levels is None:
        return
    if levels < 1:
        raise BtforgeInputError(f"{stage} param 'levels'", f"expected at least 1, found {levels}",
                                "use 1 for a single-resolution synthesis, 3 for the usual pyramid")
    coarsest = level_sizes(*exemplar_size, levels)[-1]
    if min(coarsest) < neighborhood:
        raise BtforgeInputError(
            f"{stage} param 'levels'",
            f"{levels} levels shrink the {exemplar_size[0]} x {exemplar_size[1]} exemplar to "
            f"{coarsest[0]} x {coarsest[1]}, smaller than the {neighborhood} x {neighborhood} neighbourhood",
            "use fewer levels, a smaller neighbourhood or a larger exemplar")
