"""Height from shading after Liu, Yu & Shum (2001), the modified Leclerc-Bobick method, and its baselines.

Unknowns are a height ``z`` and a grey albedo ``rho`` per texel.  The energy (the paper's eq. 5) is

    E = sum_texels  alpha / K * sum_k eta_k (rho R_k(p, q) - I_k)^2  +  lambda mu (u^2 + v^2)  +  gamma (s^2 + t^2)

with ``p, q`` the central first differences of ``z``, ``u, v`` its second differences along columns and rows,
``s, t`` those of ``rho``, ``R_k = n . l_k`` (not clamped: samples the model cannot explain get weight 0),
``eta`` robust per-sample weights and ``mu`` per-texel smoothness weights that are weaker at image edges.  Terms
are taken at interior texels, so the border heights only enter through their neighbours' differences.

It is minimised by preconditioned non-linear conjugate gradients (Polak-Ribiere, secant line search), from
heights integrated out of robust photometric stereo.  The energy and gradient run on OpenCL (``height.cl``);
``terms_numpy`` / ``gather_numpy`` are the NumPy twin.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from btforge.backend import get_backend

KERNEL_FILE = Path(__file__).with_name("height.cl")
TUKEY_C = 4.685          # Tukey biweight cut-off in robust standard deviations (95 % efficiency at the normal)
MIN_SCALE = 0.02         # floor of the robust residual scale, as a fraction of the albedo (noise-free data)
ATTACHED_EPS = 0.02      # n.l below this: the sample is in attached shadow and carries no Lambertian information
STEP_GROWTH = 1.0        # the next trial step, as a multiple of the last accepted one (the secant grows it)
SECANT_SKIP = 0.25       # CG keeps its trial step, without evaluating the secant minimum, when they differ less
STALL_WINDOW = 10        # CG stops when the energy fell by less than STALL_RTOL of itself over this many iterations
STALL_RTOL = 1e-4
DARK_FRACTION = 0.05     # photometric stereo starts without samples darker than this fraction of a texel's brightest


# ----------------------------------------------------------------------------------------------- energy (twin)


def terms_numpy(z, rho, image, eta, lights, mu, alpha, lam, gam):
    """The per-texel terms of ``hfs_terms``: ``(energy, gp, gq, gu, gv, grho, gs, gt)``, float32 ``[H, W]``."""
    f = np.float32
    z, rho, mu = (np.asarray(a, f) for a in (z, rho, mu))
    H, W = z.shape
    K = image.shape[0]
    out = [np.zeros((H, W), f) for _ in range(8)]
    if H < 3 or W < 3:
        return tuple(out)
    c = (slice(1, -1), slice(1, -1))
    zc = z[c]
    p = f(0.5) * (z[1:-1, 2:] - z[1:-1, :-2])
    q = f(0.5) * (z[:-2, 1:-1] - z[2:, 1:-1])
    inv_s = f(1) / np.sqrt(f(1) + p * p + q * q)
    r = rho[c]
    e_data, d_p, d_q, d_rho = (np.zeros_like(p) for _ in range(4))
    for k in range(K):
        lx, ly, lz = (f(v) for v in lights[k, :3])
        w = eta[k][c]
        shade = (-p * lx - q * ly + lz) * inv_s
        residual = r * shade - image[k][c]
        wr = w * residual
        e_data += wr * residual
        d_rho += wr * shade
        common = wr * r * inv_s
        d_p += common * (-lx - shade * p * inv_s)
        d_q += common * (-ly - shade * q * inv_s)
    u = z[1:-1, 2:] - f(2) * zc + z[1:-1, :-2]
    v = z[2:, 1:-1] - f(2) * zc + z[:-2, 1:-1]
    su = rho[1:-1, 2:] - f(2) * r + rho[1:-1, :-2]
    sv = rho[2:, 1:-1] - f(2) * r + rho[:-2, 1:-1]
    a = f(alpha / K)
    lm = f(lam) * mu[c]
    g = f(gam)
    values = (a * e_data + lm * (u * u + v * v) + g * (su * su + sv * sv),
              f(2) * a * d_p, f(2) * a * d_q, f(2) * lm * u, f(2) * lm * v, f(2) * a * d_rho,
              f(2) * g * su, f(2) * g * sv)
    for o, val in zip(out, values):
        o[c] = val
    return tuple(out)


def gather_numpy(gp, gq, gu, gv, grho, gs, gt):
    """``hfs_gather``: the gradient ``(dE/dz, dE/drho)`` from the per-texel partials (zero off the interior)."""
    f = np.float32
    gz = -f(2) * (gu + gv)
    gz[:, 1:] += f(0.5) * gp[:, :-1] + gu[:, :-1]
    gz[:, :-1] += -f(0.5) * gp[:, 1:] + gu[:, 1:]
    gz[:-1, :] += f(0.5) * gq[1:, :] + gv[1:, :]
    gz[1:, :] += -f(0.5) * gq[:-1, :] + gv[:-1, :]
    ga = grho - f(2) * (gs + gt)
    ga[:, 1:] += gs[:, :-1]
    ga[:, :-1] += gs[:, 1:]
    ga[1:, :] += gt[:-1, :]
    ga[:-1, :] += gt[1:, :]
    return gz.astype(f), ga.astype(f)


@dataclasses.dataclass
class Problem:
    """The fixed data of one solve: grey images ``[K, H, W]``, lights ``[K, 3]``, weights and coefficients."""

    image: np.ndarray
    lights: np.ndarray
    eta: np.ndarray
    mu: np.ndarray
    alpha: float = 1.0
    lam: float = 0.05
    gam: float = 0.05

    def __post_init__(self):
        self.image = np.ascontiguousarray(self.image, np.float32)
        self.eta = np.ascontiguousarray(self.eta, np.float32)
        self.mu = np.ascontiguousarray(self.mu, np.float32)
        self.lights = np.ascontiguousarray(self.lights, np.float32)


class NumpyEnergy:
    """Energy and gradient by the NumPy twin."""

    def __init__(self, problem: Problem):
        self.problem = problem

    def __call__(self, z, rho):
        pb = self.problem
        terms = terms_numpy(z, rho, pb.image, pb.eta, pb.lights, pb.mu, pb.alpha, pb.lam, pb.gam)
        gz, ga = gather_numpy(*terms[1:])
        return float(terms[0].sum(dtype=np.float64)), gz, ga


class OpenCLEnergy:
    """Energy and gradient on the OpenCL device; the images and weights stay on it between evaluations."""

    def __init__(self, problem: Problem):
        self.problem = problem
        self.backend = b = get_backend()
        cl = b.cl
        K, H, W = problem.image.shape
        self.shape = (H, W)
        lights4 = np.zeros((K, 4), np.float32)
        lights4[:, :3] = problem.lights
        self.static = (b.to_device(problem.image), b.to_device(problem.eta), b.to_device(lights4),
                       b.to_device(problem.mu))
        mf = cl.mem_flags
        self.z_buf = cl.Buffer(b.context, mf.READ_ONLY, H * W * 4)
        self.rho_buf = cl.Buffer(b.context, mf.READ_ONLY, H * W * 4)
        self.terms = [cl.Buffer(b.context, mf.READ_WRITE, H * W * 4) for _ in range(8)]
        self.grads = [cl.Buffer(b.context, mf.WRITE_ONLY, H * W * 4) for _ in range(2)]
        program = b.program(KERNEL_FILE)
        self.k_terms = cl.Kernel(program, "hfs_terms")
        self.k_gather = cl.Kernel(program, "hfs_gather")
        self.k_terms.set_args(self.z_buf, self.rho_buf, *self.static, np.int32(H), np.int32(W), np.int32(K),
                              np.float32(problem.alpha / max(K, 1)), np.float32(problem.lam),
                              np.float32(problem.gam), *self.terms)
        self.k_gather.set_args(*self.terms[1:], np.int32(H), np.int32(W), *self.grads)

    def __call__(self, z, rho):
        cl, queue = self.backend.cl, self.backend.queue
        H, W = self.shape
        cl.enqueue_copy(queue, self.z_buf, np.ascontiguousarray(z, np.float32))
        cl.enqueue_copy(queue, self.rho_buf, np.ascontiguousarray(rho, np.float32))
        cl.enqueue_nd_range_kernel(queue, self.k_terms, (W, H), None)
        cl.enqueue_nd_range_kernel(queue, self.k_gather, (W, H), None)
        energy = np.empty((H, W), np.float32)
        gz = np.empty((H, W), np.float32)
        ga = np.empty((H, W), np.float32)
        cl.enqueue_copy(queue, energy, self.terms[0])
        cl.enqueue_copy(queue, gz, self.grads[0])
        cl.enqueue_copy(queue, ga, self.grads[1])
        queue.finish()
        return float(energy.sum(dtype=np.float64)), gz, ga


# ----------------------------------------------------------------------------------------------- solver


def diagonal_preconditioner(problem: Problem, rho: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rough inverse curvatures of the energy in ``z`` and ``rho`` per texel (Gauss-Newton diagonal, bounded)."""
    K = max(problem.image.shape[0], 1)
    wsum = problem.eta.sum(axis=0) / K
    horizontal = (problem.eta * (problem.lights[:, 0, None, None] ** 2 + problem.lights[:, 1, None, None] ** 2)).sum(0) / K
    dz = 2 * problem.alpha * 0.5 * horizontal * np.maximum(rho, 0.1) ** 2 + 2 * problem.lam * problem.mu * 12 + 1e-3
    da = 2 * problem.alpha * wsum * 0.5 + 2 * problem.gam * 12 + 1e-3
    return (1 / dz).astype(np.float64), (1 / da).astype(np.float64)


