// The shared refinement's hot loops (refine.py).  Twins: _rank_numpy, _sweeps_numpy and _correct_numpy there.
// Exemplar texels are `texels [eh * ew * D]` (D appearance values each, row-major); sources are flat exemplar
// texel indices y * ew + x.  Every sum runs in float32 in the order the twins use, without contraction.
#pragma OPENCL FP_CONTRACT OFF

#ifndef D
#define D 6
#endif
#ifndef PATCH
#define PATCH 8
#endif
#ifndef CAND
#define CAND 9
#endif

__constant int SIDE_Y[4] = {-1, 1, 0, 0};
__constant int SIDE_X[4] = {0, 0, -1, 1};

// c / ew and c % ew for c >= 0 without an integer division (the float quotient is at most a step or two off).
inline int2 split_index(const int c, const int ew, const float inverse)
{
    int row = (int)((float)c * inverse);
    int col = c - row * ew;
    while (col < 0) { col += ew; --row; }
    while (col >= ew) { col -= ew; ++row; }
    return (int2)(row, col);
}

// The index of output texel (y + dy, x + dx), wrapped around an h x w output, or -1 outside it without wrap
// (|dy|, |dx| <= 1).
inline int output_neighbour(const int y, const int x, const int dy, const int dx, const int h, const int w,
                            const int wrap)
{
    int ny = y + dy, nx = x + dx;
    if (!wrap && (ny < 0 || ny >= h || nx < 0 || nx >= w)) return -1;
    ny = ny < 0 ? ny + h : (ny >= h ? ny - h : ny);
    nx = nx < 0 ? nx + w : (nx >= w ? nx - w : nx);
    return ny * w + nx;
}

// Squared distance of exemplar texels a and b.
inline float texel_distance(__global const float *texels, const int a, const int b)
{
    float sum = 0.0f;
    for (int d = 0; d < D; ++d) {
        const float diff = texels[a * D + d] - texels[b * D + d];
        sum += diff * diff;
    }
    return sum;
}

// Candidate re-ranking, one work-item per searched query window q: of its CAND candidate exemplar windows
// (origins flat in the gy x gx window grid, `cand [nq * CAND]`), the one of least squared distance to the query
// (`query [nq * PATCH * PATCH * D]`, texel by texel, row-major) plus its `extra_cost` (per query and candidate,
// `[nq * CAND]`: the occurrence and contrast terms); writes its origin and its squared distance (without the extra
// cost).  The first of equal costs wins.
__kernel void rf_rank(__global const float *texels, const int ew, const int gx,
                      __global const float *query, __global const int *cand, __global const float *extra_cost,
                      const int nq, __global int *best_origin, __global float *best_distance)
{
    const int q = get_global_id(0);
    if (q >= nq) return;
    __global const float *mine = query + (long)q * PATCH * PATCH * D;
    int best = cand[q * CAND];
    float best_cost = INFINITY, best_dist = 0.0f;
    for (int c = 0; c < CAND; ++c) {
        const int origin = cand[q * CAND + c];
        const int top = origin / gx, left = origin % gx;
        const float extra = extra_cost[q * CAND + c];
        float dist = 0.0f;
        // squares are >= 0 and float sums of them never decrease: once the partial cost reaches the best, the
        // candidate cannot win
        for (int dy = 0; dy < PATCH && dist + extra < best_cost; ++dy) {
            __global const float *row = texels + ((long)(top + dy) * ew + left) * D;
            __global const float *qrow = mine + dy * PATCH * D;
            for (int i = 0; i < PATCH * D; ++i) {
                const float diff = row[i] - qrow[i];
                dist += diff * diff;
            }
        }
        const float cost = dist + extra;
        if (cost < best_cost) { best_cost = cost; best = origin; best_dist = dist; }
    }
    best_origin[q] = best;
    best_distance[q] = best_dist;
}

