/* Internal reflections in the fused kernels (shading/bounces.follow), shared by
 * specular.c and rousiers.c: the paths of one block of pixels, the budget's bookkeeping
 * and the march between the layers from one interface to the next. Each method brings
 * its own interface model (``tr_inside_fn``: bounces.ShadeFn after the first exit). */

#ifndef TORCHREFRACT_BOUNCES_H
#define TORCHREFRACT_BOUNCES_H

#include "frame.h"

/* The budget (bounces.BounceSettings; limit 0: none) and what it writes. */
typedef struct {
    int limit;                  /* interfaces after the first exit (K, or the auto cap) */
    int rays;                   /* rays of the first internal reflection (1 or 4) */
    int steps;                  /* coarse steps of each inside march */
    float tol;                  /* a ray stops at this throughput (max over RGB; 0 for K) */
    float *bounces, *residual;  /* out (B*H*W,) bounces.bounce_passes */
} Bounces;

/* The internal reflections of one block's pixels (bounces.follow's state): per pixel the
 * light leaving through the interfaces met from inside (``acc``), the bounces followed and
 * the residual throughput; per ray still alive its pixel, where it is (its arrival at the
 * next interface once marched), its direction, throughput, lobe variance, share of its
 * path and the roughness where it arrives. */
#define RAYS (4 * BLOCK)
typedef struct {
    float acc[BLOCK][3], bounces[BLOCK], residual[BLOCK];
    int n;
    int pix[RAYS];
    float p[RAYS][3], t[RAYS][3], w[RAYS][3], var[RAYS], share[RAYS], normal[RAYS][3];
    float alpha[RAYS];  /* materials.roughness_at at the arrival's UV (not clamped) */
    uint8_t found[RAYS];
    /* the light leaving each ray's interface, asked for by the method's tr_inside_fn and
     * looked up for the whole wave (inside_lookups): along look_d, with sharpness look_k
     * (an SG lookup) or a plain one (the method's ``sg`` 0), times look_w */
    float look_d[RAYS][3], look_k[RAYS], look_w[RAYS];
    /* table coordinates a method finds for the whole wave before its rays are shaded
     * (its tr_coords_fn: each ray's chain of dependent steps then runs beside the
     * others'), read by its tr_inside_fn */
    float coord[RAYS][8];
} Paths;

/* A method's interface model for ray r of the paths at a later interface: asks for the
 * light leaving (``look_d``, ``look_k``, ``look_w``: inside_lookups adds it to ``acc``);
 * returns the reflectance, and the reflected lobe's direction and variance. */
typedef float (*tr_inside_fn)(const void *job, const SgAxes *view_axes, Paths *ps, int r,
                              int64_t b, int last, float *dir, float *var_out);

/* A method's table coordinates for rays [0, n) of the paths (``coord``), before they are
 * shaded; NULL where its tr_inside_fn needs none. */
typedef void (*tr_coords_fn)(const void *job, Paths *ps, int64_t r0, int n, int last);

/* materials.roughness_at at the barycentrics of triangle tri (0 where none:
 * gbuffer.interpolate of tri.clamp(min=0)). */
static float roughness_on(const Frame *f, int64_t b, const float *bary, int64_t tri) {
    float uv[2];
    interpolate(bary, f->tri_uvs + 6 * (tri > 0 ? tri : 0), 2, uv);
    return roughness_at(f, b, uv);
}

/* bounces.follow's bookkeeping for the rays an interface reflects inside: throughput
 * w_next = w refl goes on where the interface was found, the ray is not at the budget's
 * last interface and w_next exceeds the tolerance (max over RGB); elsewhere its mean is
 * residual. Returns whether it goes on. */
static int goes_on(const Bounces *bo, Paths *ps, int pix, int found, int last, const float *w,
                   float refl, float *w_next) {
    for (int c = 0; c < 3; c++) w_next[c] = w[c] * refl;
    float mx = tmax(tmax(w_next[0], w_next[1]), w_next[2]);
    if (found && !last && mx > bo->tol && refl > 0.0f) return 1;
    ps->residual[pix] += ((w_next[0] + w_next[1]) + w_next[2]) / 3.0f;
    return 0;
}

/* Add a ray to the paths: from p along t with throughput w and lobe variance var. */
static void add_ray(Paths *ps, int pix, const float *p, const float *t, const float *w,
                    float var, float share) {
    int r = ps->n++;
    ps->pix[r] = pix;
    for (int c = 0; c < 3; c++) {
        ps->p[r][c] = p[c];
        ps->t[r][c] = t[c];
        ps->w[r][c] = w[c];
    }
    ps->var[r] = var;
    ps->share[r] = share;
    ps->bounces[pix] += share;
}

/* The light leaving the interfaces of rays [0, n) (their look_* requests), added to their
 * pixels' ``acc`` in ray order: eight rays' lookups at a time, their map coordinates in
 * lanes and their texels asked for before any is read. ``sg``: SG lookups (incident_sg),
 * else plain ones (incident). */
