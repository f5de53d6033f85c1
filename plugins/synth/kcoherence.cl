// Texton-based neighbourhood synthesis: k-means assignment, all-pairs neighbourhood search, k-coherence passes.
//
// Every kernel has a NumPy twin in kcoherence.py that performs the same float32 operations in the same order,
// so both give identical integer results (labels, candidate lists, coordinates), ties included.  Contraction
// into fused multiply-adds would change the rounding of the k-means distances, so it is switched off.
//
// Build options: -DNOFF=<entries of an offset table> (private array sizes), -DTOP=<list length> (search).
#pragma OPENCL FP_CONTRACT OFF

#ifndef NOFF
#define NOFF 24
#endif
#ifndef TOP
#define TOP 8
#endif
#define NO_INDEX 2147483647

// ------------------------------------------------------------------------------------------- k-means assignment
// x: [n, DIM] ; centres: [nc, DIM] ; labels, dist: [n].  The first nearest centre wins ties.
#ifndef DIM
#define DIM 1
#endif
__kernel void kmeans_assign(__global const float *x, __global const float *centres, const int n, const int nc,
                            __global int *labels, __global float *dist)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    float xi[DIM];
    for (int j = 0; j < DIM; ++j) xi[j] = x[(size_t)i * DIM + j];
    float best = INFINITY;
    int best_c = 0;
    for (int c = 0; c < nc; ++c) {
        __global const float *cc = centres + (size_t)c * DIM;
        float acc = 0.0f;
        for (int j = 0; j < DIM; ++j) {
            const float t = xi[j] - cc[j];
            acc += t * t;
        }
        if (acc < best) { best = acc; best_c = c; }
    }
    labels[i] = best_c;
    dist[i] = best;
}

// ------------------------------------------------------------------------------------------- neighbourhood search
// For exemplar texels p0 .. p0 + count - 1 (row-major in an h x w exemplar): the TOP texels q with the smallest
// neighbourhood distance sum_o table[tex(p + o), tex(q + o)], among those with allowed[q] != 0 and Chebyshev
// distance to p above `exclude`.  tex is the texton map edge-padded by `pad` on every side (row length wp);
// offs[o] are the window offsets as flat steps in that padded map.  Entries of `table` must be >= 0, which
// makes partial sums monotone: a q is abandoned as soon as its partial sum exceeds the current TOP-th best,
// without changing the result.  To make that bite early, the texels whose own texton equals p's (members
// [starts[t], starts[t + 1]) of texton t) are tried first; the full scan then skips texels already listed.
// Lists are sorted by (distance, index), which does not depend on the visiting order; missing entries are
// -1 / INFINITY.
inline void search_try(const int q, const int qy, const int qx, const int py, const int px, const int wp,
                       const int pad, const int exclude, __global const uchar *allowed, __global const int *tex,
                       const int *offs, __global const float *table, const int *rows,
                       float *best_cost, int *best_idx, float *worst, int *worst_idx)
{
    if (!allowed[q] || (abs(qy - py) <= exclude && abs(qx - px) <= exclude)) return;
    const int cq = (qy + pad) * wp + qx + pad;
    float acc = 0.0f;
    for (int o = 0; o < NOFF; ++o) {
        acc += table[rows[o] + tex[cq + offs[o]]];
        if (acc > *worst) return;
    }
    if (!(acc < *worst || (acc == *worst && q < *worst_idx))) return;
    for (int j = 0; j < TOP; ++j) {
        if (best_idx[j] == q) return;  // tried before
    }
    int j = TOP - 1;
    while (j > 0 && (best_cost[j - 1] > acc || (best_cost[j - 1] == acc && best_idx[j - 1] > q))) {
        best_cost[j] = best_cost[j - 1];
        best_idx[j] = best_idx[j - 1];
        --j;
    }
    best_cost[j] = acc;
    best_idx[j] = q;
    *worst = best_cost[TOP - 1];
    *worst_idx = best_idx[TOP - 1];
}

