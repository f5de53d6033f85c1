// Per-texel Lafortune lobes: Levenberg-Marquardt fit (one work-item per texel and fitted signal) and evaluation.
// The algorithm, its constants and its guards are documented in model.py, whose NumPy twins follow this code.
//
// Model of one signal in a texel frame F (rows t, b, n):  value = max(uz, 0) * (rho + sum_i max(C_i . x, 0)^n_i),
// x = (ux vx, uy vy, uz vz), u and v the light and view in the frame.  Parameters q: q[0] = rho, lobe i at
// q[1 + 4i .. 3 + 4i] = (Cx, Cy, Cz) and q[4 + 4i] = ln n_i.
// Build options: -DNLOBE=k (lobes per fitted signal, 1..7), -DVW=w (samples per vector in the fit: 4, 8 or 16)
// and model.BUILD_OPTIONS (every constant).

#pragma OPENCL FP_CONTRACT OFF

#ifndef NLOBE
#define NLOBE 1
#endif
#define NP (1 + 4 * NLOBE)

// The constants (P_MAX, LOBE_CAP, CAP_DROP, T_CAP, B_MIN, LAM0, NU0, LAM_MIN, LAM_MAX, LAM_DEC, FTOL, GTOL, ETOL, ATOL,
// D_FLOOR, W_FLOOR, MAXC, N_DIRS, N_EXPS, RACE_ITER) come from model.BUILD_OPTIONS only, so the NumPy twins share them.
#if !defined(T_CAP) || !defined(W_FLOOR) || !defined(N_EXPS) || !defined(MAXC) || !defined(RACE_ITER)
#error "build lafortune.cl with model.BUILD_OPTIONS"
#endif
#define N_CAND (N_DIRS * N_EXPS)

inline void to_frame(const float *F, __global const float *d, float *out) {
    for (int i = 0; i < 3; ++i) out[i] = (F[3 * i] * d[0] + F[3 * i + 1] * d[1]) + F[3 * i + 2] * d[2];
}

inline float lobe_value(float cx, float cy, float cz, float n, const float *x) {
    const float b = (cx * x[0] + cy * x[1]) + cz * x[2];
    if (!(b > B_MIN)) return 0.0f;                // never a negative base to a non-integer power
    return exp(fmin(n * log(b), T_CAP));
}

// ----------------------------------------------------------------------------------------------- evaluation

// Texel t at light u and view w, both already in the texel's frame; writes its n_channel values to o.
// diffuse [n, 1 or C] ; lobes [n, K, 3] ; expo [n, K] ; colour [n, C] (lum)
inline void lafortune_texel(const size_t t, const float *u, const float *w, __global const float *diffuse,
                            __global const float *lobes, __global const float *expo, __global const float *colour,
                            const int n_channel, const int k_total, const int luminance, __global float *o)
{
    float x[3];
    for (int i = 0; i < 3; ++i) x[i] = u[i] * w[i];
    const float c = fmax(u[2], 0.0f);
    __global const float *lob = lobes + t * k_total * 3;
    __global const float *ex = expo + t * k_total;
    if (luminance) {
        float f = diffuse[t];
        for (int k = 0; k < k_total; ++k) f += lobe_value(lob[3 * k], lob[3 * k + 1], lob[3 * k + 2], ex[k], x);
        const float value = c * f;
        for (int ch = 0; ch < n_channel; ++ch) o[ch] = colour[t * n_channel + ch] * value;
    } else {
        const int per = k_total / n_channel;
        for (int ch = 0; ch < n_channel; ++ch) {
            float f = diffuse[t * n_channel + ch];
            for (int j = 0; j < per; ++j) {
                const int k = ch * per + j;
                f += lobe_value(lob[3 * k], lob[3 * k + 1], lob[3 * k + 2], ex[k], x);
            }
            o[ch] = c * f;
        }
    }
}

// frames [n, 9] (rows t, b, n) ; lights [L, 3], views [V, 3] in the surface frame ; out [V, L, n, C]
__kernel void lafortune_eval(__global const float *frames, __global const float *diffuse, __global const float *lobes,
                             __global const float *expo, __global const float *colour,
                             __global const float *lights, __global const float *views,
                             const int n_light, const int n_view, const int n_texel, const int n_channel,
                             const int k_total, const int luminance, __global float *out)
{
    const int t = get_global_id(0), l = get_global_id(1), v = get_global_id(2);
    if (t >= n_texel || l >= n_light || v >= n_view) return;
    float F[9];
    for (int i = 0; i < 9; ++i) F[i] = frames[(size_t)t * 9 + i];
    float u[3], w[3];
    to_frame(F, lights + 3 * l, u);
    to_frame(F, views + 3 * v, w);
    lafortune_texel(t, u, w, diffuse, lobes, expo, colour, n_channel, k_total, luminance,
                    out + (((size_t)v * n_light + l) * n_texel + t) * n_channel);
}

