"""The Levenberg-Marquardt fit of Lafortune lobes to one texel's samples, in NumPy: the twin of the fit kernel in
``lafortune.cl`` (which takes the constants below as build options, so the two cannot drift apart).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

EXPONENT_MIN = 1.0
EXPONENT_MAX = 1000.0
P_MAX = math.log(EXPONENT_MAX)
LOBE_CAP = 10.0          # the first lobe's peak over all directions <= LOBE_CAP x the texel's brightest sample,
LATER_CAP = 2.0          # ... a later lobe's <= LATER_CAP x (allowed 10x, residual lobes spiked between lights)
CAP_DROP = math.log(LOBE_CAP / LATER_CAP)
T_CAP = 20.0             # numerical guard: n ln(base) is clamped here (the cap above normally binds first)
B_MIN = 1e-30            # bases at or below this count as 0
LAM0, LAM_MIN, LAM_MAX = 1e-3, 1e-7, 1e7
NU0 = 2.0                # a rejected step multiplies lambda by nu, and nu by 2 (reset to NU0 on acceptance)
LAM_DEC = 1e-4           # damping of the Gauss-Newton step whose predicted gain (the Newton decrement) ...
FTOL = 1e-3              # ... is at most FTOL x cost + ETOL x sum(y^2): converged; so is an accepted step that
GTOL = 1e-4              # ... gains at most GTOL x cost + ETOL x sum(y^2)
ETOL = 1e-9
ATOL = 1e-12             # ... or when cost <= ATOL x sum(y^2) (an exact fit)
D_FLOOR = 1e-9           # Marquardt scaling floor relative to the largest diagonal entry
W_FLOOR = 1e-3           # a new lobe starts with at least this x brightest sample as its peak
# Initial lobe shapes: C = w^(1/n) * d with max_j |d_j| = 1, so the lobe's peak is w.
CANDIDATE_DIRS = np.array([[-1.0, -1.0, 1.0],   # mirror lobe: base = u . reflect(v) (specular)
                           [1.0, 1.0, 1.0],     # retro lobe: base = u . v
                           [0.0, 0.0, 1.0]])    # normal lobe: base = uz vz (shaped diffuse)
# 1, 1.5, 2, 3, 4, 6, ... 768 (steps of x1.33 and x1.5; coarser grids strand LM): every power of a base is a
# square of the one two rungs below, so scoring the grid needs no exp or log.
CANDIDATE_EXPONENTS = np.array([m * 2.0 ** e for e in range(10) for m in (1.0, 1.5)])
DEFAULT_ITERATIONS = 100
N_STARTS = 2            # the first lobe is fitted from this many start shapes (the best, then the best broader one)
RACE_ITER = 3           # ... each for this many LM steps; only the better one is refined further


def _candidates() -> list[tuple[np.ndarray, float]]:
    return [(d, float(n)) for n in CANDIDATE_EXPONENTS for d in CANDIDATE_DIRS]


# ----------------------------------------------------------------------------------------------- NumPy fit
#
# Inside the fit a lobe is held as (psi, alpha, p): C = exp(alpha / n) psi with max_j |psi_j| = 1, so the lobe
# is exp(alpha + n ln(psi . x)) - alpha its peak's log, n = exp(p) its sharpness - which decouples height from
# width (with C itself, changing n at |C| != 1 also changes the height, and LM crawls along that valley).  The
# largest |psi_j| is held at +-1 during a step (the gauge), so each lobe has 4 free parameters; after each step
# psi is renormalised into alpha.  State layout: z[0] = rho, lobe i at z[1 + 5i : 6 + 5i] = (psi, alpha, p).


def _lobe_terms(z: np.ndarray, k: int, x: np.ndarray, derivatives: bool):
    """Lobe values ``[M, S, k]`` (and derivatives by psi ``[M, S, k, 3]``, alpha, p) of state ``z`` at ``x``."""
    m, s = x.shape[:2]
    val = np.zeros((m, s, k))
    d_psi, d_alpha, d_p = (np.zeros((m, s, k, 3)), np.zeros((m, s, k)), np.zeros((m, s, k))) if derivatives else (None,) * 3
    for i in range(k):
        psi, alpha, n = z[:, 1 + 5 * i:4 + 5 * i], z[:, 4 + 5 * i], np.exp(z[:, 5 + 5 * i])
        base = np.einsum("msj,mj->ms", x, psi)
        pos = base > B_MIN
        safe = np.where(pos, base, 1.0)
        lb = np.log(safe)
        t = alpha[:, None] + n[:, None] * lb
        v = np.where(pos, np.exp(np.minimum(t, T_CAP)), 0.0)
        val[..., i] = v
        if derivatives:
            live = pos & (t <= T_CAP)
            d_psi[:, :, i] = np.where(live, v * n[:, None] / safe, 0.0)[..., None] * x
            d_alpha[..., i] = np.where(live, v, 0.0)
            d_p[..., i] = np.where(live, v * n[:, None] * lb, 0.0)
    return val, d_psi, d_alpha, d_p


def _model64(z: np.ndarray, k: int, x: np.ndarray, c: np.ndarray) -> np.ndarray:
    f = z[:, :1] + (_lobe_terms(z, k, x, False)[0].sum(axis=2) if k else 0.0)
    return c * f


def _lobe_log_cap(log_cap, i: int):
    return log_cap - CAP_DROP if i > 0 else log_cap


def _project(z: np.ndarray, k: int, log_cap: np.ndarray) -> np.ndarray:
    """rho >= 0; p in [0, ln 1000]; psi renormalised to max |psi_j| = 1 (into alpha); alpha <= log_cap."""
    z = z.copy()
    z[:, 0] = np.maximum(z[:, 0], 0.0)
    for i in range(k):
        z[:, 5 + 5 * i] = np.clip(z[:, 5 + 5 * i], 0.0, P_MAX)
        n = np.exp(z[:, 5 + 5 * i])
        psi = z[:, 1 + 5 * i:4 + 5 * i]
        mx = np.abs(psi).max(axis=1)
        live = mx > B_MIN
        msafe = np.where(live, mx, 1.0)
        z[:, 1 + 5 * i:4 + 5 * i] = psi / msafe[:, None]
        z[:, 4 + 5 * i] = np.minimum(z[:, 4 + 5 * i] + np.where(live, n * np.log(msafe), 0.0), _lobe_log_cap(log_cap, i))
    return z


def _free_columns(z: np.ndarray, k: int) -> np.ndarray:
    """State index of each free parameter ``[M, 1 + 4k]``: rho, then per lobe the two psi components other
    than the largest (first on ties), alpha and p."""
    cols = np.zeros((len(z), 1 + 4 * k), np.int64)
    for i in range(k):
        frozen = np.abs(z[:, 1 + 5 * i:4 + 5 * i]).argmax(axis=1)
        first = np.where(frozen == 0, 1, 0)
        second = np.where(frozen == 2, 1, 2)
        cols[:, 1 + 4 * i] = 1 + 5 * i + first
        cols[:, 2 + 4 * i] = 1 + 5 * i + second
        cols[:, 3 + 4 * i] = 4 + 5 * i
        cols[:, 4 + 4 * i] = 5 + 5 * i
    return cols


def _cholesky_solve(a: np.ndarray, rhs: np.ndarray):
    """Batched Cholesky solve of ``a [M, P, P]`` x = ``rhs [M, P]``; ``ok`` False where a pivot is not > 0."""
    m, p, _ = a.shape
    low = np.zeros_like(a)
    ok = np.ones(m, bool)
    for j in range(p):
        s = a[:, j, j] - (low[:, j, :j] ** 2).sum(axis=1)
        ok &= s > 0
        d = np.sqrt(np.where(s > 0, s, 1.0))
        low[:, j, j] = d
        if j + 1 < p:
            low[:, j + 1:, j] = (a[:, j + 1:, j] - np.einsum("mik,mk->mi", low[:, j + 1:, :j], low[:, j, :j])) / d[:, None]
    y = np.zeros_like(rhs)
    for i in range(p):
        y[:, i] = (rhs[:, i] - (low[:, i, :i] * y[:, :i]).sum(axis=1)) / low[:, i, i]
    x = np.zeros_like(rhs)
    for i in range(p - 1, -1, -1):
        x[:, i] = (y[:, i] - (low[:, i + 1:, i] * x[:, i + 1:]).sum(axis=1)) / low[:, i, i]
    return x, ok


def _nnls_box(scc, sgg, scg, sct, sgt, stt, wmax):
    """min over rho >= 0, 0 <= w <= wmax of ||t - rho c - w g||^2 from the sums; returns (rho, w, cost)."""
    def cost(r, w):
        return stt - 2 * r * sct - 2 * w * sgt + r * r * scc + 2 * r * w * scg + w * w * sgg
    zero = np.zeros_like(scc)
    det = scc * sgg - scg * scg
    okdet = (det > 1e-12 * scc * sgg) & (det > 0)
    dsafe = np.where(okdet, det, 1.0)
    r4 = (sgg * sct - scg * sgt) / dsafe
    w4 = (scc * sgt - scg * sct) / dsafe
    ok4 = okdet & (r4 >= 0) & (w4 >= 0) & (w4 <= wmax)
    r1 = np.where(scc > 0, np.maximum(sct / np.where(scc > 0, scc, 1.0), 0.0), 0.0)
    w2 = np.where(sgg > 0, np.clip(sgt / np.where(sgg > 0, sgg, 1.0), 0.0, wmax), 0.0)
    r3 = np.where(scc > 0, np.maximum((sct - wmax * scg) / np.where(scc > 0, scc, 1.0), 0.0), 0.0)
    options = [(np.where(ok4, r4, 0.0), np.where(ok4, w4, 0.0), ok4), (r1, zero, None), (zero, w2, None), (r3, wmax, None)]
    best_r, best_w = zero.copy(), zero.copy()
    best_c = np.full_like(scc, np.inf)
    for r, w, valid in options:
        w = np.broadcast_to(w, scc.shape)
        cst = cost(r, w)
        better = cst < best_c if valid is None else valid & (cst < best_c)
        best_r, best_w, best_c = np.where(better, r, best_r), np.where(better, w, best_w), np.where(better, cst, best_c)
    return best_r, best_w, best_c


def _normal_equations(z, k, y, x, c):
    """Cost ``[M]``, ``J'J [M, P, P]``, ``J'r [M, P]`` and the free columns ``[M, P]`` at states ``z [M, 1 + 5k]``."""
    val, d_psi, d_alpha, d_p = _lobe_terms(z, k, x, True)
    full = np.empty(x.shape[:2] + (1 + 5 * k,))
    full[..., 0] = c
    for i in range(k):
        full[..., 1 + 5 * i:4 + 5 * i] = c[..., None] * d_psi[:, :, i]
        full[..., 4 + 5 * i] = c * d_alpha[:, :, i]
        full[..., 5 + 5 * i] = c * d_p[:, :, i]
    cols = _free_columns(z, k)
    jac = np.take_along_axis(full, cols[:, None, :], axis=2)
    r = y - c * (z[:, :1] + val.sum(axis=2))
    return (r * r).sum(axis=1), np.einsum("msi,msj->mij", jac, jac), np.einsum("msi,ms->mi", jac, r), cols


def _clip_move(z, cols, delta, log_cap):
    """The kernel's ``clip_move``: each free parameter's move ``delta [M, P]`` cut where it would leave the box."""
    value = np.take_along_axis(z, cols, axis=1)
    slot = (cols - 1) % 5
    lobe = np.maximum(cols - slot, 1)
    alpha, n = np.take_along_axis(z, lobe + 3, axis=1), np.exp(np.take_along_axis(z, lobe + 4, axis=1))
    cap = np.where((cols - 1) // 5 > 0, log_cap[:, None] - CAP_DROP, log_cap[:, None])
    reach = np.exp(np.maximum(cap - alpha, 0.0) / n)
    low = np.where((cols == 0) | (slot == 4), -value, -np.inf)
    high = np.where(cols == 0, np.inf, np.where(slot == 4, P_MAX - value, np.where(slot == 3, cap - value, np.inf)))
    to = value + delta
    psi_move = np.where(np.abs(to) <= reach, delta, np.copysign(reach, to) - value)   # delta itself unless it crosses
    return np.where((cols > 0) & (slot < 3), psi_move, np.minimum(np.maximum(delta, low), high))


def _damped_step(h, g, dg, lam, z, cols, log_cap):
    """The kernel's ``damped_step`` for every row: ``(delta [M, P], predicted gain [M])``, gain NaN where a
    Cholesky factorisation fails."""
    m, p = g.shape
    diagonal = np.arange(p)
    pinned = np.zeros((m, p), bool)
    delta = np.zeros((m, p))
    ok = np.ones(m, bool)
    for _ in range(2):
        fixed = np.where(pinned, delta, 0.0)
        rhs = np.where(pinned, delta, g - np.einsum("mij,mj->mi", h, fixed) + np.einsum("mii,mi->mi", h, fixed))
        a = np.where(~pinned[:, :, None] & ~pinned[:, None, :], h, 0.0)
        a[:, diagonal, diagonal] = np.where(pinned, 1.0, h[:, diagonal, diagonal] + lam[:, None] * dg)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            solved, good = _cholesky_solve(a, rhs)
        ok &= good
        delta = np.where(pinned, delta, solved)
        clipped = _clip_move(z, cols, delta, log_cap)
        new = ~pinned & (clipped != delta)
        delta = np.where(new, clipped, delta)
        pinned |= new
        if not new.any():
            break
    delta = _clip_move(z, cols, delta, log_cap)
    with np.errstate(invalid="ignore", over="ignore"):
        predicted = (delta * (2.0 * g - np.einsum("mij,mj->mi", h, delta))).sum(axis=1)
    return delta, np.where(ok, predicted, np.nan)


def _lm_numpy(z, k, y, x, c, log_cap, atol, etol, iterations):
    """Levenberg-Marquardt on the ``1 + 4k`` free parameters of every state ``z [M, 1 + 5k]``, as the kernel's
    ``levenberg_marquardt``: active-set steps, Nielsen's gain-ratio damping, the Newton-decrement stop, one pass
    per trial.  Returns ``(z, cost, converged, steps tried)``; only improving steps are taken.
    """
    m, p = len(z), 1 + 4 * k
    z = z.copy()
    cost, h, g, cols = _normal_equations(z, k, y, x, c)
    lam, nu = np.full(m, LAM0), np.full(m, NU0)
    fresh = np.ones(m, bool)
    active = np.ones(m, bool)
    conv = np.zeros(m, bool)
    its = np.zeros(m, np.int64)
    dg = np.zeros((m, p))
    while True:
        idx = np.flatnonzero(active & (its < iterations))
        nb = idx[fresh[idx]]
        if nb.size:
            diag = np.einsum("mii->mi", h[nb])
            dg[nb] = np.maximum(diag, D_FLOOR * diag.max(axis=1, keepdims=True))
            fresh[nb] = False
            _, decrement = _damped_step(h[nb], g[nb], dg[nb], np.full(nb.size, LAM_DEC), z[nb], cols[nb], log_cap[nb])
            done = ((cost[nb] <= atol[nb]) | ~np.any(g[nb] != 0, axis=1)
                    | ((decrement >= 0) & (decrement <= FTOL * cost[nb] + etol[nb])))
            conv[nb[done]] = True
            active[nb[done]] = False
            idx = np.flatnonzero(active & (its < iterations))
        if idx.size == 0:
            break
        its[idx] += 1
        delta, predicted = _damped_step(h[idx], g[idx], dg[idx], lam[idx], z[idx], cols[idx], log_cap[idx])
        go = ~np.isnan(predicted)
        tried = idx[go]
        step = np.zeros((tried.size, z.shape[1]))
        np.put_along_axis(step, cols[tried], delta[go], axis=1)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            trial = _project(z[tried] + step, k, log_cap[tried])
            cost_t, h_t, g_t, cols_t = _normal_equations(trial, k, y[tried], x[tried], c[tried])
        better = cost_t < cost[tried]
        acc, gain, pred = tried[better], cost[tried][better] - cost_t[better], predicted[go][better]
        ratio = np.where(pred > 0, gain / np.where(pred > 0, pred, 1.0), 1.0)
        lam[acc] = np.maximum(lam[acc] * np.maximum(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3), LAM_MIN)
        nu[acc] = NU0
        small = acc[gain <= GTOL * cost[acc] + etol[acc]]
        z[acc], cost[acc], h[acc], g[acc], cols[acc] = trial[better], cost_t[better], h_t[better], g_t[better], cols_t[better]
        fresh[acc] = True
        conv[small] = True
        active[small] = False
        rej = np.concatenate([idx[~go], tried[~better]])
        lam[rej] *= nu[rej]
        nu[rej] *= 2.0
        stuck = rej[lam[rej] > LAM_MAX]
        conv[stuck] = True
        active[stuck] = False
    return z, cost, conv, its


def _ladder_powers(base: np.ndarray, extra: int = 0) -> list[np.ndarray]:
    """``base ^ n`` for every ``n`` of ``CANDIDATE_EXPONENTS`` (1, 1.5, 2, 3, ...) and ``extra`` rungs beyond, by
    squaring, as the kernel; 0 where ``base <= B_MIN``."""
    pos = base > B_MIN
    even = np.where(pos, base, 0.0)
    odd = even * np.sqrt(even)
    powers = []
    for ei in range(len(CANDIDATE_EXPONENTS) + extra):
        if ei % 2:
            powers.append(odd)
            odd = odd * odd
        else:
            powers.append(even)
            even = even * even
    return powers


def _fit_signals_numpy(y, x, c, criterion, n_lobes, iterations):
    """The staged fit of scalar signals ``y [M, S]`` (geometry ``x [M, S, 3]``, cosines ``c [M, S]``).

    ``criterion(F)`` gives the final error of model values ``F [M, S]`` (it decides between stage results).
    Lobes are added one at a time: each from the best shapes of the start grid, fitted by LM with the earlier
    ones, and kept only if the criterion improves (so more lobes are never worse).
    Returns the state ``z [M, 1 + 5K]``, criterion, not-converged flags and steps tried.
    """
    m = y.shape[0]
    ymax = np.abs(y).max(axis=1)
    energy = (y * y).sum(axis=1)
    bounds = _Bounds(np.log(LOBE_CAP * np.maximum(ymax, 1e-12)), ATOL * energy, ETOL * energy, ymax)
    z = np.zeros((m, 1 + 5 * n_lobes))
    scc = (c * c).sum(axis=1)
    z[:, 0] = np.where(scc > 0, np.maximum((c * y).sum(axis=1) / np.where(scc > 0, scc, 1.0), 0.0), 0.0)
    crit = criterion(_model64(z, 0, x, c))
    flag = np.zeros(m, bool)
    its_total = np.zeros(m, np.int64)
    used = np.zeros((m, len(_candidates())), bool)
    for k in range(1, n_lobes + 1):
        costs = _start_grid(z, k - 1, y, x, c, scc, bounds)
        costs[0][used] = np.inf
        fitted, conv, fit_ci, its = _fit_lobe(z, k, y, x, c, costs, bounds, iterations)
        its_total += its
        used[np.arange(m), fit_ci] = True
        new_crit = criterion(_model64(fitted, k, x, c))
        take = new_crit < crit                  # else keep k - 1 lobes and switch this one off (psi = 0)
        z = np.where(take[:, None], fitted, z)
        crit = np.where(take, new_crit, crit)
        flag = np.where(take, ~conv, flag)
    return z, crit, flag, its_total


class _Bounds(NamedTuple):
    """Per-signal limits of a fit: the first lobe's log cap, the absolute and relative stopping tolerances and
    the brightest sample."""

    log_cap: np.ndarray
    atol: np.ndarray
    etol: np.ndarray
    ymax: np.ndarray


def _start_grid(z, j, y, x, c, scc, bounds: _Bounds):
    """Cost, diffuse term and peak of every start shape (direction x exponent) for lobe ``j`` against what the
    earlier lobes leave unexplained, each the best non-negative box fit: ``[M, shapes]`` each."""
    m = y.shape[0]
    prev = c * _lobe_terms(z, j, x, False)[0].sum(axis=2) if j else np.zeros_like(y)
    target = y - prev
    stt, sct = (target * target).sum(axis=1), (c * target).sum(axis=1)
    n_shapes = len(CANDIDATE_DIRS) * len(CANDIDATE_EXPONENTS)
    cand_cost = np.empty((m, n_shapes))
    cand_rho, cand_w = np.empty_like(cand_cost), np.empty_like(cand_cost)
    cc, ct = c * c, c * target
    for di, d in enumerate(CANDIDATE_DIRS):
        # g = c b^n: sum g^2 = sum c^2 b^(2n), the sum c^2 b^n two rungs up the ladder (as the kernel)
        powers = _ladder_powers(x @ d, extra=2)
        sums = [(cc * power).sum(axis=1) for power in powers]
        for ei in range(len(CANDIDATE_EXPONENTS)):
            ci = ei * len(CANDIDATE_DIRS) + di
            cand_rho[:, ci], cand_w[:, ci], cand_cost[:, ci] = _nnls_box(
                scc, sums[ei + 2], sums[ei], sct, (ct * powers[ei]).sum(axis=1), stt,
                np.exp(_lobe_log_cap(bounds.log_cap, j)))
    return cand_cost, cand_rho, cand_w


def _fit_lobe(z, k, y, x, c, costs, bounds: _Bounds, iterations):
    """Fit ``k`` lobes, the last one new, from the best untried start shapes (``N_STARTS`` for the first lobe,
    raced for ``RACE_ITER`` steps, then only the better one refined).  Returns the fitted states, converged
    flags, the start shape used and the steps taken per signal."""
    cand_cost, cand_rho, cand_w = costs
    cands = _candidates()
    all_d = np.array([d for d, _ in cands])
    all_n = np.array([n for _, n in cands])
    m, j, n_state = y.shape[0], k - 1, 1 + 5 * k
    rows = np.arange(m)
    its_total = np.zeros(m, np.int64)
    lowest = np.full(m, np.inf)
    starts = N_STARTS if k == 1 else 1     # later lobes start from one shape: a second one never paid off
    for attempt in range(starts):
        # The best shape not tried yet; after the first, the best broader one (lower exponent) if any: a
        # sharp start that sees one light is where LM gets stuck, a broad one can still sharpen.
        broader = np.where(all_n[None, :] < lowest[:, None], cand_cost, np.inf)
        has = np.isfinite(broader).any(axis=1)
        ci = np.where(has, np.argmin(broader, axis=1), np.argmin(cand_cost, axis=1))
        cand_cost[rows, ci] = np.inf
        lowest = np.minimum(lowest, all_n[ci])
        w0 = np.maximum(cand_w[rows, ci], W_FLOOR * bounds.ymax)
        start = z.copy()
        start[:, 0] = cand_rho[rows, ci]
        live = w0 > 0
        start[:, 1 + 5 * j:4 + 5 * j] = np.where(live[:, None], all_d[ci], 0.0)
        start[:, 4 + 5 * j] = np.log(np.where(live, w0, 1.0))
        start[:, 5 + 5 * j] = np.log(all_n[ci])
        start = _project(start, k, bounds.log_cap)
        trial = start.copy()
        budget = min(iterations, RACE_ITER) if starts > 1 else iterations
        trial[:, :n_state], cost_t, conv_t, its = _lm_numpy(start[:, :n_state], k, y, x, c, bounds.log_cap,
                                                            bounds.atol, bounds.etol, budget)
        its_total += its
        if attempt == 0:
            fitted, conv, fit_cost, fit_ci = trial, conv_t, cost_t, ci
        else:
            better = cost_t < fit_cost
            fitted = np.where(better[:, None], trial, fitted)
            conv, fit_cost, fit_ci = (np.where(better, conv_t, conv), np.where(better, cost_t, fit_cost),
                                      np.where(better, ci, fit_ci))
    more = np.flatnonzero(~conv) if starts > 1 and iterations > RACE_ITER else np.zeros(0, np.int64)
    if more.size:                           # only the better start is refined further
        fitted[more, :n_state], fit_cost[more], conv[more], its = _lm_numpy(
            fitted[more, :n_state], k, y[more], x[more], c[more], bounds.log_cap[more], bounds.atol[more],
            bounds.etol[more], iterations - RACE_ITER)
        its_total[more] += its
    return fitted, conv, fit_ci, its_total
