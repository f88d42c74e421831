/* Fused shading of ``specular`` (methods/specular.py, shading/paths.py) and
 * ``prefiltered`` (``blur``) without internal bounces, uniform roughness or a map: per
 * object pixel, in registers, the entry refraction, the march to the exit
 * (march_core.h, the march kernel's own search, candidates and walk), the exit
 * refraction, the interfaces' energies (smooth: Fresnel; rough: the SG table's, eq. 9 of
 * de Rousiers 2012, with the exit averaged over the entry lobe), the ``tir`` rule, the
 * absorption, the two environment lookups and the sphere lights.
 *
 * The tensor code (paths.trace_paths, render_specular) is the reference and the
 * differentiable path; this kernel follows it formula by formula in float32 (the table
 * lookups are trilinear as grid_sample's), and tests/test_fused.py holds the two together.
 * Rays are marched in blocks of 16 (BLOCK), so the search overlaps its plane reads as the
 * march kernel does; blocks are handed out dynamically, so a thread that loses its core
 * holds up no other.
 */

#include "frame.h"

typedef struct {
    Frame f;
    int blur;                   /* 1: ``prefiltered``: the lookups blurred by the roughness
                                 * (prefiltered.blur_sharpness), from the SG pyramids */
    float *blur_sigma;          /* (B*H*W,) with ``blur``: the transmitted lobe's k^-1/2 */
} SpecJob;

/* The exit's energies (paths.trace_paths): the smooth interface's Fresnel split, or the
 * rough one's (SG table: ``in`` the entry's axes at alpha1, ``out`` the exit's at alpha2),
 * ``tir: conserve`` averaging over the entry lobe (paths.spread_exit) with the escape
 * fraction of the trapped light. */
static void exit_energies(const Frame *j, const SgAxes *in, const SgAxes *out, int64_t b,
                          float alpha1, float alpha2, float cos1, float cos2, float f2,
                          float *e_t2, float *e_r2, float *esc) {
    float eta = j->ior[b];
    int64_t dist = j->dist[b];
    *esc = 1.0f;
    if (!j->rough) {
        *e_t2 = 1.0f - f2;
        *e_r2 = f2;
    } else if (j->tir_mode == 0) {
        int rough = alpha1 > j->table.alpha_min;
        float k1, tilt;
        transmit_lobe(&j->table, in, dist, cos1, &k1, &tilt);
        /* cos(theta2 + tilt_axis - tilt_ray) by the angle-sum identities */
        float sc1 = 1.0f - cos1 * cos1;
        float sin_t = sqrtf(sc1 > 1e-12f ? sc1 : 1e-12f) / eta;
        float st2 = 1.0f - sin_t * sin_t;
        float cos_t = sqrtf(st2 > 1e-12f ? st2 : 1e-12f);
        float ca = cosf(tilt), sa = sinf(tilt);
        float cos_d = ca * cos_t + sa * sin_t, sin_d = sa * cos_t - ca * sin_t;
        float sc2 = 1.0f - cos2 * cos2;
        float sin2 = sqrtf(sc2 > 1e-12f ? sc2 : 1e-12f);
        float c_axis = cos2 * cos_d - sin2 * sin_d;
        if (c_axis < 0.0f) c_axis = 0.0f;
        if (!rough) c_axis = cos2;
        spread_interface_energies(&j->table, out, dist, c_axis, rough ? 1.0f / k1 : 0.0f,
                                  eta, e_t2, e_r2);
        *esc = escape(j, b, alpha2);
    } else {
        interface_energies(&j->table, out, dist, cos2, f2, e_t2, e_r2);
    }
}

/* optics.exit_rule.leaving_weight: what leaves the last interface under the tir rule. */
static inline float leaving_weight(int mode, int tir, float e_t, float e_r, float esc) {
    if (mode == 0) {
        float w = e_t + e_r * esc;
        return w > 1.0f ? 1.0f : w;
    }
    if (mode == 2) return tir ? e_r : e_t;
    float kept = e_t + e_r;
    return tir ? (kept > 1.0f ? 1.0f : kept) : e_t;
}

/* Step 3 for ray i of a marched block (paths.trace_paths, render_specular, and
 * render_prefiltered with ``blur``): the exit refraction, the energies and the exit rule,
 * the absorption, the two lookups; the pixel and its passes written. */