// Scattered evaluation (for renderers): item i evaluates texel texels[i] at its own light lights[i] and view
// views[i], both already turned into that texel's frame (by the host: one rotation per item).  out [n, C].
__kernel void lafortune_eval_scattered(__global const float *diffuse, __global const float *lobes,
                                       __global const float *expo, __global const float *colour,
                                       __global const int *texels, __global const float *lights,
                                       __global const float *views, const int n, const int n_channel,
                                       const int k_total, const int luminance, __global float *out)
{
    const int i = get_global_id(0);
    if (i >= n) return;
    float u[3], w[3];
    for (int j = 0; j < 3; ++j) {
        u[j] = lights[3 * (size_t)i + j];
        w[j] = views[3 * (size_t)i + j];
    }
    lafortune_texel((size_t)texels[i], u, w, diffuse, lobes, expo, colour, n_channel, k_total, luminance,
                    out + (size_t)i * n_channel);
}

// ----------------------------------------------------------------------------------------------- fit
//
// Inside the fit a lobe is held as (psi, alpha, p): C = exp(alpha / n) psi with max_j |psi_j| = 1, the lobe is
// exp(alpha + n ln(psi . x)).  State z[0] = rho, lobe i at z[1 + 5i .. 5 + 5i] = (psi_x, psi_y, psi_z, alpha, p).
// A step moves rho, per lobe the two psi components other than the largest (held at +-1), alpha and p.

#define NS (1 + 5 * NLOBE)

// Every pass over a texel's samples works on VW samples at once (OpenCL vectors: one work-item per texel leaves
// the CPU's SIMD lanes idle otherwise).  The host pads each texel's samples to whole blocks of VW with zero
// geometry and zero values, which add exactly 0 to every sum below.
#ifndef VW
#define VW 8
#endif
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define VF CAT(float, VW)
#define VI CAT(int, VW)
// Blocks are read as whole vectors: every block starts at a multiple of VW floats of a texel's rows, and every
// texel's rows at a multiple of VW floats of the buffer.  Conditional values are vector ?: (a select) and the
// exponent clamp a compare, which compile in place where select() and fmin() were calls into PoCL's library.
#define VLOAD(p) (*(__global const VF *)(p))
#define CLAMP_T(e) ((e) < T_CAP ? (e) : (VF)T_CAP)                  /* fmin(e, T_CAP), NaN -> T_CAP as fmin */

inline float hsum(const VF v) {
#if VW == 16
    const float8 v8 = v.lo + v.hi;
    const float4 v4 = v8.lo + v8.hi;
#elif VW == 8
    const float4 v4 = v.lo + v.hi;
#else
    const float4 v4 = v;
#endif
    const float2 v2 = v4.lo + v4.hi;
    return v2.x + v2.y;
}

inline float hmax(const VF v) {
#if VW == 16
    const float8 v8 = fmax(v.lo, v.hi);
    const float4 v4 = fmax(v8.lo, v8.hi);
#elif VW == 8
    const float4 v4 = fmax(v.lo, v.hi);
#else
    const float4 v4 = v;
#endif
    const float2 v2 = fmax(v4.lo, v4.hi);
    return fmax(v2.x, v2.y);
}

// The host lays out each texel's samples and their geometry contiguously, each quantity over the texel's
// S = B x VW (padded) samples in a row: block s of quantity q is at q * S + s * VW.
typedef struct {
    __global const float *samples;   // this texel's [C, S]
    __global const float *geom;      // this texel's [4, S]: x = (ux vx, uy vy, uz vz) and c = max(uz, 0)
    int n_channel, n_block, channel;   // channel < 0: the channel mean (luminance)
} Texel;

inline void geometry(const Texel *tx, int s, VF *x, VF *c) {
    __global const float *q = tx->geom + VW * s;
    const int stride = VW * tx->n_block;
    x[0] = VLOAD(q);
    x[1] = VLOAD(q + stride);
    x[2] = VLOAD(q + 2 * stride);
    *c = VLOAD(q + 3 * stride);
}

inline VF channel_values(const Texel *tx, int s, int ch) {
    return VLOAD(tx->samples + VW * (ch * tx->n_block + s));
}

inline VF load_y(const Texel *tx, int s) {
    if (tx->channel >= 0) return channel_values(tx, s, tx->channel);
    VF acc = 0.0f;
    for (int ch = 0; ch < tx->n_channel; ++ch) acc += channel_values(tx, s, ch);
    return acc / (float)tx->n_channel;
}

// A lobe exp(alpha + n ln(base)) of the VW bases, 0 where base <= B_MIN (never a negative base to a power).
inline VF lobe_block(const VF base, float alpha, float n) {
    const VI pos = base > B_MIN;
    const VF safe = pos ? base : (VF)1.0f;
    const VF e = alpha + n * log(safe);
    return pos ? exp(CLAMP_T(e)) : (VF)0.0f;
}

