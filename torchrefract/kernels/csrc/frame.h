/* What the fused shading kernels (specular.c, rousiers.c) share: the batch's object pixels
 * and G-buffer, the march's fields, the materials, the SG table, the lighting and the
 * outputs every method writes (``Frame``), and the steps every method takes: the camera
 * coordinates and bounding chord of a ray (march.camera_coordinates,
 * march._bounding_chord), the march of a block of rays (march_core.h), the escape
 * fraction (shading.bounces.escape_fraction). */

#ifndef TORCHREFRACT_FRAME_H
#define TORCHREFRACT_FRAME_H

#include "lighting.h"
#include "march_core.h"
#include "materials.h"
#include "sgtable.h"

#include <stdlib.h>

typedef struct {
    int64_t n;                  /* object pixels */
    int64_t nb;                 /* views */
    const int64_t *idx;         /* (N,) flat (B*H*W) index of each */
    const int64_t *batch;       /* (N,) its view */
    /* the G-buffer, flat over B*H*W */
    const float *ray_dir, *front_pos, *front_normal, *front_dist, *back_dist;
    const float *eye;           /* (B, 3) */
    const float *basis;         /* (B, 9) rows: right, up, forward (camera.proj[:, 3:12]) */
    const float *proj;          /* (B, 16) camera.projection_params */
    const float *sphere_c, *sphere_r; /* (B, 3), (B,) bounding spheres */
    Job march;                  /* the march's shared fields (planes, triangles, frame) */
    /* materials, per view */
    const float *ior, *alpha, *absorption;  /* (B,), (B,), (B, 3) */
    const int64_t *dist;        /* (B,) 0 beckmann, 1 ggx */
    int tir_mode;               /* 0 conserve, 1 clamp, 2 reflect */
    int rough;                  /* some object pixel of the batch is rough: the rough
                                 * interfaces' energies for all (paths.trace_paths) */
    /* roughness maps (optics.textures): per view its (H, W) map or NULL (uniform), its
     * size and range (a value v means alpha = lo + v (hi - lo)); the corner UVs */
    const float *const *rmap;
    const int64_t *rmap_hw;     /* (B, 2) */
    const float *rrange;        /* (B, 2) */
    const float *front_uv;      /* (B*H*W, 2) */
    const float *tri_uvs;       /* (T, 3, 2) */
    SgTable table;
    const float *esc;           /* (B, esc_n) escape fraction over alpha in [0, 1] */
    int64_t esc_n;
    Lights lights;
    SgEnv env;                  /* the SG pyramids (the rough methods' lookups) */
    /* out */
    float *radiance;            /* (B*H*W, 3): the background, overwritten on the object */
    float *exit_found, *tir;    /* (B*H*W,) */
} Frame;

/* march.camera_coordinates of a point or a direction in view b. */
static inline void camera_coords(const Frame *f, int64_t b, const float *v, int point,
                                 float *out) {
    const float *e = f->eye + 3 * b, *bs = f->basis + 9 * b;
    float rel[3] = {v[0] - (point ? e[0] : 0.0f), v[1] - (point ? e[1] : 0.0f),
                    v[2] - (point ? e[2] : 0.0f)};
    for (int k = 0; k < 3; k++) out[k] = dot3(bs + 3 * k, rel);
}

/* march._bounding_chord: how far a ray from p along t runs inside the mesh's bounding
 * sphere (+1%). */
static inline float bounding_chord(const Frame *f, int64_t b, const float *p, const float *t) {
    const float *sc = f->sphere_c + 3 * b;
    float oc[3] = {p[0] - sc[0], p[1] - sc[1], p[2] - sc[2]};
    float rr = f->sphere_r[b];
    float bq = dot3(oc, t), cq = dot3(oc, oc) - rr * rr;
    float disc = bq * bq - cq;
    float ch = -bq + sqrtf(disc > 0.0f ? disc : 0.0f);
    return (ch > 1e-6f ? ch : 1e-6f) * 1.01f;
}

/* Per-block ray arrays for the march (march_core.h reads rays by index). */
typedef struct {
    float c0[3 * BLOCK], ct[3 * BLOCK], smax[BLOCK], smin[BLOCK], p[3 * BLOCK], t[3 * BLOCK];
    int64_t batch[BLOCK];
    /* out: the exits (march._exit's values) */
    float s[BLOCK], bary[3 * BLOCK], normal[3 * BLOCK], pos[3 * BLOCK];
    uint8_t found[BLOCK];
    int64_t tri[BLOCK], layer[BLOCK];
} Rays;

