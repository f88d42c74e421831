/* Fused shading of method sh (shade.render_sh, Genevaux et al. 2006 secs. 3 and 5; the
 * rough lobes ours): per object pixel, in one pass, the front interface's lobes (de
 * Rousiers' eqs. 8-9 from the SG table), the view spread carried through Snell's law,
 * eq. 2's mapping at the view and four views around it (sh_eval.c's, through
 * torchrefract_sh_map_range), the exit's lobe and the ``exit_weight`` rule, the absorption,
 * the two environment lookups (SG pyramids, sphere lights), the pixel and its passes.
 *
 * The fused methods' frame (kernels/csrc/frame.h) carries the G-buffer, materials, table
 * and lighting, so the adaptive lattice's driver (kernels/csrc/lattice.c) runs this entry
 * for the first pass and every level as it runs theirs. With ``branches: 2`` the reflected
 * branch's channels are mapped and its lobe added the same way (step 5 of shade.py). The
 * tensor code (render_sh) is the reference and the differentiable path; the same formulas
 * in float32, in its order (tests/test_sh.py holds the two together). A roughness map is
 * read at the front hit (both interfaces' roughness, as there). Not here (shade.py runs its
 * tensor code): more than 64 lights. The batch's views may show meshes of several
 * tables, each mapped with its own, and index-matched ones (no table). */

#include "../../../kernels/csrc/frame.h"
#include "sh_jobs.h"

typedef struct {
    Frame f;                 /* first: the lattice driver sets its pixels per pass */
    ShMapJob *maps;          /* (ntables,) each table's job: its table and the items' poses
                              * (the per-pixel arrays, positions and outputs are a block's
                              * own; ``rough`` is set by the entry) */
    ShMapJob *branches;      /* (ntables,) the same over the branch's channels (with
                              * ``two``), else NULL */
    const int64_t *table_of; /* (B,) each view's table; -1: none (IOR 1, index-matched) */
    int64_t ntables;
    int two;                 /* branches: 2 */
    int conserve;            /* exit_weight: 1 conserve, 0 path */
    float *lobe_sigma;       /* (B*H*W,) out: the transmitted lobe's k^-1/2 */
    float *path_length;      /* (B*H*W,) out: the world length inside */
    const void *shared;      /* the map's constants, made by the entry (NULL from Python) */
} ShShadeJob;

#define CRITICAL_MARGIN 1e-4f /* optics.exit_rule.CRITICAL_MARGIN */
#define ALPHA_MIN 1e-4f       /* optics.microfacet.ALPHA_MIN */
#define ROUGH 1e-3f           /* shade.ROUGH */

/* object_pixels' roughness of pixel px in view b: the map at its front UV, else the
 * view's; at least ALPHA_MIN. */
static inline float front_alpha(const Frame *f, int64_t b, int64_t px) {
    float a = roughness_at(f, b, f->front_uv + 2 * px);
    return a > ALPHA_MIN ? a : ALPHA_MIN;
}

/* Each view's entry and exit interfaces (frame.h's view_axes). */
static int sh_axes(const Frame *f, int64_t b, SgAxes *out) {
    view_axes(f, b, out);
    return AXES;
}

static const int64_t POSITIONS[BLOCK] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14,
                                         15};

/* nan_to_num(nan=0, posinf=0, neginf=0) */
static inline float finite_or_zero(float x) { return isfinite(x) ? x : 0.0f; }

/* Per-pixel outputs of the map (shade._map_pixels) over a block. */
typedef struct {
    float dir[3 * BLOCK], len[BLOCK], cos_x[BLOCK], thr[BLOCK], var_geo[BLOCK];
} Mapped;

/* shade._map_pixels over the block's m pixels from r0, each run of pixels whose views share
 * a table with that table's job (``maps``, per table; ``table_of``, per view). A view
 * without a table (index-matched) gets render_sh's values there: the camera ray, and the
 * layers' gap as the length (the main path), or no energy (the ``branch``). */