static void inside_lookups(const Frame *j, Paths *ps, int64_t r0, int n, int sg) {
    for (int i0 = 0; i0 < n; i0 += 8) {
        int m = n - i0 < 8 ? n - i0 : 8;
        int64_t bs[8];
        for (int i = 0; i < m; i++) bs[i] = j->batch[r0 + ps->pix[i0 + i]];
        SgTap st[8];
        EnvTap et[8];
        if (sg) sg_env_tap8(&j->lights, &j->env, m, bs, &ps->look_d[i0][0], ps->look_k + i0, st);
        else env_taps8(&j->lights, m, bs, &ps->look_d[i0][0], et);
        for (int i = 0; i < m; i++) {
            int r = i0 + i;
            float l_out[3];
            if (sg)
                incident_sg_at(&j->lights, bs[i], ps->p[r], ps->look_d[r], ps->look_k[r], st + i,
                               l_out);
            else
                incident_at(&j->lights, bs[i], ps->p[r], ps->look_d[r], et + i, l_out);
            for (int c = 0; c < 3; c++)
                ps->acc[ps->pix[r]][c] += ps->w[r][c] * ps->look_w[r] * l_out[c];
        }
    }
}

/* bounces.follow from the second interface on, over a block: march the rays still alive
 * to their next interface (march_inside: both layers, from 1e-4 of the chord), attenuate
 * them over the segment, shade it (``shade``, with view b's ``naxes`` table axes), keep
 * the rays that go on; until none does. */
static void follow_block(const Frame *j, const Bounces *bo, const void *job,
                         tr_inside_fn shade, tr_coords_fn coords, int sg, const SgAxes *axes,
                         int naxes, Paths *ps, int64_t r0) {
    Job inside = j->march;
    inside.pw = 8;
    Rays rays;
    for (int k = 1; ps->n > 0; k++) {
        for (int r0m = 0; r0m < ps->n; r0m += BLOCK) {  /* the march, BLOCK rays at a time */
            int m = ps->n - r0m < BLOCK ? ps->n - r0m : BLOCK;
            for (int i = 0; i < m; i++) {
                int r = r0m + i;
                int64_t b = j->batch[r0 + ps->pix[r]];
                float c0[3], ct[3];
                camera_coords(j, b, ps->p[r], 1, c0);
                camera_coords(j, b, ps->t[r], 0, ct);
                set_ray(j, &rays, i, b, ps->p[r], ps->t[r], c0, ct);
                rays.smin[i] = 1e-4f * rays.smax[i];
            }
            march_rays_on(&inside, &rays, m, bo->steps, j->march.refine);
            for (int i = 0; i < m; i++) {
                int r = r0m + i;
                int64_t b = j->batch[r0 + ps->pix[r]];
                int f = rays.found[i];
                float s = f ? rays.s[i] : 0.0f;
                for (int c = 0; c < 3; c++) {
                    ps->w[r][c] = ps->w[r][c] * transmittance(j->absorption[3 * b + c], s);
                    if (f) ps->p[r][c] = rays.pos[3 * i + c];
                    ps->normal[r][c] = rays.normal[3 * i + c];
                }
                ps->found[r] = (uint8_t)f;
                ps->alpha[r] = roughness_on(j, b, rays.bary + 3 * i, rays.tri[i]);
            }
        }
        int last = k >= bo->limit, n = ps->n;
        float dirs[RAYS][3], vars[RAYS], refls[RAYS];
        if (coords) coords(job, ps, r0, n, last);
        for (int r = 0; r < n; r++) {  /* shade, the light leaving looked up for all */
            int64_t b = j->batch[r0 + ps->pix[r]];
            refls[r] = shade(job, axes + naxes * b, ps, r, b, last, dirs[r], &vars[r]);
        }
        inside_lookups(j, ps, r0, n, sg);
        ps->n = 0;
        for (int r = 0; r < n; r++) {  /* compact the rays that go on in place */
            int pix = ps->pix[r];
            float w_next[3];
            if (goes_on(bo, ps, pix, ps->found[r], last, ps->w[r], refls[r], w_next))
                add_ray(ps, pix, ps->p[r], dirs[r], w_next, vars[r], ps->share[r]);
        }
    }
}

/* A block with internal bounces: follow its paths (follow_block), then write each pixel,
 * ``front`` (its front reflection's light) plus what left through the interfaces met from
 * inside, over the background unless a light hides it (``hidden``), and its bounce passes. */
static void finish_block(const Frame *j, const Bounces *bo, const void *job,
                         tr_inside_fn shade, tr_coords_fn coords, int sg, const SgAxes *axes,
                         int naxes, Paths *ps, const float (*front)[3], const uint8_t *hidden,
                         int64_t r0, int m) {
    follow_block(j, bo, job, shade, coords, sg, axes, naxes, ps, r0);
    for (int i = 0; i < m; i++) {
        int64_t px = j->idx[r0 + i];
        for (int c = 0; c < 3 && !hidden[i]; c++)
            j->radiance[3 * px + c] = front[i][c] + ps->acc[i][c];
        bo->bounces[px] = ps->bounces[i];
        bo->residual[px] = ps->residual[i];
    }
}

#endif
