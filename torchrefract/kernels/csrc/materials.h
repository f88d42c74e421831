/* Roughness maps (optics/materials.py, optics/textures.py): a view's roughness at a UV, as
 * the tensor code computes it, for the fused kernels (frame.h) and for roughness_at over a
 * batch of points (materials.c). */

#ifndef TORCHREFRACT_MATERIALS_H
#define TORCHREFRACT_MATERIALS_H

#include "common.h"

#include <math.h>

/* (i + n) % n for i in [-1, n + 1] (the padded image's index less one), without a division. */
static inline int64_t wrap_index(int64_t i, int64_t n) {
    return i < 0 ? i + n : (i >= n ? i - n : i);
}

/* textures.sample_uv: bilinear, wrapping in u and v (v = 0 at the image's bottom), through
 * the circularly padded image and grid_sample's steps (align_corners, border), op for op
 * as torch's CPU kernel takes them: the location's round trip and clamp, the four corners'
 * weights from the distances to the sides, their sum fused (the same bits as torch where
 * its kernel is compiled with FMA; a corner past the padded image reads 0 at weight 0). */
static inline float sample_uv(const float *tex, int64_t h, int64_t w, float u, float v) {
    float x = (u - floorf(u)) * (float)w - 0.5f;
    float y = 1.0f - v;
    y = (y - floorf(y)) * (float)h - 0.5f;
    float gx = 2.0f * (x + 1.0f) / (float)(w + 1) - 1.0f;
    float gy = 2.0f * (y + 1.0f) / (float)(h + 1) - 1.0f;
    /* fmaxf first: a NaN location clamps to 0, as torch's clamp_min(0, x) takes it */
    float px = fminf((float)(w + 1), fmaxf(0.0f, (gx + 1.0f) * ((float)(w + 1) / 2.0f)));
    float py = fminf((float)(h + 1), fmaxf(0.0f, (gy + 1.0f) * ((float)(h + 1) / 2.0f)));
    float xw = floorf(px), yn = floorf(py);
    int64_t x0 = (int64_t)xw, y0 = (int64_t)yn, x1 = x0 + 1, y1 = y0 + 1;
    float dw = px - xw, de = 1.0f - dw, dn = py - yn, ds = 1.0f - dn;
    float nw = ds * de, ne = ds * dw, sw = dn * de, se = dn * dw;
    /* the padded image's (row, column) r, c is the map's (r - 1, c - 1), wrapped */
    int64_t c0 = wrap_index(x0 - 1, w), c1 = wrap_index(x1 - 1, w);
    int64_t r0 = wrap_index(y0 - 1, h), r1 = wrap_index(y1 - 1, h);
    int in_e = x1 <= w + 1, in_s = y1 <= h + 1;
    float v_nw = tex[r0 * w + c0], v_ne = in_e ? tex[r0 * w + c1] : 0.0f;
    float v_sw = in_s ? tex[r1 * w + c0] : 0.0f;
    float v_se = in_e && in_s ? tex[r1 * w + c1] : 0.0f;
    return fmaf(v_se, se, fmaf(v_sw, sw, fmaf(v_ne, ne, v_nw * nw)));
}

/* materials.roughness_at for view b: its map's value at uv mapped into its range (lo + v
 * (hi - lo)), or its uniform roughness (``alpha`` (B,), ``maps`` (B,) NULL where none,
 * ``hw`` (B, 2), ``range`` (B, 2)). */
static inline float roughness_of(const float *alpha, const float *const *maps,
                                 const int64_t *hw, const float *range, int64_t b,
                                 const float *uv) {
    const float *tex = maps[b];
    if (!tex) return alpha[b];
    float lo = range[2 * b], hi = range[2 * b + 1];
    return lo + sample_uv(tex, hw[2 * b], hw[2 * b + 1], uv[0], uv[1]) * (hi - lo);
}

#endif