/* Set ray i of a block: from p along t in view b (camera coordinates c0, ct). */
static inline void set_ray(const Frame *f, Rays *r, int i, int64_t b, const float *p,
                           const float *t, const float *c0, const float *ct) {
    for (int k = 0; k < 3; k++) {
        r->p[3 * i + k] = p[k];
        r->t[3 * i + k] = t[k];
        r->c0[3 * i + k] = c0[k];
        r->ct[3 * i + k] = ct[k];
    }
    r->batch[i] = b;
    r->smax[i] = bounding_chord(f, b, p, t);
    r->smin[i] = 0.0f;
}

/* March rays [0, m) of a block with the march fields of ``base`` (march.march_back with
 * the native kernel's choices; march.march_inside where base's planes hold both layers). */
static void march_rays_on(const Job *base, Rays *r, int m, int steps, int refine) {
    float lo[BLOCK], hi[BLOCK];
    Job jm = *base;
    jm.n = m;
    jm.steps = steps;
    jm.refine = refine;
    jm.c0 = r->c0; jm.ct = r->ct; jm.s_max = r->smax; jm.s_min = r->smin;
    jm.batch = r->batch; jm.p1 = r->p; jm.t = r->t;
    jm.s_out = r->s; jm.bary_out = r->bary; jm.normal_out = r->normal; jm.pos_out = r->pos;
    jm.found = r->found; jm.tri = r->tri; jm.layer = r->layer;
    search_rays(&jm, 0, m, lo, hi);
    exit_block(&jm, 0, m, lo, hi);
}

/* March rays [0, m) of a block through the back layer (march.march_back). */
static inline void march_rays(const Frame *f, Rays *r, int m, int steps, int refine) {
    march_rays_on(&f->march, r, m, steps, refine);
}

/* materials.roughness_at: the map of view b at uv (lo + v (hi - lo)), else its roughness. */
static inline float roughness_at(const Frame *f, int64_t b, const float *uv) {
    return roughness_of(f->alpha, f->rmap, f->rmap_hw, f->rrange, b, uv);
}

/* shading.bounces.escape_fraction's interpolation of its per-view grid over alpha. */
static inline float escape(const Frame *f, int64_t b, float alpha) {
    int64_t g = f->esc_n;
    float pos = clampf(alpha, 0.0f, 1.0f) * (float)(g - 1);
    int64_t i0 = (int64_t)floorf(pos);
    if (i0 > g - 2) i0 = g - 2;
    float w = pos - (float)i0;
    const float *e = f->esc + b * g;
    return e[i0] * (1.0f - w) + e[i0 + 1] * w;
}

/* Per view: the table's interfaces at (eta, alpha) and (eta, alpha_min), entering
 * (eta = ior) and leaving (eta = 1 / ior): the first AXES of a view's axes (rousiers_core.h
 * adds its roughness levels after them). */
enum { IN = 0, IN0 = 1, OUT = 2, OUT0 = 3, AXES = 4 };

/* A view's four interfaces on the table (``out``: IN .. OUT0), at its roughness (at least
 * microfacet.ALPHA_MIN) and at the table's smallest (sg_lobe's fade). */
static inline void view_axes(const Frame *f, int64_t b, SgAxes *out) {
    float ior = f->ior[b], a = f->alpha[b] > 1e-4f ? f->alpha[b] : 1e-4f;
    float a0 = f->table.alpha_min;
    sg_axes(&f->table, ior, a, out + IN);
    sg_axes(&f->table, ior, a0, out + IN0);
    sg_axes(&f->table, 1.0f / ior, a, out + OUT);
    sg_axes(&f->table, 1.0f / ior, a0, out + OUT0);
}

/* The axes of a point of roughness ``alpha`` (at least ALPHA_MIN) in view b: the view's
 * where its roughness is uniform, else ``own`` filled at alpha (the alpha_min ones are the
 * view's). */
static inline const SgAxes *axes_at(const Frame *f, const SgAxes *view, int64_t b,
                                    float alpha, SgAxes *own) {
    if (!f->rmap[b]) return view;
    float ior = f->ior[b];
    sg_axes(&f->table, ior, alpha, own + IN);
    own[IN0] = view[IN0];
    sg_axes(&f->table, 1.0f / ior, alpha, own + OUT);
    own[OUT0] = view[OUT0];
    return own;
}

/* sg_env_tap of a block's m lookups (view of pixel i: the job's batch[r0 + i]; directions
 * dirs[3 i ...], sharpness ks[i]), eight at a time in lanes, their texels asked for (the
 * same taps as incident_sg's, read by incident_sg_at). */
static void block_taps(const Frame *j, int64_t r0, int m, const float *dirs, const float *ks,
                       SgTap *out) {
    for (int i0 = 0; i0 < m; i0 += 8)
        sg_env_tap8(&j->lights, &j->env, m - i0 < 8 ? m - i0 : 8, j->batch + r0 + i0,
                    dirs + 3 * i0, ks + i0, out + i0);
}

