// Polynomial texture maps: per-texel least-squares fit and evaluation.
// Terms are (lu^2, lv^2, lu*lv, lu, lv, 1) for a unit light (lu, lv, lw).
// Build options: -DSAMPLE_T=uchar|float ; -DUSE_LUT when samples are bytes decoded through a 256-entry table.

#define SRGB_TABLE_STEPS 4096

#ifndef SAMPLE_T
#define SAMPLE_T float
#endif

inline float load_sample(__global const SAMPLE_T *s, size_t i, __constant float *lut) {
#ifdef USE_LUT
    return lut[s[i]];
#else
    return (float)s[i];
#endif
}

// The linear half of every PTM fit: for each texel and channel ("element", texel-major), the 6 projections
// sum_l weights[l, k] * y[l, e] of its samples onto the rows of the (regularised) pseudo-inverse.  An rgb PTM is
// these projections; an lrgb PTM is finished from them on the host.  A launch covers a batch of lights, so a
// capture can be fitted as its images decode: with accumulate != 0 the batch adds onto the sums already there,
// in light order - the same float operations in the same order as one launch over all lights.
// samples: [n_batch, sample_stride] elements from element_offset on, lights light_offset .. + n_batch - 1
// weights_t: [L, 6] (the pseudo-inverse, transposed; pre-scaled by 1/255 for bytes read without a table)
// sums: [n_element, 6], i.e. [texel, channel, 6]
// Each work-item does 8 consecutive elements as float8, so every byte is read once with vector loads and the
// 48 sums stay in registers; a table lookup (linear radiance from sRGB bytes) costs gathers and is slower.
inline float8 load8(__global const SAMPLE_T *p, __constant float *lut) {
#ifdef USE_LUT
    return (float8)(lut[p[0]], lut[p[1]], lut[p[2]], lut[p[3]], lut[p[4]], lut[p[5]], lut[p[6]], lut[p[7]]);
#else
    return convert_float8(vload8(0, p));
#endif
}