static void map_block(const ShMapJob *maps, const int64_t *table_of, const void *shared,
                      const Frame *j, int64_t r0, int m, const float *view,
                      const float *var_view, const float *alpha, int branch, Mapped *out) {
    for (int s = 0, e; s < m; s = e) {
        int64_t t = table_of[j->batch[r0 + s]];
        for (e = s + 1; e < m && table_of[j->batch[r0 + e]] == t; e++) {}
        if (t < 0) {
            for (int i = s; i < e; i++) {
                int64_t px = j->idx[r0 + i];
                float gap = j->back_dist[px] - j->front_dist[px];
                for (int c = 0; c < 3; c++) out->dir[3 * i + c] = j->ray_dir[3 * px + c];
                out->len[i] = branch ? 0.0f : (gap > 0.0f ? gap : 0.0f);
                out->cos_x[i] = 1.0f;
                out->thr[i] = branch ? 0.0f : 1.0f;
                out->var_geo[i] = 0.0f;
            }
            continue;
        }
        ShMapJob mj = maps[t];
        mj.n = e - s;
        mj.sel = POSITIONS;
        mj.pix = j->idx + r0 + s;
        mj.item = j->batch + r0 + s;
        mj.view = view + 3 * s;
        mj.var_view = var_view + s;
        mj.alpha = alpha + s;
        mj.direction = out->dir + 3 * s;
        mj.length = out->len + s;
        mj.cos_exit = out->cos_x + s;
        mj.throughput = out->thr + s;
        mj.var_geo = out->var_geo + s;
        torchrefract_sh_map_range(&mj, shared, 0, e - s);
    }
}

/* The exit's lobe sharpness k (exit_lobe: held just outside TIR at the stored exit cosine,
 * widened by the path's variance) and, under ``conserve``, its leaving weight (else *w is
 * left as it is). */
static float exit_lobe(const ShShadeJob *sj, const SgAxes *ax, int64_t b, float alpha,
                       float cos_exit, float var_g, float var1, float *w) {
    const Frame *j = &sj->f;
    int64_t d = j->dist[b];
    float ior = j->ior[b], c2 = 1.0f - 1.0f / (ior * ior);
    float crit = sqrtf(c2 > 0.0f ? c2 : 0.0f) + CRITICAL_MARGIN;
    float cos_in = cos_exit > crit ? cos_exit : crit;
    cos_in = cos_in < 1.0f ? cos_in : 1.0f;
    float k_t2, ang, e;
    sg_lobe_at(&j->table, ax + OUT, ax + OUT0, d, 0, sg_theta(cos_in), &k_t2, &ang, &e);
    float inv = 1.0f / k_t2 + var_g;
    if (sj->conserve) {
        float e_t2, e_r2;
        spread_table_energies(&j->table, ax + OUT, ax + OUT0, d, cos_in, var1, &e_t2, &e_r2);
        float lw = e_t2 + e_r2 * escape(j, b, alpha);
        *w = lw < 1.0f ? lw : 1.0f;
    }
    return 1.0f / (inv > 1e-12f ? inv : 1e-12f);
}

/* Steps 1-2 of a block's pixels: what the front interface gives each. */
typedef struct {
    float view[3 * BLOCK], var_view[BLOCK], alpha[BLOCK], var1[BLOCK];
    float e_r[BLOCK], k_r[BLOCK], axis_r[3 * BLOCK], e_t1[BLOCK];
    SgAxes own[BLOCK][AXES];
    const SgAxes *ax[BLOCK];  /* each pixel's table axes (its view's, or own) */
} Front;

/* 1. object_pixels and the front lobes (lobes.front_lobes), 2. the view's spread, of the
 * block's m pixels from r0. */