inline void exponents_of(const float *z, int k, float *nexp) {
    for (int i = 0; i < k; ++i) nexp[i] = exp(z[5 + 5 * i]);
}

inline VF state_lobe(const float *z, int i, float n, const VF *x) {
    const float *psi = z + 1 + 5 * i;
    return lobe_block((psi[0] * x[0] + psi[1] * x[1]) + psi[2] * x[2], psi[3], n);
}

inline VF model_at(const float *z, const float *nexp, int k, const VF *x, const VF c) {
    VF f = z[0];
    for (int i = 0; i < k; ++i) f += state_lobe(z, i, nexp[i], x);
    return c * f;
}

float normal_equations(const Texel *tx, const float *z, int k, const int *cols, float *H, float *g);

float cost_of(const Texel *tx, const float *z, int k) {
    return normal_equations(tx, z, k, 0, 0, 0);
}

// Lobe i's log cap: log_cap (the first lobe's) less CAP_DROP for every later lobe.
inline float lobe_log_cap(float log_cap, int i) { return i > 0 ? log_cap - CAP_DROP : log_cap; }

// rho >= 0 ; p in [0, ln 1000] ; psi renormalised to max |psi_j| = 1 (folded into alpha) ; alpha <= its lobe's
// log cap, so each lobe's peak over all directions, exp(alpha), stays below its cap x the brightest sample.

inline void project(float *z, int k, float log_cap) {
    z[0] = fmax(z[0], 0.0f);
    for (int i = 0; i < k; ++i) {
        float *l = z + 1 + 5 * i;
        l[4] = clamp(l[4], 0.0f, P_MAX);
        const float n = exp(l[4]);
        const float mx = fmax(fmax(fabs(l[0]), fabs(l[1])), fabs(l[2]));
        const int live = mx > B_MIN;
        const float msafe = live ? mx : 1.0f;
        for (int j = 0; j < 3; ++j) l[j] = l[j] / msafe;
        l[3] = fmin(l[3] + (live ? n * log(msafe) : 0.0f), lobe_log_cap(log_cap, i));
    }
}

// State index of each free parameter: rho, then per lobe the psi components other than the largest, alpha, p.
inline void free_columns(const float *z, int k, int *cols) {
    cols[0] = 0;
    for (int i = 0; i < k; ++i) {
        const float *l = z + 1 + 5 * i;
        int frozen = 0;
        if (fabs(l[1]) > fabs(l[frozen])) frozen = 1;
        if (fabs(l[2]) > fabs(l[frozen])) frozen = 2;
        cols[1 + 4 * i] = 1 + 5 * i + (frozen == 0 ? 1 : 0);
        cols[2 + 4 * i] = 1 + 5 * i + (frozen == 2 ? 1 : 2);
        cols[3 + 4 * i] = 4 + 5 * i;
        cols[4 + 4 * i] = 5 + 5 * i;
    }
}

// The error that decides between stage results: the signal's squared error (rgb), or the RGB error after the
// non-negative least-squares colour (lum; the colour is written to colour_out when given).
float criterion(const Texel *tx, const float *z, int k, float *colour_out) {
    if (tx->channel >= 0) return cost_of(tx, z, k);
    float nexp[NLOBE];
    exponents_of(z, k, nexp);
    VF ffv = 0.0f, fyv[MAXC];
    float colour[MAXC];
    for (int ch = 0; ch < MAXC; ++ch) fyv[ch] = 0.0f;
    for (int s = 0; s < tx->n_block; ++s) {
        VF x[3], c;
        geometry(tx, s, x, &c);
        const VF f = model_at(z, nexp, k, x, c);
        ffv += f * f;
        for (int ch = 0; ch < tx->n_channel; ++ch) fyv[ch] += f * channel_values(tx, s, ch);
    }
    const float ff = hsum(ffv);
    for (int ch = 0; ch < tx->n_channel; ++ch) colour[ch] = ff > 1e-30f ? fmax(hsum(fyv[ch]) / ff, 0.0f) : 1.0f;
    VF ssev = 0.0f;
    for (int s = 0; s < tx->n_block; ++s) {
        VF x[3], c;
        geometry(tx, s, x, &c);
        const VF f = model_at(z, nexp, k, x, c);
        for (int ch = 0; ch < tx->n_channel; ++ch) {
            const VF r = colour[ch] * f - channel_values(tx, s, ch);
            ssev += r * r;
        }
    }
    const float sse = hsum(ssev);
    if (colour_out)
        for (int ch = 0; ch < tx->n_channel; ++ch) colour_out[ch] = colour[ch];
    return sse;
}

