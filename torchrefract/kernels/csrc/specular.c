/* Fused shading of ``specular`` (methods/specular.py, shading/paths.py) without internal
 * bounces: per object pixel, in registers, the entry refraction, the march to the exit
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

static void shade_block(const SpecJob *sj, const SgAxes *axes, int64_t r0, int m) {
    const Frame *j = &sj->f;
    Rays rays;
    float d[3 * BLOCK], n1[3 * BLOCK];
    int tir1[BLOCK];
    /* 1. Entry: the refracted ray (paths.trace_paths). */
    for (int i = 0; i < m; i++) {
        int64_t px = j->idx[r0 + i], b = j->batch[r0 + i];
        float *di = d + 3 * i, *ni = n1 + 3 * i, p1[3], t1[3], c0[3], ct[3];
        for (int k = 0; k < 3; k++) {
            di[k] = j->ray_dir[3 * px + k];
            p1[k] = j->front_pos[3 * px + k];
        }
        face_forward(j->front_normal + 3 * px, di, ni);
        tir1[i] = refract(di, ni, 1.0f / j->ior[b], t1);
        camera_coords(j, b, p1, 1, c0);
        camera_coords(j, b, t1, 0, ct);
        set_ray(j, &rays, i, b, p1, t1, c0, ct);
    }
    /* 2. The march to the exit (march_core.h). */
    march_rays(j, &rays, m, j->march.steps, j->march.refine);
    /* 3. Exit and shading (paths.trace_paths, render_specular). */
    for (int i = 0; i < m; i++) {
        int64_t px = j->idx[r0 + i], b = rays.batch[i];
        const float *di = d + 3 * i, *ni = n1 + 3 * i, *pi = rays.p + 3 * i;
        const float *ti = rays.t + 3 * i, *nrm = rays.normal + 3 * i;
        const float *pos = rays.pos + 3 * i;
        float eta = j->ior[b], alpha = j->alpha[b];
        const SgAxes *in = axes + 2 * b, *out = axes + 2 * b + 1;
        int64_t dist = j->dist[b];
        int ok = rays.found[i];
        float cos1 = -dot3(di, ni);
        float f1 = fresnel(cos1, 1.0f / eta);
        float n2[3], t2[3];
        face_forward(nrm, ti, n2);
        float cos2 = -dot3(ti, n2);
        float f2 = fresnel(cos2, eta);
        int tir2 = refract(ti, n2, eta, t2) && ok;
        if (j->tir_mode == 2 && tir2) reflect(ti, n2, t2);
        float e_t1, e_r1, e_t2, e_r2, esc = 1.0f;
        if (alpha > 0.0f) {
            interface_energies(&j->table, in, dist, cos1, f1, &e_t1, &e_r1);
            if (j->tir_mode == 0) {  /* paths.spread_exit */
                int rough = alpha > j->table.alpha_min;
                float k1, tilt;
                transmit_lobe(&j->table, in, dist, cos1, &k1, &tilt);
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
                float var = rough ? 1.0f / k1 : 0.0f;
                spread_interface_energies(&j->table, out, dist, c_axis, var, eta, &e_t2, &e_r2);
                esc = escape(j, b, alpha);
            } else {
                interface_energies(&j->table, out, dist, cos2, f2, &e_t2, &e_r2);
            }
        } else {
            e_t1 = 1.0f - f1; e_r1 = f1; e_t2 = 1.0f - f2; e_r2 = f2;
        }
        /* optics.exit_rule.leaving_weight */
        float w2;
        if (j->tir_mode == 0) {
            w2 = e_t2 + e_r2 * esc;
            if (w2 > 1.0f) w2 = 1.0f;
        } else if (j->tir_mode == 2) {
            w2 = tir2 ? e_r2 : e_t2;
        } else {
            float kept = e_t2 + e_r2;
            w2 = tir2 ? (kept > 1.0f ? 1.0f : kept) : e_t2;
        }
        float p2[3], path;
        if (ok) {
            for (int k = 0; k < 3; k++) p2[k] = pos[k];
            path = rays.s[i];
        } else {  /* no exit: leave along the refracted ray, with weight 1 */
            for (int k = 0; k < 3; k++) { t2[k] = ti[k]; p2[k] = pi[k]; }
            w2 = 1.0f;
            float th = j->back_dist[px] - j->front_dist[px];
            path = th > 0.0f ? th : 0.0f;
        }
        float refl[3], l_refl[3], l_trans[3];
        reflect(di, ni, refl);
        if (sj->blur) {  /* prefiltered.blur_sharpness; no lights (fused.py) */
            float a2 = alpha * alpha, q = 1.0f - 1.0f / eta, p = eta - 1.0f;
            float spread = q * q + p * p;
            float var_t = 0.5f * a2 * spread, var_r = 2.0f * a2;
            float k_t = var_t > 0.0f ? 1.0f / var_t : INFINITY;
            float k_r = var_r > 0.0f ? 1.0f / var_r : INFINITY;
            sg_env_lookup(&j->lights, &j->env, b, refl, k_r, l_refl);
            sg_env_lookup(&j->lights, &j->env, b, t2, k_t, l_trans);
            sj->blur_sigma[px] = 1.0f / sqrtf(k_t);
        } else {
            incident(&j->lights, b, pi, refl, l_refl);
            incident(&j->lights, b, p2, t2, l_trans);
        }
        int hidden = 0;
        if (j->lights.nl > 0) {
            int64_t l;
            hidden = hit_light(&j->lights, b, j->eye + 3 * b, di, &l) < j->front_dist[px];
        }
        if (!hidden) {
            for (int c = 0; c < 3; c++) {
                float att = expf(-j->absorption[3 * b + c] * path);
                float through = e_t1 * w2 * att * l_trans[c];
                j->radiance[3 * px + c] = e_r1 * l_refl[c] + through;
            }
        }
        j->exit_found[px] = ok ? 1.0f : 0.0f;
        j->tir[px] = (tir1[i] || tir2) ? 1.0f : 0.0f;
    }
}

static void shade_range(const void *job, const void *axes, int64_t begin, int64_t end) {
    for (int64_t r = begin; r < end; r += BLOCK)
        shade_block((const SpecJob *)job, (const SgAxes *)axes, r,
                    end - r < BLOCK ? (int)(end - r) : BLOCK);
}

/* Entry point (ctypes, shading/fused.py): shade all object pixels of ``job`` on
 * ``threads`` threads. Returns 0, or -1 where memory or a thread could not be had (the
 * caller then runs its tensor code). */
int torchrefract_specular(SpecJob *job, int threads) {
    Frame *f = &job->f;
#ifdef HAVE_AVX2_PATH
    f->march.simd = f->march.simd && __builtin_cpu_supports("avx2");
#endif
    /* Each view's entry (eta = ior) and exit (eta = 1 / ior) interfaces on the table. */
    SgAxes *axes = (SgAxes *)malloc(sizeof(SgAxes) * 2 * (size_t)(f->nb > 0 ? f->nb : 1));
    if (!axes) return -1;
    for (int64_t b = 0; b < f->nb; b++) {
        sg_axes(&f->table, f->ior[b], f->alpha[b], axes + 2 * b);
        sg_axes(&f->table, 1.0f / f->ior[b], f->alpha[b], axes + 2 * b + 1);
    }
    int rc = shade_parallel(shade_range, job, axes, f->n, threads);
    free(axes);
    return rc;
}

int64_t torchrefract_specular_job_size(void) { return (int64_t)sizeof(SpecJob); }