__kernel void nbhd_search(__global const int *tex, const int h, const int w, const int wp, const int pad,
                          __global const int *offs, const int noff, __global const float *table, const int nt,
                          __global const int *members, __global const int *starts,
                          __global const uchar *allowed, const int exclude, const int p0, const int count,
                          __global int *out_idx, __global float *out_cost)
{
    const int gi = get_global_id(0);
    if (gi >= count) return;
    const int p = p0 + gi;
    const int py = p / w, px = p % w;
    const int cp = (py + pad) * wp + px + pad;
    int rows[NOFF], off[NOFF];
    for (int o = 0; o < NOFF; ++o) {
        off[o] = offs[o];
        rows[o] = tex[cp + off[o]] * nt;
    }
    float best_cost[TOP];
    int best_idx[TOP];
    for (int j = 0; j < TOP; ++j) { best_cost[j] = INFINITY; best_idx[j] = NO_INDEX; }
    float worst = INFINITY;
    int worst_idx = NO_INDEX;
    const int own = tex[cp];
    for (int i = starts[own]; i < starts[own + 1]; ++i) {
        const int q = members[i];
        search_try(q, q / w, q % w, py, px, wp, pad, exclude, allowed, tex, off, table, rows,
                   best_cost, best_idx, &worst, &worst_idx);
    }
    for (int qy = 0; qy < h; ++qy) {
        for (int qx = 0; qx < w; ++qx) {
            search_try(qy * w + qx, qy, qx, py, px, wp, pad, exclude, allowed, tex, off, table, rows,
                       best_cost, best_idx, &worst, &worst_idx);
        }
    }
    for (int j = 0; j < TOP; ++j) {
        out_idx[(size_t)gi * TOP + j] = best_idx[j] == NO_INDEX ? -1 : best_idx[j];
        out_cost[(size_t)gi * TOP + j] = best_cost[j];
    }
}

// ------------------------------------------------------------------------------------------- k-coherence
// The exemplar level: he x we texels, texton map `tex` [he * we] and its edge-padded copy `tex_pad` (padding
// `pad` >= the window radius, row length wp), texton distance table [nt * nt], coherence sets `ksets`
// [he * we * kmax] (entry 0 is the texel itself, -1 marks a missing entry), of which the first k are used.
//
// Candidates for an output pixel: for each used neighbour (offset (dy, dx), source s), the coherent source
// s - (dy, dx) (clamped into the exemplar) and its coherence set.  Cost of a candidate c: the sum over used
// neighbours, in order, of table[tex_pad(c + offset), tex(source)].  The first candidate with the lowest cost
// wins; -1 when there is no used neighbour.  Repeated coherent sources are skipped (they add nothing), and a
// candidate is abandoned once its partial cost reaches the best so far: neither changes the result.
inline int kc_best(const int n, const int *ndy, const int *ndx, const int *nsrc, const int *ntex,
                   __global const int *tex_pad, const int he, const int we, const int wp, const int pad,
                   __global const float *table, const int nt, __global const int *ksets, const int kmax,
                   const int k)
{
    int best = -1;
    float best_cost = INFINITY;
    int seen[NOFF];
    int n_seen = 0;
    for (int i = 0; i < n; ++i) {
        const int sy = clamp(nsrc[i] / we - ndy[i], 0, he - 1);
        const int sx = clamp(nsrc[i] % we - ndx[i], 0, we - 1);
        const int c0 = sy * we + sx;
        int dup = 0;
        for (int j = 0; j < n_seen; ++j) {
            if (seen[j] == c0) { dup = 1; break; }
        }
        if (dup) continue;
        seen[n_seen++] = c0;
        for (int j = 0; j < k; ++j) {
            const int c = ksets[(size_t)c0 * kmax + j];
            if (c < 0) continue;
            const int cc = (c / we + pad) * wp + c % we + pad;
            float acc = 0.0f;
            int l = 0;
            for (; l < n; ++l) {
                acc += table[tex_pad[cc + ndy[l] * wp + ndx[l]] * nt + ntex[l]];
                if (best >= 0 && acc >= best_cost) break;
            }
            if (l < n) continue;
            if (best < 0 || acc < best_cost) { best = c; best_cost = acc; }
        }
    }
    return best;
}

// Causal pass, one wavefront: pixels (y, x) with x + step * y == t (step = radius + 1), y = y0 .. y0 + ny - 1.
// A neighbour is used when it is fixed (seeded, never rewritten in this pass) or on an earlier wavefront; with a
// non-wrapping output that is exactly the L-shaped causal neighbourhood of scanline order (plus fixed pixels),
// and no neighbour can be written by this launch.  With use_prev, the other neighbours are used too, read from
// `prev` (the state before the pass; a toroidal pass over noise).  Fixed pixels are skipped.
#define CAUSAL_ARGS __global int *cur, __global const int *prev, const int use_prev, \
                    __global const uchar *fixed, const int ho, const int wo, const int wrap, const int step, \
                    __global const int *off_dy, __global const int *off_dx, const int noff, \
                    __global const int *tex, __global const int *tex_pad, const int he, const int we, \
                    const int wp, const int pad, __global const float *table, const int nt, \
                    __global const int *ksets, const int kmax, const int k