// In-place Cholesky of the lower triangle of A (row stride NP), the reciprocal of each pivot on the diagonal
// (the solves multiply by it: a division on their critical path costs 3x a multiplication); 0 when a pivot
// is not positive.
inline int cholesky(float *A, int n) {
    for (int j = 0; j < n; ++j) {
        float s = A[j * NP + j];
        for (int m = 0; m < j; ++m) s -= A[j * NP + m] * A[j * NP + m];
        if (!(s > 0.0f)) return 0;
        const float inv = 1.0f / sqrt(s);
        A[j * NP + j] = inv;
        for (int i = j + 1; i < n; ++i) {
            float v = A[i * NP + j];
            for (int m = 0; m < j; ++m) v -= A[i * NP + m] * A[j * NP + m];
            A[i * NP + j] = v * inv;
        }
    }
    return 1;
}

inline void cholesky_solve(const float *A, const float *b, float *x, int n) {
    float y[NP];
    for (int i = 0; i < n; ++i) {
        float v = b[i];
        for (int m = 0; m < i; ++m) v -= A[i * NP + m] * y[m];
        y[i] = v * A[i * NP + i];
    }
    for (int i = n - 1; i >= 0; --i) {
        float v = y[i];
        for (int m = i + 1; m < n; ++m) v -= A[m * NP + i] * x[m];
        x[i] = v * A[i * NP + i];
    }
}

// One pass over the samples at state z: the cost |y - f(z)|^2 and, with H given, the normal equations H = J'J
// (lower triangle) and g = J'r of the 1 + 4k free parameters (their state indices in cols).  The calls with
// k = NLOBE and k = 1 (the last and the first lobe stage) are compiled with k known.  Each lobe's two free psi
// columns come straight from the x they multiply (psi_a: x[0] or x[1], psi_b: x[1] or x[2], the components
// other than the frozen largest), so no Jacobian entry is gathered.
inline __attribute__((always_inline))
float normal_equations_k(const Texel *tx, const float *z, const int k, const int *cols, float *H, float *g) {
    const int np = 1 + 4 * k;
    float nexp[NLOBE];
    int psi_a[NLOBE], psi_b[NLOBE];
    VF J[NP], Hv[NP * (NP + 1) / 2], gv[NP];
    exponents_of(z, k, nexp);
    if (H) {
        for (int i = 0; i < np * (np + 1) / 2; ++i) Hv[i] = 0.0f;
        for (int i = 0; i < np; ++i) gv[i] = 0.0f;
        for (int i = 0; i < k; ++i) {
            psi_a[i] = cols[1 + 4 * i] - (1 + 5 * i);
            psi_b[i] = cols[2 + 4 * i] - (1 + 5 * i);
        }
    }
    VF cost = 0.0f;
    for (int s = 0; s < tx->n_block; ++s) {
        VF x[3], c;
        geometry(tx, s, x, &c);
        J[0] = c;
        VF f = z[0];
        for (int i = 0; i < k; ++i) {
            const float *l = z + 1 + 5 * i;
            const VF b = (l[0] * x[0] + l[1] * x[1]) + l[2] * x[2];
            const VI pos = b > B_MIN;
            const VF safe = pos ? b : (VF)1.0f;
            const VF lb = log(safe);
            const VF e = l[3] + nexp[i] * lb;
            const VF v = pos ? exp(CLAMP_T(e)) : (VF)0.0f;
            f += v;
            if (!H) continue;
            const VI live = pos & (e <= T_CAP);                   // else no derivative
            const VF dpsi = live ? v * nexp[i] / safe : (VF)0.0f;
            J[1 + 4 * i] = c * (dpsi * (psi_a[i] == 0 ? x[0] : x[1]));
            J[2 + 4 * i] = c * (dpsi * (psi_b[i] == 1 ? x[1] : x[2]));
            J[3 + 4 * i] = c * (live ? v : (VF)0.0f);
            J[4 + 4 * i] = c * (live ? v * nexp[i] * lb : (VF)0.0f);
        }
        const VF r = load_y(tx, s) - c * f;
        cost += r * r;
        if (!H) continue;
        for (int a = 0, ab = 0; a < np; ++a) {
            gv[a] += J[a] * r;
            for (int b2 = 0; b2 <= a; ++b2, ++ab) Hv[ab] += J[a] * J[b2];
        }
    }
    if (H)
        for (int a = 0, ab = 0; a < np; ++a) {
            g[a] = hsum(gv[a]);
            for (int b2 = 0; b2 <= a; ++b2, ++ab) H[a * NP + b2] = hsum(Hv[ab]);
        }
    return hsum(cost);
}

float normal_equations(const Texel *tx, const float *z, int k, const int *cols, float *H, float *g) {
    if (k == NLOBE) return normal_equations_k(tx, z, NLOBE, cols, H, g);
    if (k == 1) return normal_equations_k(tx, z, 1, cols, H, g);
    return normal_equations_k(tx, z, k, cols, H, g);
}

