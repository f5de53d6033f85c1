// Template images of a height field (Liu, Yu & Shum 2001, sec. 6.1): grey shading with attached and cast shadows,
// occlusion and foreshortening, seen orthographically and resampled into the texture frame (as a rectified BTF).
//
// For output texel (row, col) the camera ray passes through the reference-plane point (x = col, y = -row,
// z = z_ref).  It is marched downward from the highest height in 0.5-texel horizontal steps until it meets the
// (bilinear, wrapped) surface; the crossing is refined linearly.  The hit is shaded albedo * max(0, n . l), with
// n the bilinear normal, and marched toward the light for a cast shadow; the shadow march skips the samples that
// fall in a tile whose highest height is below the ray (they cannot occlude), which changes no result.  The NumPy twin is `render_numpy` in
// template.py and performs the same float32 operations.
#pragma OPENCL FP_CONTRACT OFF

inline int wrap_index(int index, int period)
{
    if (index >= 0 && index < period) {   // the common case, without an integer division
        return index;
    }
    int m = index % period;
    return m < 0 ? m + period : m;
}

// Bilinear sample of a [H, W, n] field at (col, row), wrapping; writes n values.
inline void bilinear(__global const float *field, int n, float col, float row, int H, int W, float *out)
{
    float col0 = floor(col);
    float row0 = floor(row);
    float fx = col - col0;
    float fy = row - row0;
    int c0 = wrap_index((int)col0, W);
    int r0 = wrap_index((int)row0, H);
    int c1 = (c0 + 1 == W) ? 0 : c0 + 1;
    int r1 = (r0 + 1 == H) ? 0 : r0 + 1;
    for (int i = 0; i < n; ++i) {
        float a = field[(r0 * W + c0) * n + i];
        float b = field[(r0 * W + c1) * n + i];
        float c = field[(r1 * W + c0) * n + i];
        float d = field[(r1 * W + c1) * n + i];
        float top = a + fx * (b - a);
        float bottom = c + fx * (d - c);
        out[i] = top + fy * (bottom - top);
    }
}

// Whether the shadow ray can skip ahead from step k: the highest height under the tile (TILE x TILE texels, the
// last row and column of tiles possibly narrower) holding the sample's bilinear cell is below the ray, so no sample
// in the tile can occlude (the ray only rises).  Returns the next step that may leave the tile (one early, so
// rounding never skips a step outside it), or k + 1 when the ray cannot skip (or does not rise).
inline int skip_tile(__global const float *tile_max, int tiles_w, int tile, float col, float row, float ray,
                     float4 lm, int k, int H, int W)
{
    const int c0 = wrap_index((int)floor(col), W);
    const int r0 = wrap_index((int)floor(row), H);
    const int tc = c0 / tile;
    const int tr = r0 / tile;
    const float top = tile_max[tr * tiles_w + tc];
    if (lm.z < 0.0f || !(ray > top + 1e-5f * (fabs(top) + 1.0f))) {
        return k + 1;
    }
    // the unwrapped position within the texel grid, and the steps left until floor(col) or floor(row) leaves
    // the tile's range [tc * tile, min((tc + 1) * tile, W) - 1]
    const float cw = (float)c0 + (col - floor(col));
    const float rw = (float)r0 + (row - floor(row));
    float steps = 1e30f;
    if (lm.x > 0.0f) {
        steps = fmin(steps, ((float)min((tc + 1) * tile, W) - cw) / lm.x);
    } else if (lm.x < 0.0f) {
        steps = fmin(steps, (cw - (float)(tc * tile)) / -lm.x);
    }
    if (lm.y > 0.0f) {
        steps = fmin(steps, ((float)min((tr + 1) * tile, H) - rw) / lm.y);
    } else if (lm.y < 0.0f) {
        steps = fmin(steps, (rw - (float)(tr * tile)) / -lm.y);
    }
    const float ahead = floor(steps) - 1.0f;
    return ahead >= 1.0f ? k + (int)fmin(ahead, (float)(1 << 24)) : k + 1;
}

