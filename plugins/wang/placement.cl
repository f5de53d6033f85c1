// Patch-placement error: for every placement (y, x) on a grid of step `stride` of a window in the exemplar, the sum over the window's
// known pixels p of |F[y + dy_p, x + dx_p] - T_p|^2.  One work item per placement; NumPy twin in placement.py.

__kernel void placement_ssd(__global const float *feats,      // [H, W, D] exemplar features
                            const int width, const int dims,
                            __global const int *offsets,      // [n, 2] (dy, dx) of the known pixels
                            __global const float *target,     // [n, D] their features
                            const int n_pix,
                            const int n_cols,                 // placements per output row
                            const int stride,                 // placements every `stride` texels
                            __global float *out)              // [n_rows, n_cols]
{
    const int x = get_global_id(0) * stride;
    const int y = get_global_id(1) * stride;
    float acc = 0.0f;
    for (int p = 0; p < n_pix; ++p) {
        const int oy = offsets[2 * p], ox = offsets[2 * p + 1];
        __global const float *f = feats + ((size_t)(y + oy) * width + (size_t)(x + ox)) * dims;
        __global const float *t = target + (size_t)p * dims;
        float part = 0.0f;
        for (int d = 0; d < dims; ++d) {
            const float e = f[d] - t[d];
            part = fma(e, e, part);
        }
        acc += part;
    }
    out[(size_t)get_global_id(1) * n_cols + get_global_id(0)] = acc;
}