@dataclasses.dataclass
class SolveReport:
    iterations: int
    evaluations: int
    energy_start: float
    energy_end: float


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    # Not BLAS: a threaded BLAS dot spins against the OpenCL device's threads on a small machine.
    return float(np.multiply(a, b).sum())


def conjugate_gradients(energy, z0, rho0, iterations, precondition=None, tolerance=1e-9, stall_rtol=STALL_RTOL):
    """Minimise ``energy(z, rho) -> (E, dE/dz, dE/drho)`` by preconditioned Polak-Ribiere CG, for at most
    ``iterations``, stopping early once the energy fell by less than ``stall_rtol`` of itself over the last
    ``STALL_WINDOW`` iterations (on the built-in 256^2 x 48 capture that is after 30-40 iterations, and the
    normal error is then within 0.01 degrees of that after 100).

    The line search takes a trial step, fits a secant to the directional derivative at 0 and at the trial, and
    accepts the secant minimum when it lowers the energy (else the trial, else it quarters the step).  When the
    secant minimum lies within ``SECANT_SKIP`` of the trial step and the trial lowered the energy, the trial is
    kept without evaluating the secant point: one energy evaluation per iteration instead of two, the cost of
    an iteration being almost all in the evaluation.
    """
    shape = z0.shape
    x = np.concatenate([np.asarray(z0, np.float64).ravel(), np.asarray(rho0, np.float64).ravel()])
    n = z0.size
    m = np.ones_like(x) if precondition is None else np.concatenate([precondition[0].ravel(), precondition[1].ravel()])

    def evaluate(v):
        e, gz, ga = energy(v[:n].reshape(shape).astype(np.float32), v[n:].reshape(shape).astype(np.float32))
        return e, np.concatenate([gz.ravel(), ga.ravel()]).astype(np.float64)

    e, g = evaluate(x)
    evals, e_start = 1, e
    s = m * g
    d = -s
    step = 1.0
    done = 0
    history = [e]
    for done in range(1, iterations + 1):
        slope0 = _dot(g, d)
        if slope0 >= 0:  # lost descent: restart along the preconditioned steepest descent
            d = -s
            slope0 = _dot(g, d)
        if -slope0 <= tolerance * max(1.0, abs(e)):
            break
        e1, g1 = evaluate(x + step * d)
        evals += 1
        slope1 = _dot(g1, d)
        candidates = [(e1, step, g1)]
        if slope1 > slope0:
            t = step * slope0 / (slope0 - slope1)
            close = abs(t - step) <= SECANT_SKIP * step and e1 < e
            if np.isfinite(t) and t > 0 and not close:
                et, gt = evaluate(x + t * d)
                evals += 1
                candidates.append((et, t, gt))
        e_new, t_new, g_new = min(candidates, key=lambda c: c[0])
        while e_new >= e and t_new > 1e-12:
            t_new *= 0.25
            e_new, g_new = evaluate(x + t_new * d)
            evals += 1
        if e_new >= e:
            break
        x = x + t_new * d
        step = float(np.clip(t_new * STEP_GROWTH, 1e-8, 1e8))
        s_new = m * g_new
        beta = max(0.0, _dot(g_new, s_new - s) / max(_dot(g, s), 1e-300))
        d = -s_new + beta * d
        g, s, e = g_new, s_new, e_new
        history.append(e)
        if len(history) > STALL_WINDOW and history[-1 - STALL_WINDOW] - e <= stall_rtol * abs(e):
            break
    return x[:n].reshape(shape), x[n:].reshape(shape), SolveReport(done, evals, e_start, e)