// Each lobe's reach exp((cap - alpha) / n) at state z: how far |psi_j| may go before the lobe passes its cap.
inline void lobe_reach(const float *z, int k, float log_cap, float *reach) {
    for (int i = 0; i < k; ++i)
        reach[i] = exp(fmax(lobe_log_cap(log_cap, i) - z[4 + 5 * i], 0.0f) / exp(z[5 + 5 * i]));
}

// How far free parameter `col` may move by `d` before it leaves its box (rho >= 0, p in [0, P_MAX], alpha <=
// log_cap, and |psi_j| <= its lobe's reach: the lobe cap once psi is renormalised into alpha): d itself, or the
// move that lands it on the bound it would cross.
inline float clip_move(const float *z, int col, float d, float log_cap, const float *reach) {
    if (col == 0) return fmax(d, -z[0]);
    const int slot = (col - 1) % 5;
    if (slot == 4) return clamp(d, -z[col], P_MAX - z[col]);
    if (slot == 3) return fmin(d, lobe_log_cap(log_cap, (col - 1) / 5) - z[col]);
    const float r = reach[(col - 1) / 5];
    const float to = z[col] + d;
    return fabs(to) <= r ? d : copysign(r, to) - z[col];   // d itself unless it crosses (no rounding)
}

// The damped step (H + lam D) d = g inside the box: a parameter whose step would leave the box moves onto the
// bound it crosses (a parameter already there stays) and the others are solved again with that move fixed.
// Clipping the step instead (and projecting) left LM trying ever shorter steps against a bound that the
// other parameters did not know about.  Returns the gain the quadratic model predicts, 2 d'g - d'Hd (<= 0 when
// the box leaves no descent), or NaN when a Cholesky factorisation fails.  (Compiled with np known for the
// first and the last lobe stage: 5-10 % faster.)
inline __attribute__((always_inline))
float damped_step_n(const float *H, const float *g, const float *dg, float lam, const float *z, const int *cols,
                    const int np, float log_cap, const float *reach, float *delta) {
    float A[NP * NP], rhs[NP];
    int pinned[NP];
    for (int i = 0; i < np; ++i) pinned[i] = 0;
    for (int round = 0; round < 2; ++round) {
        for (int i = 0; i < np; ++i) {
            rhs[i] = g[i];
            for (int j = 0; round > 0 && j < np; ++j)             // nothing is pinned in the first round
                if (pinned[j] && j != i) rhs[i] -= (i > j ? H[i * NP + j] : H[j * NP + i]) * delta[j];
            for (int j = 0; j < i; ++j) A[i * NP + j] = (pinned[i] || pinned[j]) ? 0.0f : H[i * NP + j];
            A[i * NP + i] = pinned[i] ? 1.0f : H[i * NP + i] + lam * dg[i];
            if (pinned[i]) rhs[i] = delta[i];
        }
        if (!cholesky(A, np)) return NAN;
        cholesky_solve(A, rhs, delta, np);
        int more = 0;
        for (int i = 0; i < np; ++i) {
            const float d = clip_move(z, cols[i], delta[i], log_cap, reach);
            if (!pinned[i] && d != delta[i]) { pinned[i] = 1; delta[i] = d; more = 1; }
        }
        if (!more) break;
    }
    for (int i = 0; i < np; ++i) delta[i] = clip_move(z, cols[i], delta[i], log_cap, reach);
    float predicted = 0.0f;
    for (int i = 0; i < np; ++i) {
        float hd = 0.0f;
        for (int j = 0; j < np; ++j) hd += (i >= j ? H[i * NP + j] : H[j * NP + i]) * delta[j];
        predicted += delta[i] * (2.0f * g[i] - hd);
    }
    return predicted;
}

float damped_step(const float *H, const float *g, const float *dg, float lam, const float *z, const int *cols,
                  int np, float log_cap, const float *reach, float *delta) {
    if (np == NP) return damped_step_n(H, g, dg, lam, z, cols, NP, log_cap, reach, delta);
    if (np == 5) return damped_step_n(H, g, dg, lam, z, cols, 5, log_cap, reach, delta);
    return damped_step_n(H, g, dg, lam, z, cols, np, log_cap, reach, delta);
}

