// k-means assignment of the texton analysis (textons.py): nearest centre of every vector.
//
// Its NumPy twin, assign_numpy, performs the same float32 operations in the same order, so labels agree exactly,
// ties included.  Contraction into fused multiply-adds would change the rounding, so it is switched off.
#pragma OPENCL FP_CONTRACT OFF

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
