// Light-table bases (hsh, rbf, bilinear): per-texel projection (the fit) and evaluation (relighting).
//
// Every basis is linear in its coefficients: a texel with coefficients c[P] relit under light l shows
//   rgb(l) = lw[l, 0] + sum_p c[p] lw[l, p + 1]          (lw: [L, P + 1, 3], the basis at the light, in RGB)
// and its coefficients are a linear function of its samples y[L, 3]:
//   c[p] = sum_{l, k} proj[p, l, k] y[l, k] - offset[p]   (proj: the regularised least-squares inverse).
// The host builds lw and proj; these kernels do the per-texel work.  NumPy twins: model.evaluate_numpy and
// fit.project_numpy.
//
// Build options: -DBYTES (basis_project reads uchar samples, 0..255; proj already carries the 1/255);
// -DSRGB_STEPS=<n> (basis_eval exists only with it: model.EVAL_OPTIONS).

#ifdef BYTES
#define SAMPLE_T uchar
#else
#define SAMPLE_T float
#endif

// samples: [L, T, 3] ; proj: [P, L, 3] ; offset: [P] ; coeffs out: [T, P].  Global size (T, P).
__kernel void basis_project(__global const SAMPLE_T *samples, __global const float *proj,
                            __global const float *offset, const int n_light, const int n_texel, const int n_plane,
                            __global float *coeffs)
{
    const int t = get_global_id(0);
    const int p = get_global_id(1);
    if (t >= n_texel || p >= n_plane) return;
    __global const float *row = proj + (size_t)p * n_light * 3;
    float acc = 0.f;
    for (int l = 0; l < n_light; ++l) {
        __global const SAMPLE_T *y = samples + ((size_t)l * n_texel + t) * 3;
        acc += row[3 * l] * (float)y[0] + row[3 * l + 1] * (float)y[1] + row[3 * l + 2] * (float)y[2];
    }
    coeffs[(size_t)t * n_plane + p] = acc - offset[p];
}

// sRGB display value -> linear radiance: the curve sampled at SRGB_STEPS + 1 points (model.SRGB_TABLE, set by
// -DSRGB_STEPS) and interpolated linearly, clipping to [0, 1] first.  pow() costs more than the whole sum on CPU
// devices; the interpolation is within 1e-7 of the curve.
#ifdef SRGB_STEPS
inline float srgb_decode(const float value, __constant float *table)
{
    const float x = clamp(value, 0.0f, 1.0f) * (float)SRGB_STEPS;
    const int i = min((int)x, SRGB_STEPS - 1);
    const float f = x - (float)i;
    return table[i] + f * (table[i + 1] - table[i]);
}

// coeffs: [T, P] ; lw: [L, P + 1, 3] ; srgb_table: [SRGB_STEPS + 1] ; out: [L, T, 3] linear radiance.
// Global size (T, L).
__kernel void basis_eval(__global const float *coeffs, __constant float *lw, __constant float *srgb_table,
                         const int n_plane, const int n_texel, const int n_light, __global float *out)
{
    const int t = get_global_id(0);
    const int l = get_global_id(1);
    if (t >= n_texel || l >= n_light) return;
    __constant float *w = lw + (size_t)l * (n_plane + 1) * 3;
    __global const float *c = coeffs + (size_t)t * n_plane;
    float r = w[0], g = w[1], b = w[2];
    for (int p = 0; p < n_plane; ++p) {
        const float cp = c[p];
        r += cp * w[3 * p + 3];
        g += cp * w[3 * p + 4];
        b += cp * w[3 * p + 5];
    }
    __global float *o = out + ((size_t)l * n_texel + t) * 3;
    o[0] = srgb_decode(r, srgb_table);
    o[1] = srgb_decode(g, srgb_table);
    o[2] = srgb_decode(b, srgb_table);
}
#endif  // SRGB_STEPS
