// Jump-map walk: one work-item visits the output's pixels in the given order (Hilbert curve or scanline), since
// each pixel needs the ones visited before it.
// Twin: walk_numpy in jumpmap.py (same float32 comparisons and sums in the same order, so identical results).
//
// A neighbour q is synthesized ("done") when it was visited before the pixel.  Directions d: left, up, right,
// down; candidate d continues the source of that neighbour by one texel towards the pixel, replaced by a jump
// target with the texel's jump probability, or forced to jump from the source when the copy would leave the
// exemplar.  Candidates are compared over the done pixels of the 3 x 3 window (row-major); the first lowest
// wins.  flags[p]: bit 0 the chosen candidate jumped, bit 1 the jump was forced.  With balance, the use of every
// exemplar cell is counted after each pixel.
#pragma OPENCL FP_CONTRACT OFF

#ifndef JUMPS
#define JUMPS 3
#endif
#ifndef OVERUSE
#define OVERUSE 4
#endif

__constant int NBR_Y[4] = {0, -1, 0, 1};
__constant int NBR_X[4] = {-1, 0, 1, 0};

// The cell (cell x cell exemplar texels, cw cells a row) that exemplar texel c of a we-wide exemplar lies in
inline int cell_of(const int c, const int we, const int cell, const int cw)
{
    return (c / we) / cell * cw + (c % we) / cell;
}

// Whether `use` copies of a cell's texels exceed OVERUSE times its fair share of `done` pixels (fair_scale: the
// exemplar's texel count) plus one cell's worth (a slack, so the first copies never count as over-use).
inline int over_share(const int use, const int cell, const long fair_scale, const long done)
{
    return (long)(use - cell * cell) * fair_scale > OVERUSE * done * cell * cell;
}

// The target drawn by u from the cumulative probabilities; with balance, of the targets from the drawn one on
// (cyclically), the first whose exemplar cell has been used least so far, or `escape` (a random interior texel)
// when even that cell holds more than OVERUSE times its fair share of the `done` pixels so far.
inline int pick_target(const int texel, const float u, __global const float *cumulative,
                       __global const int *targets, const int balance, __global const int *usage, const int we,
                       const int cell, const int cw, const int escape, const long fair_scale, const long done)
{
    int j = 0;
    for (int i = 0; i < JUMPS; ++i) {
        if (u >= cumulative[texel * JUMPS + i]) ++j;
    }
    j = min(j, JUMPS - 1);
    int best = targets[texel * JUMPS + j];
    if (!balance || best < 0) return best;
    int best_use = usage[cell_of(best, we, cell, cw)];
    for (int i = 1; i < JUMPS; ++i) {
        const int c = targets[texel * JUMPS + (j + i) % JUMPS];
        if (c < 0) continue;
        const int use = usage[cell_of(c, we, cell, cw)];
        if (use < best_use) { best = c; best_use = use; }
    }
    return over_share(best_use, cell, fair_scale, done) ? escape : best;
}

// Whether texel c's exemplar cell holds more than OVERUSE times its fair share of the `done` pixels.
inline int overused(const int c, __global const int *usage, const int we, const int cell, const int cw,
                    const long fair_scale, const long done)
{
    return over_share(usage[cell_of(c, we, cell, cw)], cell, fair_scale, done);
}

// Flat index of output pixel (qy, qx) one step from the image: wrapped around a tiling output, -1 outside one
// that does not tile.
inline int output_neighbour(int qy, int qx, const int ho, const int wo, const int wrap)
{
    if (wrap) {
        qy = (qy + ho) % ho;
        qx = (qx + wo) % wo;
    } else if (qy < 0 || qy >= ho || qx < 0 || qx >= wo) {
        return -1;
    }
    return qy * wo + qx;
}

