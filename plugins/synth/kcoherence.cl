// k-coherence synthesis passes over texton maps (causal wavefronts and correction sub-passes).
//
// Every kernel has a NumPy twin in kcoherence.py that performs the same float32 operations in the same order,
// so both give identical coordinates, ties included.
//
// Build options: -DNOFF=<entries of an offset table> (private array sizes).
#pragma OPENCL FP_CONTRACT OFF

#ifndef NOFF
#define NOFF 24
#endif

// The cell (cell x cell exemplar texels, cw cells a row) that exemplar texel c of a we-wide exemplar lies in
inline int cell_of(const int c, const int we, const int cell, const int cw)
{
    return (c / we) / cell * cw + (c % we) / cell;
}

// ------------------------------------------------------------------------------------------- k-coherence
// The exemplar level: he x we texels, texton map `tex` [he * we] and its edge-padded copy `tex_pad` (padding
// `pad` >= the window radius, row length wp), texton distance table [nt * nt], coherence sets `ksets`
// [he * we * kmax] (entry 0 is the texel itself, -1 marks a missing entry), of which the first k are used.
//
// Candidates for an output pixel: for each used neighbour (offset (dy, dx), source s), the coherent source
// s - (dy, dx) (clamped into the exemplar) and its coherence set.  Cost of a candidate c: the sum over used
// neighbours, in order, of table[tex_pad(c + offset), tex(source)].  The first candidate with the lowest cost
// wins; -1 when there is no used neighbour.  `own` >= 0 (the pixel's current source) is tried before all others,
// at its cost times `own_scale` (<= 1: it is kept unless another candidate is clearly cheaper).  Repeated coherent sources are skipped (they add nothing), and a
// candidate is abandoned once its partial cost reaches the best so far: neither changes the result.
// The coherent source suggested by neighbour (dy, dx) with source `src`, clamped into the exemplar; -1 when an
// earlier neighbour suggested it already (`seen` keeps the n_seen sources so far).
inline int new_coherent_source(const int src, const int dy, const int dx, const int he, const int we, int *seen,
                               int *n_seen)
{
    const int c0 = clamp(src / we - dy, 0, he - 1) * we + clamp(src % we - dx, 0, we - 1);
    for (int j = 0; j < *n_seen; ++j) {
        if (seen[j] == c0) return -1;
    }
    seen[(*n_seen)++] = c0;
    return c0;
}

// Cost of candidate c: the sum over the used neighbours, in order, of table[tex_pad(c + offset), tex(source)];
// INFINITY as soon as the partial sum reaches `stop_at` (the candidate cannot win), so callers skip it.
inline float window_cost(const int c, const int n, const int *ndy, const int *ndx, const int *ntex,
                         __global const int *tex_pad, const int we, const int wp, const int pad,
                         __global const float *table, const int nt, const float stop_at)
{
    const int cc = (c / we + pad) * wp + c % we + pad;
    float acc = 0.0f;
    for (int l = 0; l < n; ++l) {
        acc += table[tex_pad[cc + ndy[l] * wp + ndx[l]] * nt + ntex[l]];
        if (acc >= stop_at) return INFINITY;
    }
    return acc;
}

inline int kc_best(const int n, const int *ndy, const int *ndx, const int *nsrc, const int *ntex,
                   __global const int *tex_pad, const int he, const int we, const int wp, const int pad,
                   __global const float *table, const int nt, __global const int *ksets, const int kmax,
                   const int k, const int own, const float own_scale, float *cost_out)
{
    int best = -1;
    float best_cost = INFINITY;
    if (own >= 0 && n > 0) {  // the pixel's own source goes first, so it is kept where nothing beats it
        best = own;
        best_cost = window_cost(own, n, ndy, ndx, ntex, tex_pad, we, wp, pad, table, nt, INFINITY) * own_scale;
    }
    int seen[NOFF];
    int n_seen = 0;
    for (int i = 0; i < n; ++i) {
        const int c0 = new_coherent_source(nsrc[i], ndy[i], ndx[i], he, we, seen, &n_seen);
        if (c0 < 0) continue;
        for (int j = 0; j < k; ++j) {
            const int c = ksets[(size_t)c0 * kmax + j];
            if (c < 0) continue;
            const float acc = window_cost(c, n, ndy, ndx, ntex, tex_pad, we, wp, pad, table, nt,
                                          best >= 0 ? best_cost : INFINITY);
            if (isinf(acc)) continue;
            if (best < 0 || acc < best_cost) { best = c; best_cost = acc; }
        }
    }
    *cost_out = best_cost;
    return best;
}

