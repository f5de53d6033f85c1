// Image quilting on per-texel appearance vectors: overlap distances, candidate projections, rejection.
//
// Build option: -DD=<feature dimensions> (every kernel is built per D).
//
// Candidates and overlaps
//   feats   [n_texel * D]  float: the exemplar's appearance vectors, texel-major (texel = row * width + column)
//   bases   [n_cand]       int:   flat texel index of each candidate block's top-left texel
//   offsets [n_pix]        int:   flat texel offset (row stride = exemplar width) of each overlap texel from the
//                                 block's top-left texel, in the order of the unfolded overlap vector
// so element (p, d) of candidate c's unfolded overlap vector is feats[(bases[c] + offsets[p]) * D + d].
//
// Projections: basis function j is piecewise constant - it lives on feature dimension dims[j] and takes value
// coefs[j][b] on up to four boxes b of the block (a 2D Haar function of one overlap rectangle) - so its
// projection is a signed sum of box sums, four reads each in a summed-area table.

#pragma OPENCL EXTENSION cl_khr_fp64 : enable

// The distances of a search must be bit-identical whichever candidates a launch covers (the rejection search
// recomputes survivors' distances and must reproduce the brute-force values exactly), so no contraction into
// fused multiply-adds, whose use could differ between vectorised and scalar code paths.
#pragma OPENCL FP_CONTRACT OFF

#ifndef D
#define D 1
#endif

#define MAX_BOXES 4

// Sum of squared differences between a candidate's overlap and the query, in a fixed order of operations: both
// searches call this, so the rejection's survivors get exactly the brute-force values.
inline float overlap_ssd(__global const float *feats, const int base, __global const int *offsets,
                         __global const float *query, const int n_pix)
{
    float acc = 0.0f;
    for (int p = 0; p < n_pix; ++p) {
        __global const float *f = feats + (size_t)(base + offsets[p]) * D;
        __global const float *q = query + (size_t)p * D;
        for (int d = 0; d < D; ++d) {
            const float diff = f[d] - q[d];
            acc += diff * diff;
        }
    }
    return acc;
}

// Brute force: every candidate's overlap distance, one work-item per candidate.
// query [n_pix * D] float ; out [n_cand] float
__kernel void quilt_ssd(__global const float *feats, __global const int *bases, __global const int *offsets,
                        __global const float *query, const int n_cand, const int n_pix, __global float *out)
{
    const int c = get_global_id(0);
    if (c >= n_cand) return;
    out[c] = overlap_ssd(feats, bases[c], offsets, query, n_pix);
}

// Projections of every candidate onto every basis function: one work-item per candidate and run of PROJECT_RUN
// functions (adjacent work-items read adjacent table entries for the same function, which vectorises).
// sat     [n_dim, plane] double: summed-area table of each feature dimension (mean removed), (H+1) x (W+1),
//         entry (y, x) = sum of rows < y, columns < x
// corners [n_cand] int: flat index (y * (W+1) + x) of each candidate's top-left corner in a table
// boxes   [n_proj, MAX_BOXES] int4: flat table offsets of a box's corners (y1x1, y0x1, y1x0, y0x0) from the
//         candidate's corner ; coefs [n_proj, MAX_BOXES] double (all 0 for padding functions) ; dims [n_proj] int
// proj    [n_proj / 8, n_cand, 8] float: projections in chunks of 8 (n_proj is a multiple of 8), chunk-major, so
//         the first chunks - which the rejection reads for every candidate - are contiguous and stay in cache
#define PROJECT_RUN 64
__kernel void quilt_project(__global const double *sat, const int plane, __global const int *corners,
                            __global const int4 *boxes, __global const double *coefs, __global const int *dims,
                            const int n_cand, const int n_proj, __global float *proj)
{
    const int c = get_global_id(0);
    const int j0 = get_global_id(1) * PROJECT_RUN;
    if (c >= n_cand) return;
    const int j1 = min(j0 + PROJECT_RUN, n_proj);
    const int corner = corners[c];
    for (int j = j0; j < j1; ++j) {
        __global const double *s = sat + (size_t)dims[j] * plane + corner;
        double acc = 0.0;
        for (int b = 0; b < MAX_BOXES; ++b) {
            const double w = coefs[j * MAX_BOXES + b];
            if (w != 0.0) {
                const int4 o = boxes[j * MAX_BOXES + b];
                acc += w * (((s[o.x] - s[o.y]) - s[o.z]) + s[o.w]);
            }
        }
        proj[((size_t)(j / 8) * n_cand + c) * 8 + j % 8] = (float)acc;
    }
}

// Projection-kernel rejection, one work-item per candidate: accumulate the candidate's lower bound from its
// projections eight at a time (one float8) and drop it as soon as the bound exceeds the limit of the projections
// used so far (the threshold widened by their rounding margin); survivors get their full overlap distance right
// away.  proj [n_proj / 8, n_cand, 8] as quilt_project writes it ; qlimit [2 * n_proj] float: the query's projections,
// then the limits.  out [2 * n_cand]: first used[c] = the first projection count j at which the running bound
// exceeded limit[j - 1] in the block that dropped c (1..n_proj), or n_proj + 1 if it survived; then dist[c] (float
// bits) = its overlap distance if it survived (as quilt_ssd computes it), else its lower bound when dropped.
__kernel void quilt_reject(__global const float *proj, __global const float *qlimit, const int n_cand,
                           const int n_proj, __global const float *feats, __global const int *bases,
                           __global const int *offsets, __global const float *query, const int n_pix,
                           __global int *out)
{
    const int c = get_global_id(0);
    if (c >= n_cand) return;
    __global int *used = out;
    __global float *dist = (__global float *)(out + n_cand);
    __global const float *limit = qlimit + n_proj;
    __global const float8 *chunks = (__global const float8 *)proj + c;  // chunk b of c is chunks[b * n_cand]
    __global const float8 *q8 = (__global const float8 *)qlimit;
    float lb = 0.0f;
    for (int b = 0; b < n_proj / 8; ++b) {
        const float8 diff = chunks[(size_t)b * n_cand] - q8[b];
        const float8 sq = diff * diff;
        const float before = lb;
        lb += ((sq.s0 + sq.s1) + (sq.s2 + sq.s3)) + ((sq.s4 + sq.s5) + (sq.s6 + sq.s7));
        if (lb > limit[8 * b + 7]) {
            // Report the first projection of the block whose running bound was already over its limit.
            const float s[8] = {sq.s0, sq.s1, sq.s2, sq.s3, sq.s4, sq.s5, sq.s6, sq.s7};
            float run = before;
            int at = 8 * b + 8;
            for (int i = 0; i < 8; ++i) {
                run += s[i];
                if (run > limit[8 * b + i]) {
                    at = 8 * b + i + 1;
                    break;
                }
            }
            used[c] = at;
            dist[c] = lb;
            return;
        }
    }
    used[c] = n_proj + 1;
    dist[c] = overlap_ssd(feats, bases[c], offsets, query, n_pix);
}