__kernel void ptm_project(__global const SAMPLE_T *samples_all, __constant float *lut, __constant float *weights_t,
                          const int n_batch, const int light_offset, const long sample_stride,
                          const long element_offset, const long n_element, const int accumulate,
                          __global float *sums)
{
    const long e0 = (long)get_global_id(0) * 8;
    if (e0 >= n_element) return;
    __global const SAMPLE_T *samples = samples_all + element_offset + e0;
    __global float *o = sums + e0 * 6;
    if (e0 + 8 > n_element) {  // the last few elements, one at a time
        for (long e = 0; e < n_element - e0; ++e) {
            float acc[6];
            for (int k = 0; k < 6; ++k) acc[k] = accumulate ? o[e * 6 + k] : 0.f;
            for (int b = 0; b < n_batch; ++b) {
                const float y = load_sample(samples, (size_t)(b * sample_stride + e), lut);
                for (int k = 0; k < 6; ++k) acc[k] += weights_t[(light_offset + b) * 6 + k] * y;
            }
            for (int k = 0; k < 6; ++k) o[e * 6 + k] = acc[k];
        }
        return;
    }
    float8 acc[6];
    if (accumulate) {
        const float8 a = vload8(0, o), b = vload8(1, o), c = vload8(2, o);
        const float8 d = vload8(3, o), f = vload8(4, o), g = vload8(5, o);
        acc[0] = (float8)(a.s0, a.s6, b.s4, c.s2, d.s0, d.s6, f.s4, g.s2);
        acc[1] = (float8)(a.s1, a.s7, b.s5, c.s3, d.s1, d.s7, f.s5, g.s3);
        acc[2] = (float8)(a.s2, b.s0, b.s6, c.s4, d.s2, f.s0, f.s6, g.s4);
        acc[3] = (float8)(a.s3, b.s1, b.s7, c.s5, d.s3, f.s1, f.s7, g.s5);
        acc[4] = (float8)(a.s4, b.s2, c.s0, c.s6, d.s4, f.s2, g.s0, g.s6);
        acc[5] = (float8)(a.s5, b.s3, c.s1, c.s7, d.s5, f.s3, g.s1, g.s7);
    } else {
        for (int k = 0; k < 6; ++k) acc[k] = (float8)(0.f);
    }
    __global const SAMPLE_T *row = samples;
    __constant float *w = weights_t + light_offset * 6;
    for (int b = 0; b < n_batch; ++b, row += sample_stride, w += 6) {
        const float8 y = load8(row, lut);
        acc[0] += w[0] * y;
        acc[1] += w[1] * y;
        acc[2] += w[2] * y;
        acc[3] += w[3] * y;
        acc[4] += w[4] * y;
        acc[5] += w[5] * y;
    }
    vstore8((float8)(acc[0].s0, acc[1].s0, acc[2].s0, acc[3].s0, acc[4].s0, acc[5].s0, acc[0].s1, acc[1].s1), 0, o);
    vstore8((float8)(acc[2].s1, acc[3].s1, acc[4].s1, acc[5].s1, acc[0].s2, acc[1].s2, acc[2].s2, acc[3].s2), 1, o);
    vstore8((float8)(acc[4].s2, acc[5].s2, acc[0].s3, acc[1].s3, acc[2].s3, acc[3].s3, acc[4].s3, acc[5].s3), 2, o);
    vstore8((float8)(acc[0].s4, acc[1].s4, acc[2].s4, acc[3].s4, acc[4].s4, acc[5].s4, acc[0].s5, acc[1].s5), 3, o);
    vstore8((float8)(acc[2].s5, acc[3].s5, acc[4].s5, acc[5].s5, acc[0].s6, acc[1].s6, acc[2].s6, acc[3].s6), 4, o);
    vstore8((float8)(acc[4].s6, acc[5].s6, acc[0].s7, acc[1].s7, acc[2].s7, acc[3].s7, acc[4].s7, acc[5].s7), 5, o);
}

// An lrgb PTM from the per-channel projections (kernel ptm_project): the luminance polynomial a is their channel
// mean, its energy over the lights a^T G a and its correlation with channel c a^T G s_c, with G = D^T D the Gram
// matrix of the design.  The colour is the non-negative least-squares scale per channel, kept in [0, 1] by
// moving any excess into the polynomial.  NumPy twin: finish_lrgb in model.py.
// sums: [n_texel, n_channel, 6] ; gram: [6, 6] ; coeffs out: [n_texel, 6] ; albedo out: [n_texel, n_channel]
__kernel void ptm_finish_lrgb(__global const float *sums, __constant float *gram, const int n_texel,
                              const int n_channel, __global float *coeffs, __global float *albedo)
{
    const int t = get_global_id(0);
    if (t >= n_texel) return;
    __global const float *s = sums + (size_t)t * n_channel * 6;
    float a[6], ga[6];
    const float inv_c = 1.0f / (float)n_channel;
    for (int k = 0; k < 6; ++k) {
        float m = 0.f;
        for (int c = 0; c < n_channel; ++c) m += s[c * 6 + k];
        a[k] = m * inv_c;
    }
    float pp = 0.f;
    for (int k = 0; k < 6; ++k) {
        float g = 0.f;
        for (int j = 0; j < 6; ++j) g += gram[j * 6 + k] * a[j];
        ga[k] = g;
        pp += a[k] * g;
    }
    float scale[4];  // lrgb takes at most 4 channels (checked on the host)
    float top = 0.f;
    for (int c = 0; c < n_channel; ++c) {
        float cross = 0.f;
        for (int k = 0; k < 6; ++k) cross += s[c * 6 + k] * ga[k];
        // A channel anti-correlated with the luminance polynomial (sparse highlights) would get a negative
        // colour, which no file format stores: the best non-negative scale is then 0.
        scale[c] = pp > 1e-20f ? fmax(cross / pp, 0.0f) : 1.0f;
        top = fmax(top, scale[c]);
    }
    const float norm = top > 1.0f ? top : 1.0f;
    for (int c = 0; c < n_channel; ++c) albedo[(size_t)t * n_channel + c] = scale[c] / norm;
    for (int k = 0; k < 6; ++k) coeffs[(size_t)t * 6 + k] = a[k] * norm;
}