// Coverage tie-break (correction passes): among the candidates whose cost is at most best_cost * (1 + tol),
// the one whose exemplar cell (cell x cell texels, cw cells a row) is used least beyond its fair share
// (`excess`), then the cheapest, then the first.  Off when tol == 0 or the best cost is not finite.
inline int kc_fairest(const int best, const float best_cost, const int n, const int *ndy, const int *ndx,
                      const int *nsrc, const int *ntex, __global const int *tex_pad, const int he, const int we,
                      const int wp, const int pad, __global const float *table, const int nt,
                      __global const int *ksets, const int kmax, const int k, __global const float *excess,
                      const int cell, const int cw, const float tol, const int own, const float own_scale)
{
    if (!(tol > 0.0f) || best < 0 || !isfinite(best_cost)) return best;
    const float limit = best_cost * (1.0f + tol);
    const float above_limit = nextafter(limit, INFINITY);
    int pick = best;
    float pick_excess = excess[cell_of(best, we, cell, cw)];
    float pick_cost = best_cost;
    if (own >= 0 && own != best) {  // the pixel's own source, at its scaled cost, comes before the others
        const float e = excess[cell_of(own, we, cell, cw)];
        const float acc = window_cost(own, n, ndy, ndx, ntex, tex_pad, we, wp, pad, table, nt, INFINITY) * own_scale;
        if (acc <= limit && (e < pick_excess || (e == pick_excess && acc < pick_cost))) {
            pick = own; pick_excess = e; pick_cost = acc;
        }
    }
    int seen[NOFF];
    int n_seen = 0;
    for (int i = 0; i < n; ++i) {
        const int c0 = new_coherent_source(nsrc[i], ndy[i], ndx[i], he, we, seen, &n_seen);
        if (c0 < 0) continue;
        for (int j = 0; j < k; ++j) {
            const int c = ksets[(size_t)c0 * kmax + j];
            if (c < 0) continue;
            const float e = excess[cell_of(c, we, cell, cw)];
            if (e > pick_excess) continue;
            const float acc = window_cost(c, n, ndy, ndx, ntex, tex_pad, we, wp, pad, table, nt, above_limit);
            if (!(acc <= limit)) continue;
            if (e < pick_excess || acc < pick_cost) { pick = c; pick_excess = e; pick_cost = acc; }
        }
    }
    return pick;
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
    float cost;
    const int best = kc_best(n, ndy, ndx, nsrc, ntex, tex_pad, he, we, wp, pad, table, nt, ksets, kmax, k,
                             -1, 1.0f, &cost);
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
                         __global const int *ksets, const int kmax, const int k,
                         __global const float *excess, const int cell, const int cw, const float tol,
                         const float own_scale)
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
    float cost;
    const int own = own_scale >= 0.0f && n > 0 ? prev[p] : -1;
    int best = kc_best(n, ndy, ndx, nsrc, ntex, tex_pad, he, we, wp, pad, table, nt, ksets, kmax, k, own,
                       own_scale, &cost);
    best = kc_fairest(best, cost, n, ndy, ndx, nsrc, ntex, tex_pad, he, we, wp, pad, table, nt, ksets, kmax, k,
                      excess, cell, cw, tol, own, own_scale);
    cur[p] = best >= 0 ? best : prev[p];
}
