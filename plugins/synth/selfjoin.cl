// One improvement step of the coherence-propagated self-join (PatchMatch with NN-descent): every texel p of an
// H x W image keeps a list of the TOPK texels whose neighbourhood vectors are nearest its own, and improves it
// from candidates that image coherence makes likely:
//   - propagation: texel q = p + spread * delta (delta: the 8 around p) matched j, so p may match
//     j - spread * delta (spreads that halve from step to step carry a match across the image in log steps);
//   - neighbours of neighbours: what p's NN nearest matches matched (their NN nearest);
//   - n_random texels drawn by an integer hash of (seed, step, p, r), so every part of the image is reached.
// Lists are read from the previous step (idx_in / d_in) and written to idx_out / d_out, so the result does not
// depend on the order work-items run.  A candidate enters when it is allowed, more than `exclude` texels
// (Chebyshev) from p, not listed yet, and (distance, index) before the last entry: the list ends as the TOPK
// smallest (distance, index) pairs of the old list and all candidates, which the NumPy twin (selfjoin.py,
// improve_numpy) forms by sorting.  Distances: t = a - b, acc += t * t over the dimensions in order, without
// contraction (as search.cl).  Missing entries are index -1, distance INFINITY, and sort after every texel.
//
// Build options: -DDIM=<vector dimension>, -DTOPK=<list length>, -DNN=<entries of p's list, and of theirs,
// whose matches are tried>.
#pragma OPENCL FP_CONTRACT OFF

#ifndef DIM
#define DIM 1
#endif
#ifndef TOPK
#define TOPK 1
#endif
#ifndef NN
#define NN TOPK
#endif

uint mix_hash(uint h)
{
    h ^= h >> 16;
    h *= 0x7feb352du;
    h ^= h >> 15;
    h *= 0x846ca68bu;
    h ^= h >> 16;
    return h;
}

// (d, i) before (e, j) in list order; a missing entry (-1) sorts after every texel at the same distance
int before(const float d, const int i, const float e, const int j)
{
    const uint a = (uint)i, b = (uint)j;   // -1 becomes the largest key
    return d < e || (d == e && a < b);
}

__kernel void selfjoin_step(__global const float *vectors, const int h, const int w, const int exclude,
                            __global const uchar *allowed, __global const int *idx_in, __global const float *d_in,
                            __global int *idx_out, __global float *d_out, const uint seed, const uint step,
                            const int n_random, const int spread)
{
    const int p = get_global_id(0);
    const int n = h * w;
    if (p >= n) return;
    const int py = p / w, px = p % w;
    __global const float *v = vectors + (size_t)p * DIM;
    float d[TOPK];
    int id[TOPK];
    for (int j = 0; j < TOPK; ++j) { d[j] = d_in[(size_t)p * TOPK + j]; id[j] = idx_in[(size_t)p * TOPK + j]; }
    const int n_prop = 8 * TOPK, n_nn = NN * NN;
    for (int c_i = 0; c_i < n_prop + n_nn + n_random; ++c_i) {
        int c = -1;
        if (c_i < n_prop) {                         // propagation from the 8 neighbours
            int o = c_i / TOPK;
            o += o >= 4;                            // skip the centre of the 3 x 3 offsets
            const int dy = spread * (o / 3 - 1), dx = spread * (o % 3 - 1);
            const int qy = py + dy, qx = px + dx;
            if (qy >= 0 && qy < h && qx >= 0 && qx < w) {
                const int j = idx_in[(size_t)(qy * w + qx) * TOPK + c_i % TOPK];
                if (j >= 0) {
                    const int cy = j / w - dy, cx = j % w - dx;
                    if (cy >= 0 && cy < h && cx >= 0 && cx < w) c = cy * w + cx;
                }
            }
        } else if (c_i < n_prop + n_nn) {           // neighbours of neighbours
            const int m = idx_in[(size_t)p * TOPK + (c_i - n_prop) / NN];
            if (m >= 0) c = idx_in[(size_t)m * TOPK + (c_i - n_prop) % NN];
        } else {                                    // random texels
            const uint r = (uint)(c_i - n_prop - n_nn);
            c = (int)(mix_hash(seed ^ mix_hash((uint)p * 0x9e3779b1u ^ mix_hash(step * 0x10001u + r))) % (uint)n);
        }
        if (c < 0 || !allowed[c]) continue;
        if (max(abs(c / w - py), abs(c % w - px)) <= exclude) continue;
        int listed = 0;
        for (int j = 0; j < TOPK; ++j) listed |= id[j] == c;
        if (listed) continue;
        __global const float *row = vectors + (size_t)c * DIM;
        const float worst = d[TOPK - 1];
        float acc = 0.0f;
        int k = 0;
        for (; k < DIM; ++k) {
            const float t = v[k] - row[k];
            acc += t * t;
            if (acc > worst) break;                 // partial sums only grow
        }
        if (k < DIM || !before(acc, c, worst, id[TOPK - 1])) continue;
        int slot = TOPK - 1;
        while (slot > 0 && before(acc, c, d[slot - 1], id[slot - 1])) {
            d[slot] = d[slot - 1];
            id[slot] = id[slot - 1];
            --slot;
        }
        d[slot] = acc;
        id[slot] = c;
    }
    for (int j = 0; j < TOPK; ++j) { d_out[(size_t)p * TOPK + j] = d[j]; idx_out[(size_t)p * TOPK + j] = id[j]; }
}