/* A method's work on one block of m <= BLOCK pixels from r0, given each view's table
 * axes; and the filling of one view's axes (returns how many it filled, from out[0]). */
typedef void (*tr_block_fn)(const void *job, const SgAxes *axes, int64_t r0, int m);
typedef int (*tr_axes_fn)(const Frame *f, int64_t b, SgAxes *out);

typedef struct {
    tr_block_fn fn;
    const void *job;
    const SgAxes *axes;
    const Frame *f;  /* the job's frame: its pixels and G-buffer (pixels_prefetch) */
} ShadeRange;

/* The G-buffer values every kernel reads of pixels [r, e), asked into the cache: a
 * block's pixels are a sparse, increasing list over frames of tens of MB (the adaptive
 * lattice's), which the hardware's stream prefetchers follow poorly. */
static inline __attribute__((always_inline)) void pixels_prefetch(const Frame *f, int64_t r,
                                                                   int64_t e) {
    for (int64_t i = r; i < e; i++) {
        int64_t px = f->idx[i];
        __builtin_prefetch(f->ray_dir + 3 * px);
        __builtin_prefetch(f->front_pos + 3 * px);
        __builtin_prefetch(f->front_normal + 3 * px);
        __builtin_prefetch(f->front_uv + 2 * px);
        __builtin_prefetch(f->front_dist + px);
        __builtin_prefetch(f->back_dist + px);
    }
}

/* The blocks of pixels [begin, end), each asking for the next one's G-buffer values
 * before it is shaded. */
static void shade_range(const void *arg, int64_t begin, int64_t end) {
    const ShadeRange *rg = (const ShadeRange *)arg;
    pixels_prefetch(rg->f, begin, end - begin < BLOCK ? end : begin + BLOCK);
    for (int64_t r = begin; r < end; r += BLOCK) {
        int64_t next = r + BLOCK, stop = next + BLOCK < end ? next + BLOCK : end;
        if (next < end) pixels_prefetch(rg->f, next, stop);
        rg->fn(rg->job, rg->axes, r, end - r < BLOCK ? (int)(end - r) : BLOCK);
    }
}

/* A method kernel's entry: each view's ``naxes`` table axes filled (``fill``) with their
 * slices of the table (sgtable.h's sg_slices, for the view's distribution: a lookup at
 * the view's axes then reads two values per channel), then the pixels in chunks of 64,
 * handed out dynamically with OpenMP (a thread whose core is busy with another process
 * takes fewer), else one contiguous range per thread (common.h).
 * Returns 0, or -1 where memory or a thread could not be had (the caller then runs its
 * tensor code). */
static int run_shading(const void *job, Frame *f, int naxes, tr_axes_fn fill, tr_block_fn fn,
                       int threads) {
#ifdef HAVE_AVX2_PATH
    f->march.simd = f->march.simd && __builtin_cpu_supports("avx2");
#endif
    size_t nviews = (size_t)(f->nb > 0 ? f->nb : 1), per = (size_t)(SG_SLICES * f->table.nt);
    SgAxes *axes = (SgAxes *)malloc(sizeof(SgAxes) * (size_t)naxes * nviews);
    int *filled = (int *)malloc(sizeof(int) * nviews);
    float *slices = NULL;
    size_t total = 0;
    if (axes && filled) {
        for (int64_t b = 0; b < f->nb; b++) {
            filled[b] = fill(f, b, axes + naxes * b);
            total += (size_t)filled[b];
        }
        slices = (float *)malloc(sizeof(float) * per * (total > 0 ? total : 1));
    }
    if (!slices) {
        free(axes);
        free(filled);
        return -1;
    }
    for (int64_t b = 0, k = 0; b < f->nb; b++)
        for (int q = 0; q < filled[b]; q++, k++)
            sg_slices(&f->table, f->dist[b], axes + naxes * b + q, slices + per * (size_t)k);
    ShadeRange rg = {fn, job, axes, f};
    int rc = 0;
#ifdef _OPENMP
    int64_t chunks = (f->n + 63) / 64;
#pragma omp parallel for schedule(dynamic, 1) num_threads(threads > 0 ? threads : 1)
    for (int64_t c = 0; c < chunks; c++)
        shade_range(&rg, c * 64, c * 64 + 64 < f->n ? c * 64 + 64 : f->n);
#else
    rc = tr_parallel_for(shade_range, &rg, f->n, 256, threads);
#endif
    free(axes);
    free(filled);
    free(slices);
    return rc;
}

#endif