// Levenberg-Marquardt on the 1 + 4k free parameters of state z; only improving steps are taken.  Damped normal
// equations with Marquardt's scaling D = diag(H), solved by Cholesky; lam follows the gain ratio of actual to
// predicted reduction (Nielsen's trust-region rule: shrink by up to 3 on a good step, double the growth factor
// on every rejected one).  Each trial's pass also builds its normal equations, so an accepted step costs one
// pass.  Converged: an exact fit, a zero gradient, a Gauss-Newton step (damped by LAM_DEC only) that promises
// less than FTOL x cost - the Newton decrement, unlike a small gain of one step, is not fooled by short steps in
// a curved valley - or no descent left at all (lam > LAM_MAX).  Returns the steps tried; *cost_out the final
// cost, *converged whether a test was met.
int levenberg_marquardt(const Texel *tx, float *z, int k, float log_cap, float atol, float etol, int max_iter,
                        float *cost_out, int *converged) {
    const int np = 1 + 4 * k;
    float H[NP * NP], Ht[NP * NP], g[NP], gt[NP], dg[NP], delta[NP], trial[NS], reach[NLOBE];
    int cols[NP], cols_t[NP];
    free_columns(z, k, cols);
    float cost = normal_equations(tx, z, k, cols, H, g);
    float lam = LAM0, nu = NU0;
    int its = 0, conv = 0, fresh = 1;
    while (its < max_iter) {
        if (fresh) {
            float dmax = 0.0f;
            int zero = 1;
            for (int i = 0; i < np; ++i) {
                dmax = fmax(dmax, H[i * NP + i]);
                zero &= (g[i] == 0.0f);
            }
            for (int i = 0; i < np; ++i) dg[i] = fmax(H[i * NP + i], D_FLOOR * dmax);
            if (cost <= atol || zero) { conv = 1; break; }
            lobe_reach(z, k, log_cap, reach);
            const float decrement = damped_step(H, g, dg, LAM_DEC, z, cols, np, log_cap, reach, delta);
            if (decrement >= 0.0f && decrement <= FTOL * cost + etol) { conv = 1; break; }   // NaN compares false
            fresh = 0;
        }
        ++its;
        const float predicted = damped_step(H, g, dg, lam, z, cols, np, log_cap, reach, delta);
        float trial_cost = INFINITY;
        if (!isnan(predicted)) {
            for (int i = 0; i < 1 + 5 * k; ++i) trial[i] = z[i];
            for (int a = 0; a < np; ++a) trial[cols[a]] += delta[a];
            project(trial, k, log_cap);
            free_columns(trial, k, cols_t);
            trial_cost = normal_equations(tx, trial, k, cols_t, Ht, gt);
        }
        if (trial_cost < cost) {                  // NaN compares false: rejected
            const float ratio = predicted > 0.0f ? (cost - trial_cost) / predicted : 1.0f;
            const float q = 2.0f * ratio - 1.0f;
            lam = fmax(lam * fmax(1.0f / 3.0f, 1.0f - q * q * q), LAM_MIN);
            nu = NU0;
            for (int i = 0; i < 1 + 5 * k; ++i) z[i] = trial[i];
            for (int i = 0; i < np; ++i) {
                cols[i] = cols_t[i];
                g[i] = gt[i];
                for (int j = 0; j <= i; ++j) H[i * NP + j] = Ht[i * NP + j];
            }
            const int small = cost - trial_cost <= GTOL * cost + etol;
            cost = trial_cost;
            fresh = 1;
            if (small) { conv = 1; break; }
        } else {
            lam *= nu;
            nu *= 2.0f;
            if (lam > LAM_MAX) { conv = 1; break; }   // no descent left at this point: a stationary point
        }
    }
    *cost_out = cost;
    *converged = conv;
    return its;
}

// min over rho >= 0, 0 <= w <= wmax of |t - rho c - w g|^2, from the sums of products.
inline float nnls_box(float scc, float sgg, float scg, float sct, float sgt, float stt, float wmax, float *rho, float *w) {
#define BOX_COST(r, ww) (stt - 2 * (r) * sct - 2 * (ww) * sgt + (r) * (r) * scc + 2 * (r) * (ww) * scg + (ww) * (ww) * sgg)
    float br = 0.0f, bw = 0.0f, bc = INFINITY;
    const float det = scc * sgg - scg * scg;
    if (det > 1e-12f * scc * sgg && det > 0.0f) {
        const float r4 = (sgg * sct - scg * sgt) / det, w4 = (scc * sgt - scg * sct) / det;
        if (r4 >= 0.0f && w4 >= 0.0f && w4 <= wmax) {
            const float c4 = BOX_COST(r4, w4);
            if (c4 < bc) { br = r4; bw = w4; bc = c4; }
        }
    }
    const float r1 = scc > 0.0f ? fmax(sct / scc, 0.0f) : 0.0f;
    const float c1 = BOX_COST(r1, 0.0f);
    if (c1 < bc) { br = r1; bw = 0.0f; bc = c1; }
    const float w2 = sgg > 0.0f ? clamp(sgt / sgg, 0.0f, wmax) : 0.0f;
    const float c2 = BOX_COST(0.0f, w2);
    if (c2 < bc) { br = 0.0f; bw = w2; bc = c2; }
    const float r3 = scc > 0.0f ? fmax((sct - wmax * scg) / scc, 0.0f) : 0.0f;
    const float c3 = BOX_COST(r3, wmax);
    if (c3 < bc) { br = r3; bw = wmax; bc = c3; }
#undef BOX_COST
    *rho = br;
    *w = bw;
    return bc;
}

