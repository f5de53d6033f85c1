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

// samples: [L, n_texel, C] ; solve: [6, L] (pseudo-inverse of the design matrix) ; design: [L, 6]
// coeffs out: [n_texel, K, 6] with K = C (rgb) or 1 (lrgb) ; albedo out: [n_texel, C] (lrgb only)
// Work-item t handles texel t of the outputs and texel (texel_offset + t) of the samples, so a launch can cover
// one band of a whole capture that is read in place.
__kernel void ptm_fit(__global const SAMPLE_T *samples_all, __constant float *lut,
                      __constant float *solve, __constant float *design,
                      const int n_light, const int sample_stride, const int texel_offset, const int n_texel,
                      const int n_channel, const int luminance,
                      __global float *coeffs, __global float *albedo)
{
    const int t = get_global_id(0);
    if (t >= n_texel) return;
    // Index samples as [L, sample_stride, C] from the band's first texel.
    __global const SAMPLE_T *samples = samples_all + (size_t)texel_offset * n_channel;
    if (!luminance) {
        for (int c = 0; c < n_channel; ++c) {
            float acc[6] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
            for (int l = 0; l < n_light; ++l) {
                const float y = load_sample(samples, ((size_t)l * sample_stride + t) * n_channel + c, lut);
                for (int k = 0; k < 6; ++k) acc[k] += solve[k * n_light + l] * y;
            }
            for (int k = 0; k < 6; ++k) coeffs[((size_t)t * n_channel + c) * 6 + k] = acc[k];
        }
        return;
    }
    // LRGB: fit the channel mean, then the least-squares colour scale of each channel against that polynomial.
    float acc[6] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
    const float inv_c = 1.0f / (float)n_channel;
    for (int l = 0; l < n_light; ++l) {
        float y = 0.f;
        for (int c = 0; c < n_channel; ++c) y += load_sample(samples, ((size_t)l * sample_stride + t) * n_channel + c, lut);
        y *= inv_c;
        for (int k = 0; k < 6; ++k) acc[k] += solve[k * n_light + l] * y;
    }
    float pp = 0.f;
    float cross[4] = {0.f, 0.f, 0.f, 0.f};  // channels beyond 4 are not supported by lrgb (checked on the host)
    for (int l = 0; l < n_light; ++l) {
        float p = 0.f;
        for (int k = 0; k < 6; ++k) p += design[l * 6 + k] * acc[k];
        pp += p * p;
        for (int c = 0; c < n_channel; ++c) cross[c] += p * load_sample(samples, ((size_t)l * sample_stride + t) * n_channel + c, lut);
    }
    float scale[4];
    float top = 0.f;
    for (int c = 0; c < n_channel; ++c) {
        // A channel anti-correlated with the luminance polynomial (sparse highlights) would get a negative
        // colour, which no file format stores: the best non-negative scale is then 0.
        scale[c] = pp > 1e-20f ? fmax(cross[c] / pp, 0.0f) : 1.0f;
        top = fmax(top, scale[c]);
    }
    // Keep the colour in [0, 1] (as file formats require) by moving any excess into the polynomial.
    const float norm = top > 1.0f ? top : 1.0f;
    for (int c = 0; c < n_channel; ++c) albedo[(size_t)t * n_channel + c] = scale[c] / norm;
    for (int k = 0; k < 6; ++k) coeffs[(size_t)t * 6 + k] = acc[k] * norm;
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
