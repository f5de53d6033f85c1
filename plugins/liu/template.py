"""Template images: a height field rendered grey, with shadows and occlusion, at each target (view, light).

See ``template.cl`` for the method.  :func:`march_plan` fixes the sample points on the host so the kernel and
the NumPy twin :func:`render_numpy` walk the same ones.  The height field is sampled as a tileable texture
(lookups wrap): a synthesized field made with ``wrap`` tiles exactly; a recovered one shows a seam where a ray
or shadow crosses its border.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from btforge.backend import get_backend

KERNEL_FILE = Path(__file__).with_name("template.cl")
STEP = 0.5                 # horizontal texels between two samples of a march
MAX_LENGTH_FACTOR = 4      # a march is at most this many times max(H, W) texels long
SHADOW_BIAS = 1e-3         # texels: keeps a hit point from shadowing itself through rounding
VERTICAL_EPS = 1e-6
_CHUNK_BYTES = 64 << 20
TILE = 8                   # texels per side of the tiles whose highest height lets the kernel's shadow march skip


def tile_maxima(heights: np.ndarray, tile: int = TILE) -> np.ndarray:
    """``[ceil(H / tile), ceil(W / tile)]`` the highest height of each tile's texels and of the texels one row and
    column beyond it (wrapping): an upper bound of every bilinear sample whose cell's corner lies in the tile."""
    H, W = heights.shape
    grown = np.maximum(heights, np.roll(heights, -1, 0))
    grown = np.maximum(grown, np.roll(grown, -1, 1))
    th, tw = -(-H // tile), -(-W // tile)
    padded = np.full((th * tile, tw * tile), -np.inf, np.float32)
    padded[:H, :W] = grown
    return padded.reshape(th, tile, tw, tile).max(axis=(1, 3)).astype(np.float32)


def march_plan(heights: np.ndarray, views: np.ndarray, lights: np.ndarray):
    """Per-setting ``(view_march, view_start, light_march, lights4)`` float32 ``[S, 4]`` (see template.cl)."""
    H, W = heights.shape
    top, bottom = float(heights.max()), float(heights.min())
    z_ref = 0.5 * (top + bottom)
    cap = math.ceil(MAX_LENGTH_FACTOR * max(H, W) / STEP)
    S = len(views)
    view_march = np.zeros((S, 4), np.float32)
    view_start = np.zeros((S, 4), np.float32)
    light_march = np.zeros((S, 4), np.float32)
    lights4 = np.zeros((S, 4), np.float32)
    for s, ((vx, vy, vz), (lx, ly, lz)) in enumerate(zip(views.astype(np.float64), lights.astype(np.float64))):
        lights4[s, :3] = (lx, ly, lz)
        horizontal = math.hypot(vx, vy)
        if horizontal < VERTICAL_EPS or top == bottom:
            view_start[s, 3] = 1.0
        else:
            t0 = (top - z_ref) / max(vz, 1e-6)          # up the camera ray from the reference plane to the top
            view_start[s, :3] = (t0 * vx, -t0 * vy, top)
            descent = STEP * vz / horizontal
            steps = min(cap, math.ceil((top - bottom) / max(descent, 1e-9)) + 1)
            view_march[s] = (-STEP * vx / horizontal, STEP * vy / horizontal, -descent, steps)
        horizontal = math.hypot(lx, ly)
        if horizontal >= VERTICAL_EPS and top > bottom:
            rise = lz / horizontal
            steps = cap if rise <= 0 else min(cap, math.ceil((top - bottom) / (rise * STEP)) + 1)
            light_march[s] = (STEP * lx / horizontal, -STEP * ly / horizontal, STEP * rise, steps)
    return view_march, view_start, light_march, lights4


def _bilinear(field: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """template.cl's ``bilinear`` on float32 coordinate arrays; ``field [H, W]`` or ``[H, W, n]``."""
    H, W = field.shape[:2]
    col0, row0 = np.floor(col), np.floor(row)
    fx, fy = col - col0, row - row0
    c0 = col0.astype(np.int64) % W
    r0 = row0.astype(np.int64) % H
    c1 = np.where(c0 + 1 == W, 0, c0 + 1)
    r1 = np.where(r0 + 1 == H, 0, r0 + 1)
    if field.ndim == 3:
        fx, fy = fx[..., None], fy[..., None]
    a, b, c, d = field[r0, c0], field[r0, c1], field[r1, c0], field[r1, c1]
    top = a + fx * (b - a)
    bottom = c + fx * (d - c)
    return top + fy * (bottom - top)


def render_numpy(heights, albedo, normals, views, lights):
    """The NumPy twin of :func:`render`: ``(image [S, H, W] float32, shadow [S, H, W] bool)``."""
    heights, albedo, normals = (np.ascontiguousarray(a, np.float32) for a in (heights, albedo, normals))
    H, W = heights.shape
    plan = march_plan(heights, np.asarray(views), np.asarray(lights))
    f = np.float32
    top = f(heights.max())
    rows, cols = np.meshgrid(np.arange(H, dtype=f), np.arange(W, dtype=f), indexing="ij")
    images = np.empty((len(views), H, W), f)
    shadows = np.empty((len(views), H, W), bool)
    for s in range(len(views)):
        vm, vs, lm, l4 = (p[s] for p in plan)
        if vs[3] != 0:
            hit_c, hit_r = cols.copy(), rows.copy()
        else:
            c, r, z = cols + vs[0], rows + vs[1], np.full_like(cols, vs[2])
            gap_prev = z - _bilinear(heights, c, r)
            hit_c, hit_r = c.copy(), r.copy()
            active = gap_prev > 0
            cp, rp, zp = c.copy(), r.copy(), z.copy()
            for k in range(1, int(vm[3]) + 1):
                if not active.any():
                    break
                kf = f(k)
                idx = np.flatnonzero(active.ravel())
                cp.ravel()[idx], rp.ravel()[idx], zp.ravel()[idx] = c.ravel()[idx], r.ravel()[idx], z.ravel()[idx]
                cn = cols.ravel()[idx] + vs[0] + kf * vm[0]
                rn = rows.ravel()[idx] + vs[1] + kf * vm[1]
                zn = np.full(idx.shape, vs[2] + kf * vm[2], f)
                gap = zn - _bilinear(heights, cn, rn)
                crossed = gap <= 0
                g_prev = gap_prev.ravel()[idx]
                frac = np.where(crossed, g_prev / np.where(crossed, g_prev - gap, f(1)), f(0)).astype(f)
                c_prev, r_prev, z_prev = cp.ravel()[idx], rp.ravel()[idx], zp.ravel()[idx]
                cn = np.where(crossed, c_prev + frac * (cn - c_prev), cn)
                rn = np.where(crossed, r_prev + frac * (rn - r_prev), rn)
                zn = np.where(crossed, z_prev + frac * (zn - z_prev), zn)
                c.ravel()[idx], r.ravel()[idx], z.ravel()[idx] = cn, rn, zn
                gap_prev.ravel()[idx] = gap
                active.ravel()[idx[crossed]] = False
            hit_c, hit_r = c, r
        hit_z = _bilinear(heights, hit_c, hit_r)
        n = _bilinear(normals, hit_c, hit_r)
        a = _bilinear(albedo, hit_c, hit_r)
        norm = np.sqrt(n[..., 0] * n[..., 0] + n[..., 1] * n[..., 1] + n[..., 2] * n[..., 2])
        n_dot_l = (n[..., 0] * l4[0] + n[..., 1] * l4[1] + n[..., 2] * l4[2]) / norm
        dark = n_dot_l <= 0
        pending = np.flatnonzero(~dark.ravel())
        for k in range(1, int(lm[3]) + 1):
            if pending.size == 0:
                break
            kf = f(k)
            ray = hit_z.ravel()[pending] + f(SHADOW_BIAS) + kf * lm[2]
            below = ray < top
            pending, ray = pending[below], ray[below]
            terrain = _bilinear(heights, hit_c.ravel()[pending] + kf * lm[0], hit_r.ravel()[pending] + kf * lm[1])
            hit = terrain > ray
            dark.ravel()[pending[hit]] = True
            pending = pending[~hit]
        images[s] = np.where(dark, f(0), a * n_dot_l)
        shadows[s] = dark
    return images, shadows


def render(heights, albedo, normals, views, lights):
    """Template images ``[S, H, W]`` float32 and shadow masks ``[S, H, W]`` bool for settings ``(views[s],
    lights[s])`` (unit ``[S, 3]`` each), on OpenCL.  ``albedo`` is grey ``[H, W]``."""
    heights, albedo, normals = (np.ascontiguousarray(a, np.float32) for a in (heights, albedo, normals))
    H, W = heights.shape
    S = len(views)
    images = np.empty((S, H, W), np.float32)
    shadows = np.empty((S, H, W), np.uint8)
    if S == 0:
        return images, shadows.astype(bool)
    b = get_backend()
    kernel = b.kernel(KERNEL_FILE, "render_template")
    plan = march_plan(heights, np.asarray(views), np.asarray(lights))
    field = [b.to_device(heights), b.to_device(albedo), b.to_device(normals)]
    tiles = tile_maxima(heights)
    per = max(1, min(S, _CHUNK_BYTES // (H * W * 5)))
    img_buf, sh_buf = b.empty(per * H * W * 4), b.empty(per * H * W)
    for start in range(0, S, per):
        stop = min(S, start + per)
        kernel(b.queue, (W, H, stop - start), None, *field, *(b.to_device(p[start:stop]) for p in plan),
               np.int32(H), np.int32(W), np.float32(heights.max()), np.float32(SHADOW_BIAS), b.to_device(tiles),
               np.int32(tiles.shape[1]), np.int32(TILE), img_buf, sh_buf)
        b.cl.enqueue_copy(b.queue, images[start:stop], img_buf)
        b.cl.enqueue_copy(b.queue, shadows[start:stop], sh_buf)
    b.queue.finish()
    return images, shadows.astype(bool)