static void shade_pixel(const SpecJob *sj, const SgAxes *ax, const Rays *rays, int i,
                        const float *d, const float *n1, int tir1, int64_t px, int64_t b) {
    const Frame *j = &sj->f;
    const float *p1 = rays->p + 3 * i, *t1 = rays->t + 3 * i;
    float eta = j->ior[b];
    int ok = rays->found[i];
    /* the roughness at the entry and at the exit (a map's, at their UVs) */
    float alpha = roughness_at(j, b, j->front_uv + 2 * px), alpha2 = alpha, uv2[2];
    SgAxes own[2];
    if (j->rmap[b]) {
        if (ok) {
            interpolate(rays->bary + 3 * i, j->tri_uvs + 6 * rays->tri[i], 2, uv2);
            alpha2 = roughness_at(j, b, uv2);
        }
        sg_axes(&j->table, eta, alpha, own);
        sg_axes(&j->table, 1.0f / eta, alpha2, own + 1);
        ax = own;
    }
    float cos1 = -dot3(d, n1), f1 = fresnel(cos1, 1.0f / eta);
    float n2[3], t2[3], p2[3], e_t1, e_r1, e_t2, e_r2, esc;
    face_forward(rays->normal + 3 * i, t1, n2);
    float cos2 = -dot3(t1, n2), f2 = fresnel(cos2, eta);
    int tir2 = refract(t1, n2, eta, t2) && ok;
    if (j->tir_mode == 2 && tir2) reflect(t1, n2, t2);
    if (j->rough) {
        interface_energies(&j->table, ax, j->dist[b], cos1, f1, &e_t1, &e_r1);
    } else {
        e_t1 = 1.0f - f1;
        e_r1 = f1;
    }
    exit_energies(j, ax, ax + 1, b, alpha, alpha2, cos1, cos2, f2, &e_t2, &e_r2, &esc);
    float w2 = leaving_weight(j->tir_mode, tir2, e_t2, e_r2, esc), path;
    if (ok) {
        for (int c = 0; c < 3; c++) p2[c] = rays->pos[3 * i + c];
        path = rays->s[i];
    } else {  /* no exit: leave along the refracted ray, with weight 1 */
        for (int c = 0; c < 3; c++) { t2[c] = t1[c]; p2[c] = p1[c]; }
        w2 = 1.0f;
        float th = j->back_dist[px] - j->front_dist[px];
        path = th > 0.0f ? th : 0.0f;
    }
    float refl[3], l_refl[3], l_trans[3];
    reflect(d, n1, refl);
    if (sj->blur) {  /* prefiltered.blur_sharpness */
        float a2 = alpha * alpha, q = 1.0f - 1.0f / eta, p = eta - 1.0f;
        float var_t = 0.5f * a2 * (q * q + p * p), var_r = 2.0f * a2;
        float k_t = var_t > 0.0f ? 1.0f / var_t : INFINITY;
        float k_r = var_r > 0.0f ? 1.0f / var_r : INFINITY;
        incident_sg(&j->lights, &j->env, b, p1, refl, k_r, l_refl);
        incident_sg(&j->lights, &j->env, b, p2, t2, k_t, l_trans);
        sj->blur_sigma[px] = 1.0f / sqrtf(k_t);
    } else {
        incident(&j->lights, b, p1, refl, l_refl);
        incident(&j->lights, b, p2, t2, l_trans);
    }
    int64_t l;
    int hidden = j->lights.nl > 0 &&
                 hit_light(&j->lights, b, j->eye + 3 * b, d, &l) < j->front_dist[px];
    if (!hidden) {
        for (int c = 0; c < 3; c++) {
            float att = expf(-j->absorption[3 * b + c] * path);
            j->radiance[3 * px + c] = e_r1 * l_refl[c] + e_t1 * w2 * att * l_trans[c];
        }
    }
    j->exit_found[px] = ok ? 1.0f : 0.0f;
    j->tir[px] = (tir1 || tir2) ? 1.0f : 0.0f;
}

/* One block of pixels: 1. the entry refraction (paths.trace_paths), 2. the march to the
 * exit over the block (march_core.h), 3. the rest per pixel. */
static void shade_block(const void *job, const SgAxes *axes, int64_t r0, int m) {
    const SpecJob *sj = (const SpecJob *)job;
    const Frame *j = &sj->f;
    Rays rays;
    float d[3 * BLOCK], n1[3 * BLOCK];
    int tir1[BLOCK];
    for (int i = 0; i < m; i++) {
        int64_t px = j->idx[r0 + i], b = j->batch[r0 + i];
        float *di = d + 3 * i, *ni = n1 + 3 * i, p1[3], t1[3], c0[3], ct[3];
        for (int c = 0; c < 3; c++) {
            di[c] = j->ray_dir[3 * px + c];
            p1[c] = j->front_pos[3 * px + c];
        }
        face_forward(j->front_normal + 3 * px, di, ni);
        tir1[i] = refract(di, ni, 1.0f / j->ior[b], t1);
        camera_coords(j, b, p1, 1, c0);
        camera_coords(j, b, t1, 0, ct);
        set_ray(j, &rays, i, b, p1, t1, c0, ct);
    }
    march_rays(j, &rays, m, j->march.steps, j->march.refine);
    for (int i = 0; i < m; i++) {
        int64_t b = j->batch[r0 + i];
        shade_pixel(sj, axes + 2 * b, &rays, i, d + 3 * i, n1 + 3 * i, tir1[i], j->idx[r0 + i],
                    b);
    }
}

/* Each view's entry (eta = ior) and exit (eta = 1 / ior) interfaces on the table (views
 * with a roughness map take theirs per pixel). */
static void spec_axes(const Frame *f, int64_t b, SgAxes *out) {
    sg_axes(&f->table, f->ior[b], f->alpha[b], out);
    sg_axes(&f->table, 1.0f / f->ior[b], f->alpha[b], out + 1);
}

/* Entry point (ctypes, shading/fused.py): shade all object pixels of ``job`` on
 * ``threads`` threads (frame.h's run_shading). */
int torchrefract_specular(SpecJob *job, int threads) {
    return run_shading(job, &job->f, 2, spec_axes, shade_block, threads);
}

int64_t torchrefract_specular_job_size(void) { return (int64_t)sizeof(SpecJob); }
