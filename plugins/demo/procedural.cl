// Lambertian shading with cast shadows of a tileable height field, one work-item per (texel, light).
//
// The NumPy reference `render_lights_numpy` in procedural.py performs the same float32 operations in the same
// order, so the two agree bit for bit except where the compiler rounds differently.  Fused multiply-adds would
// change the rounding of every `a * b + c` below, hence contraction is switched off.
#pragma OPENCL FP_CONTRACT OFF

// Euclidean remainder: lookups wrap around because the height field is periodic (tileable).
inline int wrap_index(int index, int period)
{
    int m = index % period;
    return m < 0 ? m + period : m;
}

// Bilinear height at texel coordinates (col, row); texel centres sit on integers.  The lerp form returns the
// exact stored value on a constant patch, so a flat field never shadows itself through rounding.
inline float height_bilinear_wrapped(__global const float *height, float col, float row, int H, int W)
{
    float col0 = floor(col);
    float row0 = floor(row);
    float fx = col - col0;
    float fy = row - row0;
    int c0 = wrap_index((int)col0, W);
    int r0 = wrap_index((int)row0, H);
    int c1 = (c0 + 1 == W) ? 0 : c0 + 1;
    int r1 = (r0 + 1 == H) ? 0 : r0 + 1;
    float h00 = height[r0 * W + c0];
    float h01 = height[r0 * W + c1];
    float h10 = height[r1 * W + c0];
    float h11 = height[r1 * W + c1];
    float top = h00 + fx * (h01 - h00);
    float bottom = h10 + fx * (h11 - h10);
    return top + fy * (bottom - top);
}

// NDRange (W, H, n_lights).  `march[l]` = (column step, row step, ray rise per step, unused) for light l, and
// `max_steps[l]` bounds its march (0 for a light at the zenith); both are precomputed on the host so the
// kernel and the NumPy reference walk the identical sequence of sample points.
__kernel void render_procedural(
    __global const float *height,     // [H, W]
    __global const float *albedo,     // [H, W, 3]
    __global const float *normals,    // [H, W, 3]
    __global const float4 *lights,    // [n_lights] (x, y, z, unused), unit, z up
    __global const float4 *march,     // [n_lights]
    __global const int *max_steps,    // [n_lights]
    const int H,
    const int W,
    const float max_height,
    const float ambient,
    const int shadows,
    __global float *out)              // [n_lights, H, W, 3]
{
    const int col = get_global_id(0);
    const int row = get_global_id(1);
    const int light = get_global_id(2);
    if (col >= W || row >= H) {
        return;
    }
    const size_t texel = (size_t)row * (size_t)W + (size_t)col;
    const float4 l = lights[light];

    const float n_dot_l = normals[3 * texel] * l.x + normals[3 * texel + 1] * l.y + normals[3 * texel + 2] * l.z;
    const float lit = n_dot_l > 0.0f ? n_dot_l : 0.0f;

    float visibility = 1.0f;
    // An unlit texel stays dark whatever its visibility, so only lit texels pay for the march.
    if (shadows != 0 && lit > 0.0f) {
        const float4 step = march[light];
        const int n_steps = max_steps[light];
        const float h0 = height[texel];
        const float col_f = (float)col;
        const float row_f = (float)row;
        for (int k = 1; k <= n_steps; ++k) {
            const float kf = (float)k;
            const float ray = kf * step.z + h0;
            if (ray >= max_height) {
                break;  // nothing in the field is higher than the ray from here on
            }
            const float terrain = height_bilinear_wrapped(height, kf * step.x + col_f, kf * step.y + row_f, H, W);
            if (terrain > ray) {
                visibility = 0.0f;
                break;
            }
        }
    }

    const float shade = ambient + lit * visibility;
    const size_t o = ((size_t)light * (size_t)H * (size_t)W + texel) * 3;
    out[o] = albedo[3 * texel] * shade;
    out[o + 1] = albedo[3 * texel + 1] * shade;
    out[o + 2] = albedo[3 * texel + 2] * shade;
}