// One half-sweep of the vote's iterated conditional modes, one work-item per output texel: every texel (y, x)
// with (y + x) % 2 == part takes, of its candidates (`votes [h * w * slots]`, -1: none), the one of least data
// cost (`data`, same layout) plus seam_weight x the seam cost against its 4-neighbours' labels (up, down, left,
// right): 0 where the neighbour's source continues the candidate, else the squared difference between the
// neighbour's texel and the candidate's exemplar neighbour (clamped to the exemplar); no neighbour across the
// output's border without wrap.  The other texels keep their labels.  Reads `labels`, writes `next`: with wrap
// and an odd side a texel's neighbour across the border has its colour, and all see the labels before the step.
// The first of equal costs wins.  A texel whose neighbours kept their labels in the last two launches
// (`moved_last`, `moved_before`: 1 where a label changed) would choose as it did before: it keeps its label.
// `moved_now` records this launch's changes.
__kernel void rf_sweep(__global const float *texels, const int eh, const int ew,
                       __global const int *votes, __global const float *data, const int slots,
                       __global const int *labels, __global int *next, const int h, const int w, const int wrap,
                       const int part, const float seam_weight, __global const uchar *moved_last,
                       __global const uchar *moved_before, __global uchar *moved_now)
{
    const int y = get_global_id(0), x = get_global_id(1);
    if (y >= h || x >= w) return;
    const int t = y * w + x;
    int around[4], fresh = 0;
    for (int s = 0; s < 4; ++s) {
        around[s] = output_neighbour(y, x, SIDE_Y[s], SIDE_X[s], h, w, wrap);
        if (around[s] >= 0) fresh |= moved_last[around[s]] | moved_before[around[s]];
    }
    if (((y + x) & 1) != part || !fresh) { next[t] = labels[t]; moved_now[t] = 0; return; }
    const float inverse = 1.0f / (float)ew;
    int neighbour[4];
    float seen[4][D];                                    // the neighbours' texels, read once
    for (int s = 0; s < 4; ++s) {
        neighbour[s] = around[s] < 0 ? -1 : labels[around[s]];
        for (int d = 0; d < D; ++d) seen[s][d] = around[s] < 0 ? 0.0f : texels[neighbour[s] * D + d];
    }
    int best = slots - 1;                                // the current source (always a candidate)
    float best_cost = INFINITY;
    for (int k = 0; k < slots; ++k) {
        const int choice = votes[t * slots + k];
        float total = data[t * slots + k];
        // seam costs are >= 0 and float sums of them never decrease: a candidate whose partial cost already
        // reaches the best cannot win (nor can one without a candidate: its data cost is infinite)
        if (choice < 0 || !(total < best_cost)) continue;
        // the same source proposed before at no higher data cost: its seams are the same, so it costs no more
        int repeated = 0;
        for (int j = 0; j < k && !repeated; ++j)
            repeated = votes[t * slots + j] == choice && data[t * slots + j] <= total;
        if (repeated) continue;
        const int2 at = split_index(choice, ew, inverse);
        for (int s = 0; s < 4 && total < best_cost; ++s) {
            const int current = neighbour[s];
            if (current < 0 || choice + SIDE_Y[s] * ew + SIDE_X[s] == current) continue;
            const int cy = clamp(at.x + SIDE_Y[s], 0, eh - 1), cx = clamp(at.y + SIDE_X[s], 0, ew - 1);
            __global const float *continued = texels + (cy * ew + cx) * D;
            float seam = 0.0f;
            for (int d = 0; d < D; ++d) {
                const float diff = continued[d] - seen[s][d];
                seam += diff * diff;
            }
            total += seam_weight * seam;
        }
        if (total < best_cost) { best_cost = total; best = k; }
    }
    next[t] = votes[t * slots + best];
    moved_now[t] = next[t] != labels[t];
}

// The corrections' candidates, one work-item per output texel: of its own source and the continuations of its
// 4-neighbours' sources (order: own, up, down, left, right), the first of least neighbourhood error: the squared
// difference over the texel and its 4-neighbours (same order, wrapping around the output) between the output and
// the exemplar around the candidate (clamped to the exemplar).  A continuation that leaves the exemplar is no
// candidate.  Writes the chosen source (the caller picks which texels take it).
__kernel void rf_correct(__global const float *texels, const int eh, const int ew,
                         __global const int *src, const int h, const int w, __global int *best_source)
{
    const int y = get_global_id(0), x = get_global_id(1);
    if (y >= h || x >= w) return;
    const int cross_y[5] = {0, -1, 1, 0, 0}, cross_x[5] = {0, 0, 0, -1, 1};
    const float inverse = 1.0f / (float)ew;
    int seen[5];
    for (int o = 0; o < 5; ++o) seen[o] = src[output_neighbour(y, x, cross_y[o], cross_x[o], h, w, 1)];
    int best = seen[0];
    float best_err = INFINITY;
    for (int c = 0; c < 5; ++c) {
        const int2 at = split_index(seen[c], ew, inverse);
        const int nr = at.x - cross_y[c], nc = at.y - cross_x[c];
        if (nr < 0 || nr >= eh || nc < 0 || nc >= ew) continue;
        float err = 0.0f;
        for (int o = 0; o < 5; ++o) {
            const int ey = clamp(nr + cross_y[o], 0, eh - 1), ex = clamp(nc + cross_x[o], 0, ew - 1);
            err += texel_distance(texels, ey * ew + ex, seen[o]);
        }
        if (err < best_err) { best_err = err; best = nr * ew + nc; }
    }
    best_source[y * w + x] = best;
}