// NDRange (W, H, S).  view_march[s] = (column step, row step, height step, number of steps) going down the
// camera ray; view_start[s] = (column offset, row offset, start height, vertical flag); light_march[s] =
// (column step, row step, rise, number of steps) toward the light; lights[s] = unit light (x, y, z, unused).
__kernel void render_template(
    __global const float *height,      // [H, W]
    __global const float *albedo,      // [H, W] grey
    __global const float *normals,     // [H, W, 3]
    __global const float4 *view_march,
    __global const float4 *view_start,
    __global const float4 *light_march,
    __global const float4 *lights,
    const int H, const int W,
    const float max_height,
    const float shadow_bias,
    __global const float *tile_max,    // [tiles_h, tiles_w] highest height of each tile's cells and their corners
    const int tiles_w, const int tile,
    __global float *image,             // [S, H, W]
    __global uchar *shadow)            // [S, H, W] 1 = attached or cast shadow
{
    const int col = get_global_id(0);
    const int row = get_global_id(1);
    const int s = get_global_id(2);
    if (col >= W || row >= H) {
        return;
    }
    const float4 vm = view_march[s];
    const float4 vs = view_start[s];
    float hit_col = (float)col;
    float hit_row = (float)row;
    float hit_z;
    float h;
    if (vs.w != 0.0f) {                      // straight down: the ray meets the surface under the texel
        bilinear(height, 1, hit_col, hit_row, H, W, &h);
        hit_z = h;
    } else {
        float c = (float)col + vs.x;
        float r = (float)row + vs.y;
        float z = vs.z;
        bilinear(height, 1, c, r, H, W, &h);
        float gap_prev = z - h;              // > 0 while the ray is above the surface
        float c_prev = c, r_prev = r, z_prev = z;
        const int n = (int)vm.w;
        int k = 1;
        for (; k <= n && gap_prev > 0.0f; ++k) {
            c_prev = c; r_prev = r; z_prev = z;
            const float kf = (float)k;
            c = (float)col + vs.x + kf * vm.x;
            r = (float)row + vs.y + kf * vm.y;
            z = vs.z + kf * vm.z;
            bilinear(height, 1, c, r, H, W, &h);
            const float gap = z - h;
            if (gap <= 0.0f) {
                const float f = gap_prev / (gap_prev - gap);
                c = c_prev + f * (c - c_prev);
                r = r_prev + f * (r - r_prev);
                z = z_prev + f * (z - z_prev);
                gap_prev = gap;
                break;
            }
            gap_prev = gap;
        }
        hit_col = c;
        hit_row = r;
        bilinear(height, 1, c, r, H, W, &h);
        hit_z = h;
    }
    float n3[3];
    float a;
    bilinear(normals, 3, hit_col, hit_row, H, W, n3);
    bilinear(albedo, 1, hit_col, hit_row, H, W, &a);
    const float norm = sqrt(n3[0] * n3[0] + n3[1] * n3[1] + n3[2] * n3[2]);
    const float4 l = lights[s];
    const float n_dot_l = (n3[0] * l.x + n3[1] * l.y + n3[2] * l.z) / norm;
    int dark = n_dot_l <= 0.0f;
    const float4 lm = light_march[s];
    const int n_light = (int)lm.w;
    for (int k = 1; !dark && k <= n_light;) {
        const float kf = (float)k;
        const float ray = hit_z + shadow_bias + kf * lm.z;
        if (ray >= max_height) {
            break;
        }
        const float c = hit_col + kf * lm.x;
        const float r = hit_row + kf * lm.y;
        const int next = skip_tile(tile_max, tiles_w, tile, c, r, ray, lm, k, H, W);
        if (next > k + 1) {      // samples k .. next - 1 lie in a tile wholly below the ray
            k = next;
            continue;
        }
        bilinear(height, 1, c, r, H, W, &h);
        if (h > ray) {
            dark = 1;
        }
        k = next;
    }
    const size_t o = (size_t)s * (size_t)(H * W) + (size_t)(row * W + col);
    image[o] = dark ? 0.0f : a * n_dot_l;
    shadow[o] = (uchar)dark;
}