static void front_block(const Frame *j, const SgAxes *axes, int64_t r0, int m, Front *fr) {
    for (int i = 0; i < m; i++) {
        int64_t px = j->idx[r0 + i], b = j->batch[r0 + i], d = j->dist[b];
        float n1[3], *v = fr->view + 3 * i;
        for (int c = 0; c < 3; c++) v[c] = -j->ray_dir[3 * px + c];
        face_forward(j->front_normal + 3 * px, j->ray_dir + 3 * px, n1);
        float cos1 = clampf(dot3(v, n1), 0.0f, 1.0f), eta = j->ior[b], ang, k_t1;
        fr->alpha[i] = front_alpha(j, b, px);
        const SgAxes *ax = fr->ax[i] = axes_at(j, axes + AXES * b, b, fr->alpha[i],
                                               fr->own[i]);
        float z = sg_theta(cos1);
        sg_lobe_at(&j->table, ax + IN, ax + IN0, d, 1, z, fr->k_r + i, &ang, fr->e_r + i);
        lobe_axis(v, n1, ang, 1.0f, fr->axis_r + 3 * i);
        sg_lobe_at(&j->table, ax + IN, ax + IN0, d, 0, z, &k_t1, &ang, fr->e_t1 + i);
        fr->var1[i] = 1.0f / (k_t1 > 1e-12f ? k_t1 : 1e-12f);
        /* _snell_spread: d theta_o / d theta_t = eta cos_t / cos_o in the plane, eta
         * across it */
        float cos_o = cos1 > 0.05f ? cos1 : 0.05f;
        float sin2_t = (1.0f - cos_o * cos_o) / (eta * eta), ct2 = 1.0f - sin2_t;
        float cos_t = sqrtf(ct2 > 0.0f ? ct2 : 0.0f), m1 = eta * cos_t / cos_o;
        fr->var_view[i] = fr->var1[i] * 0.5f * (m1 * m1 + eta * eta);
    }
}

static void sh_block(const void *vjob, const SgAxes *axes, int64_t r0, int m) {
    const ShShadeJob *sj = (const ShShadeJob *)vjob;
    const Frame *j = &sj->f;
    Front fr;
    front_block(j, axes, r0, m, &fr);
    float *view = fr.view, *var_view = fr.var_view, *alpha = fr.alpha, *var1 = fr.var1;
    float *e_r = fr.e_r, *k_r = fr.k_r, *axis_r = fr.axis_r, *e_t1 = fr.e_t1;
    const SgAxes *const *axp = fr.ax;
    /* 3. eq. 2 over the block (and the branch's): the exit direction, length, exit
     * cosine, throughput and the geometric variance */
    Mapped mp, br;
    map_block(sj->maps, sj->table_of, sj->shared, j, r0, m, view, var_view, alpha, 0, &mp);
    if (sj->two)
        map_block(sj->branches, sj->table_of, sj->shared, j, r0, m, view, var_view, alpha, 1,
                  &br);
    /* 4. the exit's lobe and weight; 5. the branch's */
    float k[BLOCK], w2[BLOCK], wb[BLOCK], kb[BLOCK];
    for (int i = 0; i < m; i++) {
        int64_t b = j->batch[r0 + i];
        const SgAxes *ax = axp[i];
        w2[i] = mp.thr[i];
        k[i] = exit_lobe(sj, ax, b, alpha[i], mp.cos_x[i], mp.var_geo[i], var1[i], w2 + i);
        if (sj->two) {  /* the branch carries its energy; conserve: the main path's share
                         * less it */
            float eb = br.thr[i];
            wb[i] = 1.0f;
            kb[i] = exit_lobe(sj, ax, b, alpha[i], br.cos_x[i], br.var_geo[i], var1[i],
                              wb + i);
            wb[i] = wb[i] * eb;
            if (sj->conserve) w2[i] = w2[i] * (1.0f - eb);
        }
        if (sj->table_of[b] < 0) {  /* index-matched: invisible (the straight ray,
                                     * unblurred, all the light) */
            e_r[i] = 0.0f;
            e_t1[i] = 1.0f;
            w2[i] = 1.0f;
            k[i] = INFINITY;
        }
    }
    /* the lookups of the block, their texels asked for at once (8 in lanes), then read;
     * the absorption, the pixel and its passes */
    SgTap t_refl[BLOCK], t_trans[BLOCK], t_b[BLOCK];
    block_taps(j, r0, m, axis_r, k_r, t_refl);
    block_taps(j, r0, m, mp.dir, k, t_trans);
    if (sj->two) block_taps(j, r0, m, br.dir, kb, t_b);
    for (int i = 0; i < m; i++) {
        int64_t px = j->idx[r0 + i], b = j->batch[r0 + i];
        const float *p1 = j->front_pos + 3 * px;
        float l_refl[3], l_trans[3], l_b[3];
        incident_sg_at(&j->lights, b, p1, axis_r + 3 * i, k_r[i], t_refl + i, l_refl);
        incident_sg_at(&j->lights, b, p1, mp.dir + 3 * i, k[i], t_trans + i, l_trans);
        if (sj->two) incident_sg_at(&j->lights, b, p1, br.dir + 3 * i, kb[i], t_b + i, l_b);
        int64_t l;
        int hidden = j->lights.nl > 0 &&
                     hit_light(&j->lights, b, j->eye + 3 * b, j->ray_dir + 3 * px, &l) <
                         j->front_dist[px];
        if (!hidden)
            for (int c = 0; c < 3; c++) {
                float a = j->absorption[3 * b + c];
                float v = e_r[i] * l_refl[c] + e_t1[i] * w2[i] * expf(-a * mp.len[i]) *
                                                   l_trans[c];
                if (sj->two) v = v + e_t1[i] * wb[i] * expf(-a * br.len[i]) * l_b[c];
                v = finite_or_zero(v);
                j->radiance[3 * px + c] = v > 0.0f ? v : 0.0f;
            }
        float kk = k[i] > 1e-12f ? k[i] : 1e-12f;
        sj->lobe_sigma[px] = finite_or_zero(1.0f / sqrtf(kk));
        sj->path_length[px] = finite_or_zero(mp.len[i]);
    }
}

