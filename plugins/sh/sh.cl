// Double spherical harmonics (view x light): constrained least-squares solve and evaluation.
//
// The design matrix of one texel's samples is the Kronecker product of the view and light SH matrices, so
// its SVD is the Kronecker product of their SVDs (done once on the host).  Per texel-channel the host
// projects the samples on the left singular vectors (proj = U^T y, [r_v, r_l]); here we
//   sh_lambda: find by bisection the smallest lambda >= 0 with  sum_i (s_i p_i / (s_i^2 + lambda))^2 <= E,
//              and write the weights w_i = s_i p_i / (s_i^2 + lambda)   (the solution in the right-singular basis);
//   sh_solve:  rotate back, c[a, b] = sum_i sum_j Vv[a, i] w[i, j] Vl[b, j].
//   sh_eval:   f(v, l) = sum_a Yv[v, a] sum_b c[a, b] Yl[l, b], clipped at 0 (coefficients optionally 8-bit).
//
// Build options: -DMAX_RV=<r_v> (sh_solve) ; -DMAX_KV=<k_v> (sh_eval) ; -DQUANTIZED (sh_eval, uchar coefficients) ;
// model.BUILD_OPTIONS (every build).

#ifndef MAX_RV
#define MAX_RV 1
#endif
#ifndef MAX_KV
#define MAX_KV 1
#endif
// LAMBDA_SPAN (the bisection searches log2(lambda) in [log2(hi) - SPAN, log2(hi)]) and LAMBDA_ITERS come from
// model.BUILD_OPTIONS only, shared with the NumPy twin.
#if !defined(LAMBDA_SPAN) || !defined(LAMBDA_ITERS)
#error "build sh.cl with model.BUILD_OPTIONS"
#endif

// Energy of the solution at lambda, in units of the target (p_scaled = p / sqrt(E)).
inline float cls_energy(__global const float *p, __global const float *s, const int r, const float inv_root,
                        const float lambda)
{
    float g = 0.f;
    for (int i = 0; i < r; ++i) {
        if (!(s[i] > 0.f)) continue;    // a direction below RCOND: weight 0
        const float w = s[i] * (p[i] * inv_root) / (s[i] * s[i] + lambda);
        g += w * w;
    }
    return g;
}

// proj: [n, r] ; s: [r] (0 marks a direction below RCOND, whose weight is 0) ; root_target: [n] = sqrt(allowed energy) (0: black texel, +inf: no bound)
// lambda out: [n] ; weights out: [n, r]
__kernel void sh_lambda(__global const float *proj, __global const float *s, __global const float *root_target,
                        const int r, const int n, __global float *lambda_out, __global float *weights)
{
    const int t = get_global_id(0);
    if (t >= n) return;
    __global const float *p = proj + (size_t)t * r;
    __global float *w = weights + (size_t)t * r;
    const float root = root_target[t];
    if (!(root > FLT_MIN)) {            // nothing was measured (or the bound is zero): the zero function
        lambda_out[t] = 0.f;
        for (int i = 0; i < r; ++i) w[i] = 0.f;
        return;
    }
    const float inv_root = 1.0f / root;  // 0 when the bound is infinite: plain least squares
    float lambda = 0.f;
    if (cls_energy(p, s, r, inv_root, 0.f) > 1.0f) {
        // g(lambda) <= sum_i (s_i p_i)^2 / lambda^2, so this upper end satisfies the bound.
        float sp = 0.f;
        for (int i = 0; i < r; ++i) {
            const float q = s[i] > 0.f ? s[i] * p[i] * inv_root : 0.f;
            sp += q * q;
        }
        float hi = 0.5f * log2(sp);
        float lo = hi - LAMBDA_SPAN;
        if (cls_energy(p, s, r, inv_root, exp2(lo)) <= 1.0f) {
            hi = lo;                     // below 2^-40 of the bracket: as good as zero, but still inside the bound
        } else {
            for (int it = 0; it < LAMBDA_ITERS; ++it) {
                const float mid = 0.5f * (lo + hi);
                if (cls_energy(p, s, r, inv_root, exp2(mid)) <= 1.0f) hi = mid; else lo = mid;
            }
        }
        lambda = exp2(hi);
    }
    lambda_out[t] = lambda;
    for (int i = 0; i < r; ++i) w[i] = s[i] > 0.f ? s[i] * p[i] / (s[i] * s[i] + lambda) : 0.f;
}