#define CAUSAL_PASS cur, prev, use_prev, fixed, ho, wo, wrap, step, off_dy, off_dx, noff, tex, tex_pad, he, we, \
                    wp, pad, table, nt, ksets, kmax, k

// Flat index of output pixel (qy, qx): wrapped around a tiling output, -1 outside one that does not tile.
inline int output_neighbour(int qy, int qx, const int ho, const int wo, const int wrap)
{
    if (wrap) {
        qy = (qy % ho + ho) % ho;
        qx = (qx % wo + wo) % wo;
    } else if (qy < 0 || qy >= ho || qx < 0 || qx >= wo) {
        return -1;
    }
    return qy * wo + qx;
}

inline void causal_pixel(const int y, const int x, const int t, CAUSAL_ARGS)
{
    if (y < 0 || y >= ho || x < 0 || x >= wo) return;
    const int p = y * wo + x;
    if (fixed[p]) return;
    int ndy[NOFF], ndx[NOFF], nsrc[NOFF], ntex[NOFF];
    int n = 0;
    for (int o = 0; o < noff; ++o) {
        const int q = output_neighbour(y + off_dy[o], x + off_dx[o], ho, wo, wrap);
        if (q < 0) continue;
        const int qy = q / wo, qx = q % wo;
        int source;
        if (fixed[q] || qx + step * qy < t) source = cur[q];
        else if (use_prev && q != p) source = prev[q];
        else continue;
        ndy[n] = off_dy[o];
        ndx[n] = off_dx[o];
        nsrc[n] = source;
        ntex[n] = tex[source];
        ++n;
    }
    const int best = kc_best(n, ndy, ndx, nsrc, ntex, tex_pad, he, we, wp, pad, table, nt, ksets, kmax, k);
    if (best >= 0) cur[p] = best;
}

// One wavefront per launch: rows y0 .. y0 + ny - 1 of wavefront t.
__kernel void kc_causal(const int t, const int y0, const int ny, CAUSAL_ARGS)
{
    const int gi = get_global_id(0);
    if (gi >= ny) return;
    causal_pixel(y0 + gi, t - step * (y0 + gi), t, CAUSAL_PASS);
}

// The whole pass in one work-group: every wavefront in turn, separated by barriers (no launch per wavefront).
__kernel void kc_causal_all(CAUSAL_ARGS)
{
    const int lid = get_local_id(0), size = get_local_size(0);
    const int t_end = (wo - 1) + step * (ho - 1) + 1;
    for (int t = 0; t < t_end; ++t) {
        const int y_lo = max(0, (t - (wo - 1) + step - 1) / step);
        const int y_hi = min(ho - 1, t / step);
        for (int y = y_lo + lid; y <= y_hi; y += size) causal_pixel(y, t - step * y, t, CAUSAL_PASS);
        barrier(CLK_GLOBAL_MEM_FENCE);
    }
}

// Correction sub-pass: pixels (cy + step * i, cx + step * j) below row y_end and left of column x_end re-chosen
// with their full neighbourhoods, read from `prev` (the state before this sub-pass) and written to `cur`.  The
// host arranges sub-passes so that pixels of one are never neighbours, also across a wrapping seam.
__kernel void kc_correct(__global const int *prev, __global int *cur, const int ho, const int wo, const int wrap,
                         const int cy, const int cx, const int step, const int y_end, const int x_end,
                         __global const int *off_dy, __global const int *off_dx, const int noff,
                         __global const int *tex, __global const int *tex_pad, const int he, const int we,
                         const int wp, const int pad, __global const float *table, const int nt,
                         __global const int *ksets, const int kmax, const int k)
{
    const int y = cy + step * (int)get_global_id(0);
    const int x = cx + step * (int)get_global_id(1);
    if (y >= y_end || x >= x_end) return;
    const int p = y * wo + x;
    int ndy[NOFF], ndx[NOFF], nsrc[NOFF], ntex[NOFF];
    int n = 0;
    for (int o = 0; o < noff; ++o) {
        const int q = output_neighbour(y + off_dy[o], x + off_dx[o], ho, wo, wrap);
        if (q < 0) continue;
        if (q == p) continue;
        ndy[n] = off_dy[o];
        ndx[n] = off_dx[o];
        nsrc[n] = prev[q];
        ntex[n] = tex[prev[q]];
        ++n;
    }
    const int best = kc_best(n, ndy, ndx, nsrc, ntex, tex_pad, he, we, wp, pad, table, nt, ksets, kmax, k);
    cur[p] = best >= 0 ? best : prev[p];
}
