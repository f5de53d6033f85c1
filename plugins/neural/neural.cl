// Relighting a NeuralModel: each work-item runs the decoder on the codes of 8 texels (model.py has the formulas).
//
//   harmonics decoder: the network once per texel gives its coefficients c[p, ch]; at light l the display value
//                      is sum_p basis[l, p] c[p, ch];
//   light decoder:     the first layer's code part once per texel, its light part (host: features @ W1[K:] + b1)
//                      added per light, then the rest of the network per light.
//
// The value is clipped to [0, 1] (fmin / fmax: a NaN becomes 0) and decoded from sRGB to linear radiance.
// Twin: NeuralModel.evaluate with engine="numpy".
//
// net: every layer's weights output-major (row o holds the inputs of unit o), then its biases; layer i starts at
// offsets[i]; sizes[0 .. N_LAYERS] are the unit counts (sizes[0] the inputs).
// Build options: -DN_LAYERS=<weight layers> -DMAX_UNITS=<widest layer> and -DHARMONICS for the harmonics decoder.

#if !defined(N_LAYERS) || !defined(MAX_UNITS)
#error "build neural.cl with -DN_LAYERS and -DMAX_UNITS"
#endif
#ifdef HARMONICS
#define FIRST_LAYER 0
#else
#define FIRST_LAYER 1   // the first layer is split into a code part and a light part
#endif

// A work-item relights LANES consecutive texels at once, as the lanes of a float8: every weight read from memory
// serves all of them, and the products are vector instructions.
#define LANES 8
typedef float8 lanes;

inline lanes elu(const lanes x)
{
    return select(expm1(x), x, x > 0.0f);
}

inline lanes display_to_linear(const lanes value)
{
    const lanes x = fmin(fmax(value, 0.0f), 1.0f);
    return select(powr((x + 0.055f) / 1.055f, 2.4f), x / 12.92f, x <= 0.04045f);
}

inline void store(__global float *out, const size_t at, const int stride, const lanes v)
{
    out[at] = v.s0; out[at + stride] = v.s1; out[at + 2 * stride] = v.s2; out[at + 3 * stride] = v.s3;
    out[at + 4 * stride] = v.s4; out[at + 5 * stride] = v.s5; out[at + 6 * stride] = v.s6; out[at + 7 * stride] = v.s7;
}

// One layer: out[o] = sum_j w[o, j] in[j] + b[o], ELU unless it is the output layer.
inline void dense(__global const float *net, __global const int *offsets, __global const int *sizes, const int i,
                  const lanes *in, lanes *out)
{
    const int n_in = sizes[i], n_out = sizes[i + 1];
    __global const float *w = net + offsets[i];
    __global const float *b = w + n_in * n_out;
    for (int o = 0; o < n_out; ++o) {
        lanes sum = (lanes)(b[o]);
        for (int j = 0; j < n_in; ++j) sum += w[o * n_in + j] * in[j];
        out[o] = i < N_LAYERS - 1 ? elu(sum) : sum;
    }
}

// Layers first .. N_LAYERS - 1 from a, alternating between a and b; the output ends in a or b by parity.
inline void run_layers(__global const float *net, __global const int *offsets, __global const int *sizes,
                       const int first, lanes *a, lanes *b)
{
    for (int i = first; i < N_LAYERS; ++i) {
        if ((i - first) % 2 == 0) dense(net, offsets, sizes, i, a, b);
        else dense(net, offsets, sizes, i, b, a);
    }
}

// codes: [K, n_padded] (texel-minor, n_padded a multiple of LANES); light_part: [n_light, sizes[1]] (light
// decoder); basis: [n_light, P] (harmonics decoder); out: [n_light, n_padded, C] linear radiance.
__kernel void neural_relight(__global const float *codes, __global const float *net, __global const int *offsets,
                             __global const int *sizes, __global const float *light_part,
                             __global const float *basis, const int k, const int n_padded, const int n_light,
                             const int n_channel, __global float *out)
{
    const int t = get_global_id(0) * LANES;
    if (t >= n_padded) return;
    lanes a[MAX_UNITS], b[MAX_UNITS];
    const int last_in_a = (N_LAYERS - FIRST_LAYER) % 2 == 0;   // where run_layers leaves the output
#ifdef HARMONICS
    for (int j = 0; j < k; ++j) a[j] = vload8(0, codes + (size_t)j * n_padded + t);
    run_layers(net, offsets, sizes, 0, a, b);
    const lanes *coeffs = last_in_a ? a : b;
    const int n_coeff = sizes[N_LAYERS] / n_channel;
    for (int l = 0; l < n_light; ++l) {
        __global const float *y = basis + (size_t)l * n_coeff;
        for (int ch = 0; ch < n_channel; ++ch) {
            lanes value = 0.0f;
            for (int p = 0; p < n_coeff; ++p) value += y[p] * coeffs[p * n_channel + ch];
            store(out, ((size_t)l * n_padded + t) * n_channel + ch, n_channel, display_to_linear(value));
        }
    }
#else
    lanes code_part[MAX_UNITS], code[MAX_UNITS];
    const int n_in = sizes[0], n_hidden = sizes[1];
    for (int j = 0; j < k; ++j) code[j] = vload8(0, codes + (size_t)j * n_padded + t);
    for (int o = 0; o < n_hidden; ++o) {
        lanes sum = 0.0f;
        for (int j = 0; j < k; ++j) sum += net[o * n_in + j] * code[j];
        code_part[o] = sum;
    }
    for (int l = 0; l < n_light; ++l) {
        __global const float *light = light_part + (size_t)l * n_hidden;
        for (int o = 0; o < n_hidden; ++o) a[o] = elu(code_part[o] + light[o]);
        run_layers(net, offsets, sizes, 1, a, b);
        const lanes *value = last_in_a ? a : b;
        for (int ch = 0; ch < n_channel; ++ch)
            store(out, ((size_t)l * n_padded + t) * n_channel + ch, n_channel, display_to_linear(value[ch]));
    }
#endif
}
