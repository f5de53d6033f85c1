"""Picking views and lights of a stack by index or by name.

A light is named by its image name (``stack.names``) or, like a view, by its angles in the Bonn UBO spelling:
``tl45_pl120`` for a light at 45 degrees from the zenith and azimuth 120, ``tv30_pv90`` for a view.  Angles match
a direction to within :data:`ANGLE_TOLERANCE_DEG`, so names read off a UBO file listing pick the right sample.
"""
from __future__ import annotations

import math
import re
from typing import Any, Sequence

import numpy as np

from btforge.buffers import SampleStack
from btforge.errors import BtforgeInputError

ANGLE_TOLERANCE_DEG = 0.75  # names round to whole degrees: up to 0.5 in each angle
_ANGLES = {"light": re.compile(r"^tl(?P<t>[+-]?\d+(?:\.\d*)?)_pl(?P<p>[+-]?\d+(?:\.\d*)?)$"),
           "view": re.compile(r"^tv(?P<t>[+-]?\d+(?:\.\d*)?)_pv(?P<p>[+-]?\d+(?:\.\d*)?)$")}


def check_selection(value: Any, where: str) -> None:
    """Refuse a selection that is not a list of non-negative indices and non-empty names (before a run)."""
    if not isinstance(value, (list, tuple)):
        raise BtforgeInputError(where, f"expected a list of indices or names, found {value!r}",
                                "e.g. [0, 2] or ['tv30_pv90'], or [] for all")
    bad = [v for v in value if isinstance(v, bool) or not (isinstance(v, int) and v >= 0 or isinstance(v, str) and v)]
    if bad:
        raise BtforgeInputError(where, f"expected indices >= 0 or names, found {bad[0]!r}",
                                "give 0-based indices or names such as 'light_003.jpg', 'tl45_pl120', 'tv30_pv90'")
    seen = set()
    for item in value:
        if item in seen:
            raise BtforgeInputError(where, f"names {item!r} twice", "list every view or light once")
        seen.add(item)


def angle_label(direction: np.ndarray, role: str) -> str:
    """``tl45_pl120`` / ``tv30_pv90`` (degrees, rounded) for a unit direction."""
    theta = math.degrees(math.acos(max(-1.0, min(1.0, float(direction[2])))))
    phi = math.degrees(math.atan2(float(direction[1]), float(direction[0]))) % 360.0
    t, p = ("tl", "pl") if role == "light" else ("tv", "pv")
    return f"{t}{theta:.0f}_{p}{phi:.0f}"


def _by_angles(match: re.Match, directions: np.ndarray) -> list[int]:
    theta, phi = math.radians(float(match["t"])), math.radians(float(match["p"]))
    target = np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)])
    cos_angle = np.clip(directions.astype(np.float64) @ target, -1.0, 1.0)
    return [int(i) for i in np.flatnonzero(np.degrees(np.arccos(cos_angle)) <= ANGLE_TOLERANCE_DEG)]


def resolve(items: Sequence[int | str], directions: np.ndarray, names: Sequence[str], role: str) -> list[int]:
    """Indices of ``items`` among ``directions`` (all when ``items`` is empty); every problem reported at once."""
    count = len(directions)
    if not items:
        return list(range(count))
    indices, problems = [], []
    for item in items:
        if isinstance(item, int):
            if item >= count:
                problems.append(f"{role} index {item} is out of range (the stack has {count} {role}s, 0..{count - 1})")
            else:
                indices.append(item)
            continue
        if item in names:
            indices.append(list(names).index(item))
            continue
        match = _ANGLES[role].match(item)
        found = _by_angles(match, directions) if match else []
        if len(found) == 1:
            indices.append(found[0])
        elif len(found) > 1:
            problems.append(f"{item!r} matches {role}s {found} (within {ANGLE_TOLERANCE_DEG} degrees)")
        else:
            known = list(names[:3]) or [angle_label(d, role) for d in directions[:3]]
            problems.append(f"no {role} is named {item!r} (names look like {', '.join(map(repr, known))}"
                            f"{', ...' if count > 3 else ''})")
    if problems:
        raise BtforgeInputError(f"stackio.select '{role}s'", "; ".join(problems),
                                f"indices are 0-based; names are image names or angles like "
                                f"{'tl45_pl120' if role == 'light' else 'tv30_pv90'} (degrees)")
    if len(set(indices)) != len(indices):
        raise BtforgeInputError(f"stackio.select '{role}s'", f"selects the same {role} twice: {indices}",
                                f"list every {role} once")
    return indices


def select(stack: SampleStack, views: Sequence[int | str] = (), lights: Sequence[int | str] = ()) -> SampleStack:
    """The stack restricted to ``views`` and ``lights`` in the order given (all of an empty list)."""
    view_index = resolve(views, stack.views, (), "view")
    light_index = resolve(lights, stack.lights, stack.names, "light")
    samples = stack.take(view_index, light_index) if (views or lights) else stack.in_memory().samples
    names = tuple(stack.names[i] for i in light_index) if stack.names else ()
    return SampleStack(samples, stack.lights[light_index], stack.views[view_index], stack.channels, stack.encoding,
                       names)
