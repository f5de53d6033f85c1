// Height from shading (Liu, Yu & Shum 2001, eq. 5): per-texel energy terms and the gradient they give.
//
// `hfs_terms` evaluates, at every interior texel, the robust Lambertian data term over the K samples, the
// edge-weighted second-difference smoothness of the height and the second-difference smoothness of the albedo,
// and leaves the partial derivatives with respect to the texel's own finite differences.  `hfs_gather` adds,
// for every texel, the partials of the differences it takes part in: the gradient of the energy.  The NumPy twin
// (`terms_numpy`, `gather_numpy` in sfs.py) does the same float32 arithmetic.
#pragma OPENCL FP_CONTRACT OFF

inline int interior(int row, int col, int H, int W)
{
    return row > 0 && col > 0 && row < H - 1 && col < W - 1;
}

// NDRange (W, H).  Frame: x = column, y = -row, z up; p = dz/dx, q = dz/dy by central differences.
__kernel void hfs_terms(
    __global const float *z,        // [H, W] heights
    __global const float *rho,      // [H, W] grey albedo
    __global const float *image,    // [K, H, W] grey intensities
    __global const float *eta,      // [K, H, W] robust sample weights
    __global const float4 *lights,  // [K] unit, toward the light
    __global const float *mu,       // [H, W] smoothness weights
    const int H, const int W, const int K,
    const float alpha_per_sample,   // alpha / K
    const float lambda_, const float gamma_,
    __global float *energy,         // [H, W] out: the texel's energy
    __global float *gp, __global float *gq,   // dE/dp, dE/dq
    __global float *gu, __global float *gv,   // dE/du, dE/dv (height second differences)
    __global float *grho,                     // dE/drho through the data term
    __global float *gs, __global float *gt)   // dE/ds, dE/dt (albedo second differences)
{
    const int col = get_global_id(0);
    const int row = get_global_id(1);
    if (col >= W || row >= H) {
        return;
    }
    const int t = row * W + col;
    if (!interior(row, col, H, W)) {
        energy[t] = 0.0f; gp[t] = 0.0f; gq[t] = 0.0f; gu[t] = 0.0f; gv[t] = 0.0f;
        grho[t] = 0.0f; gs[t] = 0.0f; gt[t] = 0.0f;
        return;
    }
    const float zc = z[t];
    const float p = 0.5f * (z[t + 1] - z[t - 1]);
    const float q = 0.5f * (z[t - W] - z[t + W]);
    const float inv_s = 1.0f / sqrt(1.0f + p * p + q * q);
    const float r = rho[t];
    float e_data = 0.0f, d_p = 0.0f, d_q = 0.0f, d_rho = 0.0f;
    for (int k = 0; k < K; ++k) {
        const float4 l = lights[k];
        const size_t s = (size_t)k * (size_t)(H * W) + (size_t)t;
        const float w = eta[s];
        const float shade = (-p * l.x - q * l.y + l.z) * inv_s;
        const float residual = r * shade - image[s];
        const float wr = w * residual;
        e_data += wr * residual;
        d_rho += wr * shade;
        // dR/dp = -l.x / s - R p / s^2, and alike for q
        const float common = wr * r * inv_s;
        d_p += common * (-l.x - shade * p * inv_s);
        d_q += common * (-l.y - shade * q * inv_s);
    }
    const float u = z[t + 1] - 2.0f * zc + z[t - 1];
    const float v = z[t + W] - 2.0f * zc + z[t - W];
    const float su = rho[t + 1] - 2.0f * r + rho[t - 1];
    const float sv = rho[t + W] - 2.0f * r + rho[t - W];
    const float lm = lambda_ * mu[t];
    energy[t] = alpha_per_sample * e_data + lm * (u * u + v * v) + gamma_ * (su * su + sv * sv);
    gp[t] = 2.0f * alpha_per_sample * d_p;
    gq[t] = 2.0f * alpha_per_sample * d_q;
    grho[t] = 2.0f * alpha_per_sample * d_rho;
    gu[t] = 2.0f * lm * u;
    gv[t] = 2.0f * lm * v;
    gs[t] = 2.0f * gamma_ * su;
    gt[t] = 2.0f * gamma_ * sv;
}

// NDRange (W, H).  Terms are zero off the interior, so neighbours outside it contribute nothing.
__kernel void hfs_gather(
    __global const float *gp, __global const float *gq,
    __global const float *gu, __global const float *gv,
    __global const float *grho, __global const float *gs, __global const float *gt,
    const int H, const int W,
    __global float *grad_z, __global float *grad_rho)
{
    const int col = get_global_id(0);
    const int row = get_global_id(1);
    if (col >= W || row >= H) {
        return;
    }
    const int t = row * W + col;
    const int has_l = col > 0, has_r = col < W - 1, has_u = row > 0, has_d = row < H - 1;
    // p(i, j) = (z[i, j+1] - z[i, j-1]) / 2 and q(i, j) = (z[i-1, j] - z[i+1, j]) / 2
    float g = 0.0f;
    if (has_l) { g += 0.5f * gp[t - 1] + gu[t - 1]; }
    if (has_r) { g += -0.5f * gp[t + 1] + gu[t + 1]; }
    if (has_d) { g += 0.5f * gq[t + W] + gv[t + W]; }
    if (has_u) { g += -0.5f * gq[t - W] + gv[t - W]; }
    g += -2.0f * (gu[t] + gv[t]);
    grad_z[t] = g;
    float a = grho[t] - 2.0f * (gs[t] + gt[t]);
    if (has_l) { a += gs[t - 1]; }
    if (has_r) { a += gs[t + 1]; }
    if (has_u) { a += gt[t - W]; }
    if (has_d) { a += gt[t + W]; }
    grad_rho[t] = a;
}
