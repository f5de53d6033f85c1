// One improvement step of the self-join of an image's neighbourhoods (PatchMatch with NN-descent): every texel
// p of an H x W image keeps a list of the TOPK texels whose (2 RADIUS + 1)^2 windows of features are nearest
// its own, and improves it from candidates that are likely matches:
//   - seeds: n_seed texels per texel given by the host (a kd-tree's nominees; only in the first step);
//   - propagation: neighbour q = p + delta (the 4 beside p) matched j, so p may match j - delta (windows one
//     texel apart share all but one row or column), from the first NPROP entries of q's list;
//   - neighbours of neighbours: the first NN entries of the lists of p's first NN matches;
//   - n_random texels drawn by an integer hash of (seed, step, p, r), so every part of the image is reached.
// Lists are read from the previous step (idx_in / d_in) and written to idx_out / d_out, so the result does not
// depend on the order work-items run.  A candidate enters when it is allowed, more than `exclude` texels
// (Chebyshev) from p, not listed yet, and (distance, index) before the last entry: the list ends as the TOPK
// smallest (distance, index) pairs of the old list and all candidates, which the NumPy twin (selfjoin.py,
// improve_numpy) forms by sorting.  Missing entries are index -1, distance INFINITY, and sort after every texel.
//
// With `skip_settled` (a step without seeds or random candidates) a texel whose own list, whose 4 neighbours'
// lists and whose first NN matches' lists all came out of the last step unchanged would try exactly the
// candidates it tried then: it keeps its list without computing anything.  changed_out[p] says whether p's
// list changed in this step.
//
// Distances are read from the edge-padded feature image (row-major, FEATURES floats a texel), one window row
// of SIDE * FEATURES contiguous floats at a time: 8 lanes accumulate t * t over the row's whole chunks of 8,
// are summed pairwise ((0+1)+(2+3))+((4+5)+(6+7)), the row's last floats are added one by one, and the row sum
// is added to the distance; after a row the distance is abandoned once it exceeds the list's last entry
// (every term is >= 0).  No contraction into fused multiply-adds, so the twin's float32 sums are the same.
//
// Build options: -DFEATURES=<floats a texel>, -DRADIUS=<window radius>, -DTOPK=<list length>,
// -DNPROP=<entries of each neighbour's list propagated>, -DNN=<matches whose matches are tried, and how many>.
#pragma OPENCL FP_CONTRACT OFF

#ifndef FEATURES
#define FEATURES 1
#endif
#ifndef RADIUS
#define RADIUS 1
#endif
#ifndef TOPK
#define TOPK 1
#endif
#ifndef NPROP
#define NPROP TOPK
#endif
#ifndef NN
#define NN TOPK
#endif
#define SIDE (2 * RADIUS + 1)
#define ROW (SIDE * FEATURES)
#define CHUNKS (ROW / 8)

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

// squared distance of the windows whose top-left corners are padded texels a and b (rows `stride` apart),
// abandoned after the first window row that takes it above `worst`
float window_distance(__global const float *image, const int stride, const int a, const int b, const float worst)
{
    float acc = 0.0f;
    for (int row = 0; row < SIDE; ++row) {
        __global const float *u = image + (size_t)(a + row * stride) * FEATURES;
        __global const float *v = image + (size_t)(b + row * stride) * FEATURES;
        float8 lanes = (float8)(0.0f);
        for (int c = 0; c < CHUNKS; ++c) {
            const float8 t = vload8(c, u) - vload8(c, v);
            lanes += t * t;
        }
        float sum = ((lanes.s0 + lanes.s1) + (lanes.s2 + lanes.s3)) + ((lanes.s4 + lanes.s5) + (lanes.s6 + lanes.s7));
        for (int j = 8 * CHUNKS; j < ROW; ++j) {
            const float t = u[j] - v[j];
            sum += t * t;
        }
        acc += sum;
        if (acc > worst) break;
    }
    return acc;
}