# ----------------------------------------------------------------------------------------------- photometric stereo


def _solve_lambertian(image, lights, weights):
    """Per texel ``b = argmin sum_k w_k (b . l_k - I_k)^2``; ``image, weights [K, H, W]`` -> ``b [H, W, 3]``."""
    K, H, W = image.shape
    L = np.asarray(lights, np.float32)
    w = np.asarray(weights, np.float32).reshape(K, -1)
    # the sums over samples as float32 matrix products (BLAS, no float64 copies of the [K, H, W] stacks), the
    # 3 x 3 systems in float64
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    outer = np.stack([L[:, i] * L[:, j] for i, j in pairs], axis=1)
    a, b, c, d, e, f = (outer.T @ w).astype(np.float64)
    a, d, f = a + 1e-9, d + 1e-9, f + 1e-9
    rhs = (L.T @ (w * np.asarray(image, np.float32).reshape(K, -1))).astype(np.float64)
    # the symmetric systems solved in closed form (adjugate over determinant): batched LAPACK calls cost
    # several times more per texel
    adj = ((d * f - e * e, c * e - b * f, b * e - c * d),
           (c * e - b * f, a * f - c * c, b * c - a * e),
           (b * e - c * d, b * c - a * e, a * d - b * b))
    det = a * adj[0][0] + b * adj[0][1] + c * adj[0][2]
    singular = det < 1e-12
    scale = 1.0 / np.where(singular, 1.0, det)
    solution = np.stack([(row[0] * rhs[0] + row[1] * rhs[1] + row[2] * rhs[2]) * scale for row in adj], axis=1)
    solution[singular] = (0.0, 0.0, 1e-6)
    return solution.reshape(H, W, 3)