// weights: [n, r_v * r_l] ; vv: [k_v, r_v] ; vl: [k_l, r_l] ; coeffs out: [n, k_v, k_l].  Global size (n, k_l).
__kernel void sh_solve(__global const float *weights, __global const float *vv, __global const float *vl,
                       const int r_v, const int r_l, const int k_v, const int k_l, const int n,
                       __global float *coeffs)
{
    const int t = get_global_id(0);
    const int b = get_global_id(1);
    if (t >= n || b >= k_l) return;
    __global const float *w = weights + (size_t)t * r_v * r_l;
    float tmp[MAX_RV];
    for (int i = 0; i < r_v; ++i) {
        float acc = 0.f;
        for (int j = 0; j < r_l; ++j) acc += w[i * r_l + j] * vl[b * r_l + j];
        tmp[i] = acc;
    }
    for (int a = 0; a < k_v; ++a) {
        float acc = 0.f;
        for (int i = 0; i < r_v; ++i) acc += vv[a * r_v + i] * tmp[i];
        coeffs[((size_t)t * k_v + a) * k_l + b] = acc;
    }
}

#ifdef QUANTIZED
#define COEFF_T uchar
#define COEFF(i, ab) ((float)coeffs[i] * scale[ab] + bias[ab])
#else
#define COEFF_T float
#define COEFF(i, ab) (coeffs[i])
#endif

// sum_b c[a, b] yl[b] for row a of one texel-channel's coefficients starting at `base`.
inline float sh_light_sum(__global const COEFF_T *coeffs, __global const float *scale, __global const float *bias,
                          const size_t base, const int a, const int k_l, __global const float *yl)
{
    float acc = 0.f;
    for (int b = 0; b < k_l; ++b) acc += COEFF(base + a * k_l + b, a * k_l + b) * yl[b];
    return acc;
}

// coeffs: [n_texel, C, k_v, k_l] ; scale, bias: [k_v, k_l] ; yv: [V, k_v] ; yl: [L, k_l]
// out: [V, L, n_texel, C].  Global size (n_texel, L).
__kernel void sh_eval(__global const COEFF_T *coeffs, __global const float *scale, __global const float *bias,
                      __global const float *yv, __global const float *yl,
                      const int k_v, const int k_l, const int n_view, const int n_light, const int n_texel,
                      const int n_channel, __global float *out)
{
    const int t = get_global_id(0);
    const int l = get_global_id(1);
    if (t >= n_texel || l >= n_light) return;
    float q[MAX_KV];
    for (int c = 0; c < n_channel; ++c) {
        const size_t base = ((size_t)t * n_channel + c) * k_v * k_l;
        for (int a = 0; a < k_v; ++a) q[a] = sh_light_sum(coeffs, scale, bias, base, a, k_l, yl + (size_t)l * k_l);
        for (int v = 0; v < n_view; ++v) {
            float acc = 0.f;
            for (int a = 0; a < k_v; ++a) acc += yv[v * k_v + a] * q[a];
            out[(((size_t)v * n_light + l) * n_texel + t) * n_channel + c] = fmax(acc, 0.0f);
        }
    }
}

// Scattered evaluation (for renderers): item i evaluates texel texels[i] with its own basis values yv[i] [k_v]
// and yl[i] [k_l] (the host evaluates the SH at each item's view and light).  out: [n, C].
__kernel void sh_eval_scattered(__global const COEFF_T *coeffs, __global const float *scale,
                                __global const float *bias, __global const int *texels,
                                __global const float *yv, __global const float *yl,
                                const int k_v, const int k_l, const int n, const int n_channel, __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    const size_t t = (size_t)texels[i];
    for (int c = 0; c < n_channel; ++c) {
        const size_t base = (t * n_channel + c) * k_v * k_l;
        float acc = 0.f;
        for (int a = 0; a < k_v; ++a)
            acc += yv[(size_t)i * k_v + a] * sh_light_sum(coeffs, scale, bias, base, a, k_l, yl + (size_t)i * k_l);
        out[(size_t)i * n_channel + c] = fmax(acc, 0.0f);
    }
}
