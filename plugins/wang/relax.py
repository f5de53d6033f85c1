"""Seam relaxation: a texel-level refinement of a canvas of exemplar coordinates after graph-cut filling.

Each movable texel may keep its exemplar texel or take the *continuation* of one of its four neighbours' (the
texel that neighbour's patch would have put there), so seams move by one texel at a time and small islands
vanish; no new content is introduced.  The energy is the filling's own seam cost (:func:`synthesis.pixel_errors`):
for neighbours ``p``, ``q = p + step`` with sources ``a``, ``b``, zero when ``b = a + step`` (they continue each
other) and otherwise ``(|F(a + step) - F(b)| + |F(a) - F(b - step)|) / 2``.  Texels are updated in a checkerboard
(iterated conditional modes): the texels of one colour have no neighbour of their own colour, so each takes its
best candidate given the other colour, and the total energy never rises.
"""
from __future__ import annotations

import numpy as np

STEPS = ((0, 1), (0, -1), (1, 0), (-1, 0))
SWEEPS = 6   # checkerboard sweeps (each: both colours); later sweeps rarely change anything


def pair_cost(feats: np.ndarray, a: np.ndarray, b: np.ndarray, step) -> np.ndarray:
    """Seam cost between texels with sources ``a [..., 2]`` and ``b [..., 2]``, ``b`` one ``step`` after ``a``
    in the canvas (``inf`` where either source is unfilled)."""
    limit = np.array(feats.shape[:2]) - 1
    step = np.asarray(step)
    continuous = np.all(b == a + step, axis=-1)
    ahead, behind = np.clip(a + step, 0, limit), np.clip(b - step, 0, limit)
    fa, fb = np.clip(a, 0, limit), np.clip(b, 0, limit)
    def at(where):   # float64: squared distances of float32 features may overflow float32
        return feats[where[..., 0], where[..., 1]].astype(np.float64)
    cost = 0.5 * (np.linalg.norm(at(ahead) - at(fb), axis=-1) + np.linalg.norm(at(fa) - at(behind), axis=-1))
    cost = np.where(continuous, 0.0, cost)
    return np.where((a[..., 0] < 0) | (b[..., 0] < 0), np.inf, cost)


def _neighbours(coords: np.ndarray) -> list[np.ndarray]:
    """Per step, the source of each texel's neighbour in that direction (``-1`` beyond the canvas)."""
    h, w = coords.shape[:2]
    padded = np.full((h + 2, w + 2, 2), -1, coords.dtype)
    padded[1:-1, 1:-1] = coords
    return [padded[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] for dy, dx in STEPS]


def texel_energy(feats: np.ndarray, candidate: np.ndarray, neighbours) -> np.ndarray:
    """Summed seam cost ``[n]`` of texels taking ``candidate [n, 2]`` against their neighbours' sources
    (``neighbours``: per step ``[n, 2]``, ``-1`` where there is none)."""
    total = np.zeros(len(candidate))
    for step, other in zip(STEPS, neighbours):
        present = other[:, 0] >= 0
        total += np.where(present, pair_cost(feats, candidate, other, step), 0.0)
    return total


def candidates(own: np.ndarray, neighbours, source_size) -> list[np.ndarray]:
    """The texels' own sources ``[n, 2]`` and their neighbours' continuations (``-1`` where they leave the
    exemplar or there is no neighbour)."""
    out = [own]
    for step, other in zip(STEPS, neighbours):
        cont = other - np.array(step, own.dtype)
        inside = (other[:, 0] >= 0) & (cont >= 0).all(-1) & (cont[:, 0] < source_size[0]) & \
                 (cont[:, 1] < source_size[1])
        out.append(np.where(inside[:, None], cont, -1))
    return out


def _on_seams(coords: np.ndarray, neighbours) -> np.ndarray:
    """Texels with at least one neighbour that does not continue them: only those can lower their energy."""
    seam = np.zeros(coords.shape[:2], bool)
    for step, other in zip(STEPS, neighbours):
        seam |= (other[..., 0] >= 0) & np.any(other != coords + np.array(step, coords.dtype), axis=-1)
    return seam


def relax_seams(coords: np.ndarray, feats: np.ndarray, movable: np.ndarray, sweeps: int = SWEEPS) -> np.ndarray:
    """``coords [h, w, 2]`` with its ``movable`` texels relaxed (module docstring); the input is not changed."""
    coords = coords.copy()
    h, w = coords.shape[:2]
    colour = (np.add.outer(np.arange(h), np.arange(w)) % 2).astype(bool)
    for _ in range(sweeps):
        changed = 0
        for parity in (False, True):
            neighbours = _neighbours(coords)
            turn = movable & (colour == parity) & (coords[..., 0] >= 0) & _on_seams(coords, neighbours)
            rows, cols = np.nonzero(turn)
            if len(rows) == 0:
                continue
            around = [n[rows, cols] for n in neighbours]
            options = candidates(coords[rows, cols], around, feats.shape[:2])
            energies = np.stack([np.where(o[:, 0] >= 0, texel_energy(feats, o, around), np.inf) for o in options])
            best = energies.argmin(0)
            # keep the present source on ties, so a sweep only moves a texel when that lowers the energy
            move = energies[best, np.arange(len(rows))] < energies[0] - 1e-9
            if move.any():
                chosen = np.stack(options)[best, np.arange(len(rows))]
                coords[rows[move], cols[move]] = chosen[move]
                changed += int(move.sum())
        if changed == 0:
            break
    return coords
