/* Sparse supersampling's sub-pixel test (subsamples.edges' first rule, the n x n render's
 * own): per pixel of a one-sample frame, from both layers' rasterized ids on its n x n
 * sub-pixel grid, whether its sub-pixels are not all alike in coverage, or all covered
 * and one's triangle folds against the first's (subsamples._folds), and whether its first
 * sub-pixel is covered. lattice.c's ``edges`` then compares that coverage with the pixel
 * center's (the repaired one-sample layer's), which gives the rule's decision exactly.
 *
 * Why flags of their own: ``edges`` reads one byte a pixel instead of both layers' n x n
 * ids (16 bytes at 2x2), and raster.c computes the flags per pixel row as it writes that
 * row's ids (``sub_flags_row``); ``torchrefract_sub_flags`` (raster.c) for ids drawn
 * elsewhere (the OpenGL passes). */

#ifndef TR_SUBPIXELS_H
#define TR_SUBPIXELS_H

#include "optics.h"

enum { SUB_FRONT_DIFFERS = 1, SUB_FRONT_FIRST = 2, SUB_BACK_DIFFERS = 4, SUB_BACK_FIRST = 8 };

/* The fold test's triangles (global ids) and tolerances. */
typedef struct {
    const float *face_normal;   /* (F, 3) */
    const float *tv, *tn;       /* (F, 3, 3) corners, their shading normals */
    float normal_tol, face_tol;
} Folds;

/* Whether triangles a and b fold against each other: no corner of a lies where one of b's
 * does with a shading normal within normal_tol of it (the interpolated normals meet
 * there: a smooth mesh's neighbours), and their faces turn by more than face_tol. */
static int folds(const Folds *f, int64_t a, int64_t b) {
    if (!(1.0f - dot3(f->face_normal + 3 * b, f->face_normal + 3 * a) > f->face_tol)) return 0;
    for (int p = 0; p < 3; p++)
        for (int q = 0; q < 3; q++) {
            const float *va = f->tv + 9 * a + 3 * p, *vb = f->tv + 9 * b + 3 * q;
            if (va[0] == vb[0] && va[1] == vb[1] && va[2] == vb[2] &&
                1.0f - dot3(f->tn + 9 * a + 3 * p, f->tn + 9 * b + 3 * q) <= f->normal_tol)
                return 0;
        }
    return 1;
}

/* One pixel's flags (1: differs, 2: first covered) from its first sub-pixel's id at ids,
 * rows nw apart. */
static inline int sub_pixel_flags(const Folds *f, const int32_t *ids, int64_t nw, int64_t n) {
    int32_t first = ids[0];
    int cov = first >= 0, out = cov ? 2 : 0;
    if (n == 2 && ids[1] == first && ids[nw] == first && ids[nw + 1] == first)
        return out;  /* one triangle (or none): the common case */
    for (int64_t i = 0; i < n; i++)
        for (int64_t k = 0; k < n; k++) {
            int32_t id = ids[i * nw + k];
            if ((id >= 0) != cov) return out | 1;
            if (id != first && folds(f, first, id)) return out | 1;  /* both covered */
        }
    return out;
}

#if defined(__AVX2__)
#include <immintrin.h>
#define TR_SUB8 1

/* The ids of sub-pixels (0, 0) and (0, 1) of 8 pixels from the row at r (n = 2: 16 ids),
 * as lanes: even and odd columns. */
static inline void sub_even_odd8(const int32_t *r, __m256i *even, __m256i *odd) {
    __m256 a = _mm256_castsi256_ps(_mm256_loadu_si256((const __m256i *)r));
    __m256 b = _mm256_castsi256_ps(_mm256_loadu_si256((const __m256i *)(r + 8)));
    *even = _mm256_permute4x64_epi64(_mm256_castps_si256(_mm256_shuffle_ps(a, b, 0x88)), 0xd8);
    *odd = _mm256_permute4x64_epi64(_mm256_castps_si256(_mm256_shuffle_ps(a, b, 0xdd)), 0xd8);
}

/* The face normals of ids a (x, y, z lanes; face 0 where ``want`` is clear). */
static inline void sub_face_normals8(const Folds *f, __m256i a, __m256i want, __m256 *n) {
    __m256i ia = _mm256_mullo_epi32(_mm256_and_si256(a, want), _mm256_set1_epi32(3));
    for (int c = 0; c < 3; c++)
        n[c] = _mm256_i32gather_ps(f->face_normal, _mm256_add_epi32(ia, _mm256_set1_epi32(c)), 4);
}

/* Lanes of ``want`` where the faces of b and of the first id (normals na) turn by more
 * than face_tol: folds' first test, its float operations (optics.dot's order). */