// whether any list p's candidates come from changed in the last step
int sources_changed(__global const uchar *changed, __global const int *idx_in, const int p, const int py,
                    const int px, const int h, const int w)
{
    if (changed[p]) return 1;
    if ((py > 0 && changed[p - w]) || (py + 1 < h && changed[p + w])) return 1;
    if ((px > 0 && changed[p - 1]) || (px + 1 < w && changed[p + 1])) return 1;
    for (int j = 0; j < NN; ++j) {
        const int m = idx_in[(size_t)p * TOPK + j];
        if (m >= 0 && changed[m]) return 1;
    }
    return 0;
}

__kernel void selfjoin_step(__global const float *image, const int h, const int w, const int exclude,
                            __global const uchar *allowed, __global const int *idx_in, __global const float *d_in,
                            __global const uchar *changed_in, __global int *idx_out, __global float *d_out,
                            __global uchar *changed_out, __global const int *seeds, const int n_seed,
                            const uint seed, const uint step, const int n_random, const int skip_settled)
{
    const int p = get_global_id(0);
    const int n = h * w;
    if (p >= n) return;
    const int py = p / w, px = p % w;
    const int stride = w + 2 * RADIUS;
    float d[TOPK];
    int id[TOPK];
    for (int j = 0; j < TOPK; ++j) { d[j] = d_in[(size_t)p * TOPK + j]; id[j] = idx_in[(size_t)p * TOPK + j]; }
    int changed = 0;
    if (!skip_settled || sources_changed(changed_in, idx_in, p, py, px, h, w)) {
        const int n_prop = 4 * NPROP, n_nn = NN * NN;
        const int total = n_seed + n_prop + n_nn + n_random;
        for (int c_i = 0; c_i < total; ++c_i) {
            int c = -1;
            if (c_i < n_seed) {
                c = seeds[(size_t)p * n_seed + c_i];
            } else if (c_i < n_seed + n_prop) {                 // propagation from the 4 neighbours
                const int o = (c_i - n_seed) / NPROP;
                const int dy = o == 0 ? -1 : (o == 1 ? 1 : 0), dx = o == 2 ? -1 : (o == 3 ? 1 : 0);
                const int qy = py + dy, qx = px + dx;
                if (qy >= 0 && qy < h && qx >= 0 && qx < w) {
                    const int j = idx_in[(size_t)(qy * w + qx) * TOPK + (c_i - n_seed) % NPROP];
                    if (j >= 0) {
                        const int cy = j / w - dy, cx = j % w - dx;
                        if (cy >= 0 && cy < h && cx >= 0 && cx < w) c = cy * w + cx;
                    }
                }
            } else if (c_i < n_seed + n_prop + n_nn) {          // neighbours of neighbours
                const int k = c_i - n_seed - n_prop;
                const int m = idx_in[(size_t)p * TOPK + k / NN];
                if (m >= 0) c = idx_in[(size_t)m * TOPK + k % NN];
            } else {                                            // random texels
                const uint r = (uint)(c_i - n_seed - n_prop - n_nn);
                c = (int)(mix_hash(seed ^ mix_hash((uint)p * 0x9e3779b1u ^ mix_hash(step * 0x10001u + r))) % (uint)n);
            }
            if (c < 0 || !allowed[c]) continue;
            const int cy = c / w, cx = c % w;
            if (max(abs(cy - py), abs(cx - px)) <= exclude) continue;
            int listed = 0;
            for (int j = 0; j < TOPK; ++j) listed |= id[j] == c;
            if (listed) continue;
            const float worst = d[TOPK - 1];
            const float acc = window_distance(image, stride, py * stride + px, cy * stride + cx, worst);
            if (!before(acc, c, worst, id[TOPK - 1])) continue;
            int slot = TOPK - 1;
            while (slot > 0 && before(acc, c, d[slot - 1], id[slot - 1])) {
                d[slot] = d[slot - 1];
                id[slot] = id[slot - 1];
                --slot;
            }
            d[slot] = acc;
            id[slot] = c;
        }
        for (int j = 0; j < TOPK; ++j) changed |= id[j] != idx_in[(size_t)p * TOPK + j];
    }
    for (int j = 0; j < TOPK; ++j) { d_out[(size_t)p * TOPK + j] = d[j]; idx_out[(size_t)p * TOPK + j] = id[j]; }
    changed_out[p] = (uchar)changed;
}