def photometric_stereo_ls(image, lights):
    """Plain least-squares Lambertian photometric stereo (Woodham): ``(normals [H, W, 3], albedo [H, W])``."""
    b = _solve_lambertian(image, lights, np.ones_like(image))
    return _split(b)


def _split(b):
    b = b.copy()
    b[..., 2] = np.maximum(b[..., 2], 1e-6)  # a normal never points into the surface
    albedo = np.linalg.norm(b, axis=-1)
    return (b / albedo[..., None]).astype(np.float32), albedo.astype(np.float32)


def robust_weights(image, lights, normals, albedo, scale_floor=MIN_SCALE):
    """Tukey biweights ``[K, H, W]`` of the samples under a Lambertian model, and the robust scale used.

    Residuals are divided by the texel's albedo (so the scale is one number for the whole field); the scale is
    1.4826 x their median absolute value over the samples the model lights (floored at ``scale_floor``).
    Samples the model puts in attached shadow (n . l < ``ATTACHED_EPS``) get weight 0.
    """
    K, H, W = image.shape
    shade = (np.asarray(lights, np.float32) @ normals.reshape(-1, 3).astype(np.float32).T).reshape(K, H, W)
    lit = shade > ATTACHED_EPS
    # every [K, H, W] operation in place and float32: this runs on every sample, several times per recovery
    residual = np.multiply(image, (1 / np.maximum(albedo.astype(np.float32), 1e-6))[None], dtype=np.float32)
    residual -= shade
    # the scale from an even subsample of the lit residuals: a median of millions is costly and no better
    step = max(1, int(lit.sum()) // 200000)
    sample = np.abs(residual.reshape(-1)[::step][lit.reshape(-1)[::step]])
    sigma = max(1.4826 * float(np.median(sample)) if sample.size else 1.0, scale_floor)
    residual *= np.float32(1 / (TUKEY_C * sigma))
    np.square(residual, out=residual)
    w = np.subtract(np.float32(1), residual, out=residual)      # 1 - x^2, then the biweight (1 - x^2)^2 for |x| < 1
    np.maximum(w, 0, out=w)
    np.square(w, out=w)
    w *= lit
    return w, sigma


def photometric_stereo_robust(image, lights, rounds=8):
    """Robust photometric stereo by iteratively reweighted least squares with Tukey weights.

    Starts without each texel's darkest samples (below ``DARK_FRACTION`` of its brightest: likely shadows), then
    re-weights every sample by its residual.  Returns ``(normals, albedo, weights [K, H, W])``.
    """
    brightest = image.max(axis=0, keepdims=True)
    weights = (image > DARK_FRACTION * brightest).astype(np.float32)
    normals, albedo = _split(_solve_lambertian(image, lights, weights))
    for _ in range(rounds):
        weights, _ = robust_weights(image, lights, normals, albedo)
        normals, albedo = _split(_solve_lambertian(image, lights, weights))
    return normals, albedo, weights


def integrate_normals(normals: np.ndarray) -> np.ndarray:
    """Least-squares heights ``[H, W]`` (mean 0) whose central slopes best match ``normals`` (Neumann borders, DCT
    Poisson solve)."""
    from scipy.fft import dctn, idctn
    n = normals.astype(np.float64)
    nz = np.maximum(n[..., 2], 0.05)
    p, q = -n[..., 0] / nz, -n[..., 1] / nz           # dz/dx, dz/dy
    gc, gr = p, -q                                     # along columns, along rows
    H, W = p.shape
    div = np.zeros((H, W))
    div[:, :-1] += 0.5 * (gc[:, :-1] + gc[:, 1:])
    div[:, 1:] -= 0.5 * (gc[:, :-1] + gc[:, 1:])
    div[:-1, :] += 0.5 * (gr[:-1, :] + gr[1:, :])
    div[1:, :] -= 0.5 * (gr[:-1, :] + gr[1:, :])
    f = dctn(div, type=2, norm="ortho")
    ky = 2 * np.cos(np.pi * np.arange(H) / H) - 2
    kx = 2 * np.cos(np.pi * np.arange(W) / W) - 2
    denom = ky[:, None] + kx[None, :]
    denom[0, 0] = 1.0
    f = f / denom
    f[0, 0] = 0.0
    z = idctn(f, type=2, norm="ortho")
    return (z - z.mean()).astype(np.float32)


def edge_weights(image: np.ndarray) -> np.ndarray:
    """Smoothness weights ``mu [H, W]`` in (0, 1]: small where the input images have strong intensity edges.

    Edge strength is each image's gradient magnitude over its mean brightness, averaged over the images;
    ``mu = 1 / (1 + (e / e0)^2)`` with ``e0`` three times the median strength, so only the strongest edges
    (creases, shadow boundaries, albedo edges) relax the smoothness.
    """
    strength = np.zeros(image.shape[1:])
    for frame in image.astype(np.float64):
        gy, gx = np.gradient(frame) if min(frame.shape) > 1 else (np.zeros_like(frame),) * 2
        strength += np.hypot(gx, gy) / (frame.mean() + 1e-6)
    strength /= max(len(image), 1)
    e0 = 3 * float(np.median(strength)) + 1e-9
    return (1 / (1 + (strength / e0) ** 2)).astype(np.float32)


# ----------------------------------------------------------------------------------------------- driver


@dataclasses.dataclass
class Recovery:
    """What :func:`recover_height` found: heights, colour albedo, weights ``[K, H, W]`` and solver figures."""

    height: np.ndarray
    albedo: np.ndarray
    weights: np.ndarray
    notes: dict


def interior_normals(z: np.ndarray) -> np.ndarray:
    """Normals of ``z`` by the energy's own central differences (one-sided on the border)."""
    from .field import normals_of
    return normals_of(z)


def recover_height(image_rgb: np.ndarray, lights: np.ndarray, *, iterations: int = 100, smoothness: float = 0.01,
                   albedo_smoothness: float = 0.01, robust: bool = True, init: str = "photometric_stereo",
                   rounds: int = 2, use_opencl: bool = True) -> Recovery:
    """Height, albedo and sample weights from ``image_rgb [K, H, W, C]`` linear radiance under ``lights [K, 3]``.

    ``rounds`` alternates the conjugate-gradient solve with re-estimating the robust weights from the current
    surface (the weights are held fixed within a solve, so each solve minimises one smooth energy).  Without
    ``robust`` a sample's weight is 1 wherever the current surface faces its light, 0 elsewhere.
    """
    image_rgb = np.asarray(image_rgb, np.float32)
    grey = image_rgb.mean(axis=3)
    ps_normals, ps_albedo, ps_weights = photometric_stereo_robust(grey, lights)
    scale = float(np.median(ps_albedo)) or 1.0
    grey_n = grey / scale
    if init == "photometric_stereo":
        z = integrate_normals(ps_normals)
        rho = ps_albedo / scale
        weights = ps_weights
    else:
        z = np.zeros(grey.shape[1:], np.float32)
        rho = np.full(grey.shape[1:], float(np.median(grey_n.max(axis=0))), np.float32)
        weights = None
    mu = edge_weights(grey)
    notes = {"photometric_stereo_scale": round(scale, 6), "rounds": []}
    for _ in range(rounds):
        normals = interior_normals(z)
        if robust and weights is None:
            weights, sigma = robust_weights(grey_n, lights, normals, np.maximum(rho, 1e-3))
        elif robust:
            sigma = None
        else:
            shade = np.einsum("hwc,kc->khw", normals, lights)
            weights, sigma = (shade > ATTACHED_EPS).astype(np.float32), None
        problem = Problem(grey_n, lights, weights, mu, 1.0, smoothness, albedo_smoothness)
        energy = OpenCLEnergy(problem) if use_opencl else NumpyEnergy(problem)
        z, rho, report = conjugate_gradients(energy, z, rho, iterations, diagonal_preconditioner(problem, rho))
        z = (z - z.mean()).astype(np.float32)
        rho = np.maximum(rho, 0).astype(np.float32)
        notes["rounds"].append({"iterations": report.iterations, "evaluations": report.evaluations,
                                "energy": [round(report.energy_start, 6), round(report.energy_end, 6)],
                                "robust_scale": None if sigma is None else round(sigma, 5)})
        weights = None  # re-estimated from the new surface at the next round
    normals = interior_normals(z)
    if robust:
        weights, _ = robust_weights(grey_n, lights, normals, np.maximum(rho, 1e-3))
    else:
        weights = (np.einsum("hwc,kc->khw", normals, lights) > ATTACHED_EPS).astype(np.float32)
    albedo = colour_albedo(image_rgb, lights, normals, weights)
    return Recovery(z, albedo, weights, notes)


def colour_albedo(image_rgb, lights, normals, weights):
    """Per-channel albedo ``[H, W, C]``: the weighted least-squares scale of ``n . l`` to each channel."""
    K, H, W, C = image_rgb.shape
    shade = np.asarray(lights, np.float32) @ normals.reshape(-1, 3).astype(np.float32).T     # [K, H W]
    np.maximum(shade, 0, out=shade)
    weighted = shade * np.asarray(weights, np.float32).reshape(K, -1)
    den = (weighted * shade).sum(axis=0, dtype=np.float64)
    pixels = np.asarray(image_rgb, np.float32).reshape(K, -1, C)
    num = np.stack([(weighted * pixels[..., ch]).sum(axis=0, dtype=np.float64) for ch in range(C)], axis=-1)
    fallback = pixels.max(axis=0)  # a texel no sample explains: its brightest observation
    albedo = np.where(den[:, None] > 1e-9, num / np.maximum(den, 1e-9)[:, None], fallback)
    return albedo.clip(0).reshape(H, W, C).astype(np.float32)