/* Entry point (ctypes, methods/sh/shade.py; the lattice driver's tr_kernel_fn): shade the
 * frame's pixels on ``threads`` threads (frame.h's run_shading). */
int torchrefract_sh_shade(ShShadeJob *job, int threads) {
    const Frame *f = &job->f;
    /* the map's constants once per call (the branch's order and window are the same) */
    size_t size = (size_t)torchrefract_sh_shared_size();
    void *shared = aligned_alloc(64, (size + 63) / 64 * 64);
    /* per view whether its pixels of this pass read the four offset views (render_sh: any
     * of them rougher than ROUGH; a view's own roughness where it has no map) */
    uint8_t *rough = (uint8_t *)calloc((size_t)(f->nb > 0 ? f->nb : 1), 1);
    if (!shared || !rough) {
        free(shared);
        free(rough);
        return -1;
    }
    for (int64_t b = 0; b < f->nb; b++)
        rough[b] = !f->rmap[b] && (f->alpha[b] > ALPHA_MIN ? f->alpha[b] : ALPHA_MIN) > ROUGH;
    for (int64_t i = 0; i < f->n; i++) {
        int64_t b = f->batch[i];
        if (f->rmap[b] && !rough[b]) rough[b] = front_alpha(f, b, f->idx[i]) > ROUGH;
    }
    torchrefract_sh_shared_init(job->maps, shared);  /* one order and window per pass */
    job->shared = shared;
    for (int64_t t = 0; t < job->ntables; t++) {
        job->maps[t].rough = rough;
        if (job->two) job->branches[t].rough = rough;
    }
    int rc = run_shading(job, &job->f, AXES, sh_axes, sh_block, threads);
    job->shared = NULL;
    for (int64_t t = 0; t < job->ntables; t++) {
        job->maps[t].rough = NULL;
        if (job->two) job->branches[t].rough = NULL;
    }
    free(shared);
    free(rough);
    return rc;
}

int64_t torchrefract_sh_shade_job_size(void) { return (int64_t)sizeof(ShShadeJob); }