static inline __m256i sub_face_turns8(const Folds *f, const __m256 *na, __m256i b,
                                      __m256i want) {
    if (_mm256_testz_si256(want, want)) return want;
    __m256 nb[3];
    sub_face_normals8(f, b, want, nb);
    __m256 d = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nb[0], na[0]),
                                           _mm256_mul_ps(nb[1], na[1])),
                             _mm256_mul_ps(nb[2], na[2]));
    __m256 turn = _mm256_sub_ps(_mm256_set1_ps(1.0f), d);
    return _mm256_and_si256(want, _mm256_castps_si256(
        _mm256_cmp_ps(turn, _mm256_set1_ps(f->face_tol), _CMP_GT_OQ)));
}

/* sub_pixel_flags of 8 pixels (n = 2) from the sub-pixel row at r (nw ids a row) as
 * lanes, but for those set in *unsure (returned): two faces seen there turn by more than
 * face_tol, and folds then compares their corners (sub_pixel_flags decides those). */
static inline __m256i sub_pixel_flags8(const Folds *f, const int32_t *r, int64_t nw,
                                       int *unsure) {
    __m256i a, b, c, d, none = _mm256_set1_epi32(-1);
    sub_even_odd8(r, &a, &b);
    sub_even_odd8(r + nw, &c, &d);
    __m256i ca = _mm256_cmpgt_epi32(a, none), cb = _mm256_cmpgt_epi32(b, none);
    __m256i cc = _mm256_cmpgt_epi32(c, none), cd = _mm256_cmpgt_epi32(d, none);
    __m256i flag = _mm256_or_si256(_mm256_xor_si256(ca, cb),
                                   _mm256_or_si256(_mm256_xor_si256(ca, cc),
                                                   _mm256_xor_si256(ca, cd)));
    /* folds only where all four are covered */
    __m256i all = _mm256_andnot_si256(flag, ca);
    __m256i wb = _mm256_andnot_si256(_mm256_cmpeq_epi32(a, b), all);
    __m256i wc = _mm256_andnot_si256(_mm256_cmpeq_epi32(a, c), all);
    __m256i wd = _mm256_andnot_si256(_mm256_cmpeq_epi32(a, d), all);
    __m256i any = _mm256_or_si256(wb, _mm256_or_si256(wc, wd));
    *unsure = 0;
    if (!_mm256_testz_si256(any, any)) {  /* two faces or more inside some pixel */
        __m256 na[3];
        sub_face_normals8(f, a, any, na);
        __m256i turns = _mm256_or_si256(sub_face_turns8(f, na, b, wb),
                                        _mm256_or_si256(sub_face_turns8(f, na, c, wc),
                                                        sub_face_turns8(f, na, d, wd)));
        *unsure = _mm256_movemask_ps(_mm256_castsi256_ps(turns));
    }
    return _mm256_or_si256(_mm256_and_si256(flag, _mm256_set1_epi32(1)),
                           _mm256_and_si256(ca, _mm256_set1_epi32(2)));
}
#endif

/* The flags of one row of w pixels from both layers' first sub-pixel rows (nw = n w ids a
 * row) into out (SUB_* bits). */
static void sub_flags_row(const Folds *f, const int32_t *front, const int32_t *back,
                          int64_t w, int64_t n, uint8_t *out) {
    int64_t nw = n * w, x = 0;
#ifdef TR_SUB8
    if (n == 2)
        for (; x + 8 <= w; x += 8) {
            int uf, ub;
            __m256i fr = sub_pixel_flags8(f, front + 2 * x, nw, &uf);
            __m256i bk = sub_pixel_flags8(f, back + 2 * x, nw, &ub);
            __m256i v = _mm256_or_si256(fr, _mm256_slli_epi32(bk, 2));
            __m128i p16 = _mm_packus_epi32(_mm256_castsi256_si128(v),
                                           _mm256_extracti128_si256(v, 1));
            _mm_storel_epi64((__m128i *)(out + x), _mm_packus_epi16(p16, p16));
            for (int u = uf | ub; u; u &= u - 1) {  /* the unsure pixels, one by one */
                int64_t i = x + __builtin_ctz((unsigned)u);
                out[i] = (uint8_t)(sub_pixel_flags(f, front + 2 * i, nw, 2) |
                                   sub_pixel_flags(f, back + 2 * i, nw, 2) << 2);
            }
        }
#endif
    for (; x < w; x++)
        out[x] = (uint8_t)(sub_pixel_flags(f, front + n * x, nw, n) |
                           sub_pixel_flags(f, back + n * x, nw, n) << 2);
}

#endif