// Candidate d of output pixel p = (y, x): the source of its done neighbour in direction d continued by one texel
// towards p, or a jump (flag 1: drawn, 3: forced); -1 where that neighbour is outside or not yet done.
inline int candidate(const int d, const int y, const int x, const int p, __global const int *src,
                     __global const uchar *done_px, const int ho, const int wo, const int wrap,
                     __global const float *uniform, __global const int *targets, __global const float *cumulative,
                     __global const float *probability, const int he, const int we, const int balance,
                     __global const int *usage, const int cell, const int cw, const int escape, const long done,
                     uchar *flag)
{
    *flag = 0;
    const int q = output_neighbour(y + NBR_Y[d], x + NBR_X[d], ho, wo, wrap);
    if (q < 0 || !done_px[q]) return -1;
    const int s = src[q];
    const int sy = s / we - NBR_Y[d], sx = s % we - NBR_X[d];
    const float u0 = uniform[((size_t)p * 4 + d) * 2], u1 = uniform[((size_t)p * 4 + d) * 2 + 1];
    const long fair_scale = (long)he * we;
    if (sy >= 0 && sy < he && sx >= 0 && sx < we) {
        const int c = sy * we + sx;
        if (targets[c * JUMPS] >= 0
            && (u0 < probability[c] || (balance && overused(c, usage, we, cell, cw, fair_scale, done)))) {
            *flag = 1;
            return pick_target(c, u1, cumulative, targets, balance, usage, we, cell, cw, escape, fair_scale, done);
        }
        return c;
    }
    const int f = pick_target(s, u1, cumulative, targets, balance, usage, we, cell, cw, escape, fair_scale, done);
    if (f >= 0) {
        *flag = 3;
        return (f / we - NBR_Y[d]) * we + f % we - NBR_X[d];
    }
    *flag = 2;
    return clamp(sy, 0, he - 1) * we + clamp(sx, 0, we - 1);
}

// Of the four candidates, the first whose 3 x 3 neighbourhood differs least (texton distances) from the done
// pixels around p; -1 where there is none.
inline int best_candidate(const int *cand, const int y, const int x, __global const int *src,
                          __global const uchar *done_px, const int ho, const int wo, const int wrap,
                          __global const int *tex, __global const int *tex_pad, const int we,
                          __global const float *table, const int nt)
{
    const int wp = we + 2;
    float cost[4] = {0.0f, 0.0f, 0.0f, 0.0f};
    for (int oy = -1; oy <= 1; ++oy) {
        for (int ox = -1; ox <= 1; ++ox) {
            if (!oy && !ox) continue;
            const int q = output_neighbour(y + oy, x + ox, ho, wo, wrap);
            if (q < 0 || !done_px[q]) continue;
            const int tq = tex[src[q]];
            for (int d = 0; d < 4; ++d) {
                if (cand[d] < 0) continue;
                const int c = cand[d];
                cost[d] += table[tex_pad[(c / we + 1 + oy) * wp + c % we + 1 + ox] * nt + tq];
            }
        }
    }
    int best = -1;
    for (int d = 0; d < 4; ++d) {
        if (cand[d] >= 0 && (best < 0 || cost[d] < cost[best])) best = d;
    }
    return best;
}

// The whole walk, in one work-item: pixels order[0 .. n - 1].  done_px starts all zero.
__kernel void jm_walk(__global int *src, __global uchar *flags, __global uchar *done_px, __global const int *order,
                      const int n, const int ho, const int wo, const int wrap,
                      __global const float *uniform, __global const int *fallback,
                      __global const int *targets, __global const float *cumulative,
                      __global const float *probability,
                      __global const int *tex, __global const int *tex_pad, const int he, const int we,
                      __global const float *table, const int nt,
                      const int balance, __global int *usage, const int cell, const int cw,
                      __global const int *escape)
{
    if (get_global_id(0) != 0) return;
    for (int k = 0; k < n; ++k) {
        const int p = order[k];
        const int y = p / wo, x = p % wo;
        int cand[4];
        uchar flag[4];
        for (int d = 0; d < 4; ++d) {
            cand[d] = candidate(d, y, x, p, src, done_px, ho, wo, wrap, uniform, targets, cumulative, probability,
                                he, we, balance, usage, cell, cw, escape[p], (long)k, &flag[d]);
        }
        const int best = best_candidate(cand, y, x, src, done_px, ho, wo, wrap, tex, tex_pad, we, table, nt);
        src[p] = best < 0 ? fallback[p] : cand[best];
        flags[p] = best < 0 ? 0 : flag[best];
        done_px[p] = 1;
        if (balance) usage[cell_of(src[p], we, cell, cw)] += 1;
    }
}
