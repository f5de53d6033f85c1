// Exact k-nearest-neighbour search: one work-item per query, the exemplar visited one tile per launch.
//
// The host launches this kernel once per (query chunk, exemplar tile) and carries each query's running list of
// the TOPK nearest exemplar rows (sorted by squared distance, then index) from one tile to the next in
// best_idx / best_d, so nothing grows with (queries x exemplar) and a tile stays in cache while the queries of
// a work-group pass over it.  Distances are summed one dimension after the other, t = q - e, acc += t * t, in
// float32 without contraction into fused multiply-adds: the NumPy twin (search.py, knn_exact_numpy) does the
// same operations and finds the same lists, ties included.
//
// Build options: -DDIM=<feature dimension>, -DTOPK=<list length>.
#pragma OPENCL FP_CONTRACT OFF

#ifndef DIM
#define DIM 1
#endif
#ifndef TOPK
#define TOPK 1
#endif

// Exemplar rows e0 .. e0 + n_tile - 1 against queries q0 .. q0 + n_query - 1; list slot i of the chunk belongs to
// query q0 + i.  Rows are visited in increasing index and a row enters only when strictly nearer than the
// current last entry, after any entries at the same distance: the lists end up sorted by (distance, index).
// A partial sum above the last entry cannot come back below it (every term is >= 0), so the row is abandoned.
__kernel void knn_tile(__global const float *exemplar, const int e0, const int n_tile,
                       __global const float *queries, const int q0, const int n_query,
                       __global int *best_idx, __global float *best_d)
{
    const int i = get_global_id(0);
    if (i >= n_query) return;
    __global const float *q = queries + (size_t)(q0 + i) * DIM;
    __global int *idx = best_idx + (size_t)i * TOPK;
    __global float *dist = best_d + (size_t)i * TOPK;
    float d[TOPK];
    int id[TOPK];
    for (int j = 0; j < TOPK; ++j) { d[j] = dist[j]; id[j] = idx[j]; }
    float worst = d[TOPK - 1];
    for (int e = e0; e < e0 + n_tile; ++e) {
        __global const float *row = exemplar + (size_t)e * DIM;
        float acc = 0.0f;
        int j = 0;
        for (; j < DIM; ++j) {
            const float t = q[j] - row[j];
            acc += t * t;
            if (acc > worst) break;
        }
        if (j < DIM || !(acc < worst)) continue;
        int slot = TOPK - 1;
        while (slot > 0 && d[slot - 1] > acc) {
            d[slot] = d[slot - 1];
            id[slot] = id[slot - 1];
            --slot;
        }
        d[slot] = acc;
        id[slot] = e;
        worst = d[TOPK - 1];
    }
    for (int j = 0; j < TOPK; ++j) { dist[j] = d[j]; idx[j] = id[j]; }
}

// Full squared distances of each query to its candidate rows (the fast engine's re-ranking): work-item
// (i, j) is query q0 + i against exemplar row rows[i * n_cand + j] (-1: none, distance INFINITY).  The same
// sum, in the same order, as knn_tile, so a neighbour found by either engine has the same distance.
__kernel void knn_distances(__global const float *exemplar, __global const float *queries, const int q0,
                            const int n_query, __global const int *rows, const int n_cand, __global float *out)
{
    const int i = get_global_id(1), j = get_global_id(0);
    if (i >= n_query || j >= n_cand) return;
    const int e = rows[(size_t)i * n_cand + j];
    float acc = INFINITY;
    if (e >= 0) {
        __global const float *q = queries + (size_t)(q0 + i) * DIM;
        __global const float *row = exemplar + (size_t)e * DIM;
        acc = 0.0f;
        for (int d = 0; d < DIM; ++d) {
            const float t = q[d] - row[d];
            acc += t * t;
        }
    }
    out[(size_t)i * n_cand + j] = acc;
}