// samples [n_texel, C, B x VW] (sample s = view * L + light, zero-padded) ; geom [n_texel, 4, B x VW]
// (model.fit_geometry).  Work-item
// (t, signal): the luminance (luminance != 0, one signal) or channel `signal` (rgb).  Outputs per (texel,
// signal): diffuse [n, n_signal], lobes [n, n_signal * NLOBE, 3], exponents [n, n_signal * NLOBE], sse,
// iterations, not-converged flag [n, n_signal]; colour [n, C] for luminance.
__kernel void lafortune_fit(__global const float *samples, __global const float *geom,
                            __global const float *CAND_DIRS, __global const float *CAND_EXPS,
                            const int n_block, const int n_texel, const int n_channel,
                            const int luminance, const int max_iter, const int n_starts,
                            __global float *diffuse_out, __global float *lobes_out, __global float *expo_out,
                            __global float *colour_out, __global float *sse_out, __global int *iter_out,
                            __global int *flag_out)
{
    const int t = get_global_id(0), sig = get_global_id(1);
    if (t >= n_texel) return;
    const int n_signal = luminance ? 1 : n_channel;
    if (sig >= n_signal) return;
    Texel tx;
    tx.samples = samples + (size_t)t * n_block * n_channel * VW;
    tx.geom = geom + (size_t)t * n_block * 4 * VW;
    tx.n_channel = n_channel;
    tx.n_block = n_block;
    tx.channel = luminance ? -1 : sig;

    VF ymaxv = 0.0f, energyv = 0.0f, sccv = 0.0f, scyv = 0.0f;
    for (int s = 0; s < tx.n_block; ++s) {
        VF x[3], c;
        geometry(&tx, s, x, &c);
        const VF y = load_y(&tx, s);
        ymaxv = fmax(ymaxv, fabs(y));
        energyv += y * y;
        sccv += c * c;
        scyv += c * y;
    }
    const float ymax = hmax(ymaxv), energy = hsum(energyv), scc = hsum(sccv), scy = hsum(scyv);
    const float log_cap = log(LOBE_CAP * fmax(ymax, 1e-12f));
    const float atol = ATOL * energy, etol = ETOL * energy;

    float z[NS], start[NS], best[NS];
    for (int i = 0; i < NS; ++i) z[i] = 0.0f;
    z[0] = scc > 0.0f ? fmax(scy / scc, 0.0f) : 0.0f;
    float colour[MAXC], trial_colour[MAXC];   // the lum colour of the kept fit (criterion's by-product)
    float crit = criterion(&tx, z, 0, colour);
    int flag = 0, its_total = 0;
    ulong used = 0ul;

    for (int k = 1; k <= NLOBE; ++k) {
        const int j = k - 1;
        // Score every start shape against the residual of the earlier lobes (rho and amplitude in closed form).
        float nexp[NLOBE];
        exponents_of(z, j, nexp);
        // Per start shape g = c b^n: sum g^2 = sum c^2 b^(2n) is the sum c^2 b^n two rungs up the ladder, so
        // two sums per rung (two more rungs at the top) give all three products the box fit needs.
        VF sttv = 0.0f, sctv = 0.0f, sccb[N_CAND + 2 * N_DIRS], sctb[N_CAND];
        float ccost[N_CAND], crho[N_CAND], cw[N_CAND];
        for (int ci = 0; ci < N_CAND + 2 * N_DIRS; ++ci) sccb[ci] = 0.0f;
        for (int ci = 0; ci < N_CAND; ++ci) sctb[ci] = 0.0f;
        for (int s = 0; s < tx.n_block; ++s) {
            VF x[3], c;
            geometry(&tx, s, x, &c);
            VF prev = 0.0f;
            for (int i = 0; i < j; ++i) prev += state_lobe(z, i, nexp[i], x);
            const VF target = load_y(&tx, s) - c * prev;
            sttv += target * target;
            sctv += c * target;
            const VF cc = c * c, ct = c * target;
            for (int di = 0; di < N_DIRS; ++di) {
                const VF b = (CAND_DIRS[3 * di] * x[0] + CAND_DIRS[3 * di + 1] * x[1]) + CAND_DIRS[3 * di + 2] * x[2];
                // The shape is 0 where b <= B_MIN (as lobe_value gives) or c = 0: those samples add exactly 0.
                const VF base = ((b > B_MIN) & (c != 0.0f)) ? b : (VF)0.0f;
                // The exponent ladder 1, 1.5, 2, 3, 4, 6, ... (model.CANDIDATE_EXPONENTS) by squaring alone:
                // b^(2n) = (b^n)^2, so the whole grid costs one sqrt and no exp or log.
                VF even = base, odd = base * sqrt(base);
#pragma unroll
                for (int ei = 0; ei < N_EXPS + 2; ++ei) {
                    const int ci = ei * N_DIRS + di;
                    VF power;
                    if (ei & 1) { power = odd; odd = odd * odd; }
                    else { power = even; even = even * even; }
                    sccb[ci] += cc * power;
                    if (ei < N_EXPS) sctb[ci] += ct * power;
                }
            }
        }
        const float stt = hsum(sttv), sct = hsum(sctv), wmax = exp(lobe_log_cap(log_cap, j));
        for (int ci = 0; ci < N_CAND; ++ci) {
            ccost[ci] = nnls_box(scc, hsum(sccb[ci + 2 * N_DIRS]), hsum(sccb[ci]), sct, hsum(sctb[ci]), stt, wmax,
                                 &crho[ci], &cw[ci]);
            if ((used >> ci) & 1ul) ccost[ci] = INFINITY;
        }
        // Starts: the best shape not tried yet; after the first, the best broader one (lower exponent) if any.
        float lowest = INFINITY, best_cost = INFINITY;
        int best_conv = 0, best_ci = 0;
        const int starts = k == 1 ? n_starts : 1;
        for (int attempt = 0; attempt < starts; ++attempt) {
            int ci = -1, cb = -1;
            for (int cj = 0; cj < N_CAND; ++cj) {
                if (!(ccost[cj] < INFINITY)) continue;
                if (ci < 0 || ccost[cj] < ccost[ci]) ci = cj;
                if (CAND_EXPS[cj / N_DIRS] < lowest && (cb < 0 || ccost[cj] < ccost[cb])) cb = cj;
            }
            if (cb >= 0) ci = cb;
            if (ci < 0) break;
            ccost[ci] = INFINITY;
            const int di = ci % N_DIRS, ei = ci / N_DIRS;
            lowest = fmin(lowest, CAND_EXPS[ei]);
            const float w0 = fmax(cw[ci], W_FLOOR * ymax);
            for (int i = 0; i < NS; ++i) start[i] = z[i];
            start[0] = crho[ci];
            for (int d = 0; d < 3; ++d) start[1 + 5 * j + d] = w0 > 0.0f ? CAND_DIRS[3 * di + d] : 0.0f;
            start[4 + 5 * j] = log(w0 > 0.0f ? w0 : 1.0f);
            start[5 + 5 * j] = log(CAND_EXPS[ei]);
            project(start, k, log_cap);
            int conv = 0;
            float cost = 0.0f;
            // With several starts each gets RACE_ITER steps and only the best is refined further.
            const int budget = starts > 1 ? min(max_iter, RACE_ITER) : max_iter;
            its_total += levenberg_marquardt(&tx, start, k, log_cap, atol, etol, budget, &cost, &conv);
            if (attempt == 0 || cost < best_cost) {
                for (int i = 0; i < NS; ++i) best[i] = start[i];
                best_cost = cost;
                best_conv = conv;
                best_ci = ci;
            }
        }
        if (!best_conv && starts > 1 && max_iter > RACE_ITER)
            its_total += levenberg_marquardt(&tx, best, k, log_cap, atol, etol, max_iter - RACE_ITER, &best_cost,
                                             &best_conv);
        used |= 1ul << best_ci;
        const float new_crit = criterion(&tx, best, k, trial_colour);
        if (new_crit < crit) {                     // else keep k - 1 lobes, this one switched off (psi = 0)
            for (int i = 0; i < NS; ++i) z[i] = best[i];
            for (int ch = 0; ch < MAXC; ++ch) colour[ch] = trial_colour[ch];
            crit = new_crit;
            flag = !best_conv;
        }
    }

    const int k_total = NLOBE * n_signal;
    diffuse_out[(size_t)t * n_signal + sig] = z[0];
    for (int i = 0; i < NLOBE; ++i) {
        const size_t k = (size_t)t * k_total + sig * NLOBE + i;
        const float *l = z + 1 + 5 * i;
        const float n = exp(l[4]);
        const float scale = exp(l[3] / n);
        for (int d = 0; d < 3; ++d) lobes_out[k * 3 + d] = scale * l[d];
        expo_out[k] = n;
    }
    if (luminance)
        for (int ch = 0; ch < n_channel; ++ch) colour_out[(size_t)t * n_channel + ch] = colour[ch];
    sse_out[(size_t)t * n_signal + sig] = crit;
    iter_out[(size_t)t * n_signal + sig] = its_total;
    flag_out[(size_t)t * n_signal + sig] = flag;
}