// The sRGB curve sampled at SRGB_TABLE_STEPS + 1 points and interpolated: pow() costs more than the whole
// polynomial on CPU devices, and interpolation is exact to ~1e-8 on this smooth curve.
inline float srgb_decode(float value, __constant float *table) {
    const float x = clamp(value, 0.0f, 1.0f) * (float)SRGB_TABLE_STEPS;
    const int i = min((int)x, SRGB_TABLE_STEPS - 1);
    const float f = x - (float)i;
    return table[i] + f * (table[i + 1] - table[i]);
}

// coeffs: [n_texel, K, 6] ; albedo: [n_texel, C] (ignored unless K == 1) ; lights: [L, 3]
// out: [L, n_texel, C].  srgb != 0: the polynomial gives display values, clipped to [0, 1] and decoded to linear.
__kernel void ptm_eval(__global const float *coeffs, __global const float *albedo, __constant float *lights,
                       const int n_light, const int n_texel, const int n_channel, const int luminance,
                       const int srgb, __constant float *srgb_table, __global float *out)
{
    const int t = get_global_id(0);
    const int l = get_global_id(1);
    if (t >= n_texel || l >= n_light) return;
    const float u = lights[3 * l], v = lights[3 * l + 1];
    const float term[6] = {u * u, v * v, u * v, u, v, 1.0f};
    const int k_count = luminance ? 1 : n_channel;
    float poly[4];
    for (int k = 0; k < k_count; ++k) {
        float p = 0.f;
        for (int i = 0; i < 6; ++i) p += coeffs[((size_t)t * k_count + k) * 6 + i] * term[i];
        poly[k] = p;
    }
    for (int c = 0; c < n_channel; ++c) {
        float value = luminance ? albedo[(size_t)t * n_channel + c] * poly[0] : poly[c];
        value = fmax(value, 0.0f);
        if (srgb) value = srgb_decode(value, srgb_table);
        out[((size_t)l * n_texel + t) * n_channel + c] = value;
    }
}

// Scattered evaluation (for renderers): item i evaluates texel texels[i] of the model at its own light lights[i].
// coeffs: [n_model_texel, K, 6] ; albedo: [n_model_texel, C] (ignored unless K == 1) ; texels: [n] flat indices
// row * width + col ; lights: [n, 3] unit, in the texel's frame ; out: [n, C].  Same arithmetic as ptm_eval.
__kernel void ptm_eval_scattered(__global const float *coeffs, __global const float *albedo,
                                 __global const int *texels, __global const float *lights,
                                 const int n, const int n_channel, const int luminance,
                                 const int srgb, __constant float *srgb_table, __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const size_t t = (size_t)texels[i];
    const float u = lights[3 * (size_t)i], v = lights[3 * (size_t)i + 1];
    const float term[6] = {u * u, v * v, u * v, u, v, 1.0f};
    const int k_count = luminance ? 1 : n_channel;
    float poly[4];
    for (int k = 0; k < k_count; ++k) {
        float p = 0.f;
        for (int j = 0; j < 6; ++j) p += coeffs[(t * k_count + k) * 6 + j] * term[j];
        poly[k] = p;
    }
    for (int c = 0; c < n_channel; ++c) {
        float value = luminance ? albedo[t * n_channel + c] * poly[0] : poly[c];
        value = fmax(value, 0.0f);
        if (srgb) value = srgb_decode(value, srgb_table);
        out[(size_t)i * n_channel + c] = value;
    }
}
