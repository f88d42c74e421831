/* Method sh: the precomputation's paths (paths.trace_paths, paper secs. 3 and 5.4) in C,
 * with Embree called from here (methods/sh/native.py builds it into the library of
 * sh_eval.c; tracer.EmbreeNative hands over the scene and rtcIntersect1/16).
 *
 * One path per (sample, view direction), followed to its end: entry refraction at the
 * sample, then per interface the nearest hit (rtcIntersect16 packets, or rtcIntersect1 as
 * embreex's EmbreeScene.run calls it, with the same ray fields: the same hits), the side of
 * the flat triangle, the interpolated shading normal, the exact Fresnel term, the branch
 * (tir or greedy), refraction or reflection, the length inside, the throughput, the
 * last exit cosine and the rough-interface gain there (paths.py). Paths run in blocks of SH_BLOCK as a wavefront: the live ones stay compact in
 * the block's arrays (no scatter back per interface), ended ones are written out. With
 * branches = 2, a path refracting out from inside for the first time (not at the last
 * interface) also appends its reflected branch to the block's live rays (room for 2 x
 * SH_BLOCK), followed from the next interface on with the same rules, and written to the
 * branch outputs (paths.trace_paths' rows count.. and PathEnds.branch).
 *
 * Every float operation is the tensor code's, in its order (optics.smooth.dot, refract,
 * reflect, fresnel_dielectric, normalize; Tensor.norm and torch.cross as in common.h;
 * torch.sqrt through the function torch uses, below), built with -ffp-contract=off and no
 * fast-math: the path ends are bit-equal to paths.trace_paths with the embree tracer on
 * every path tested (tests/test_sh.py). */

#include <stdlib.h>

#include "../../../kernels/csrc/common.h"

TR_DEFINE_VEC3(float, p, fmaf, fabsf, sqrtf, 1e-30f)

/* Embree 4's RTCRayHit (rtcore_ray.h), with room after the hit for the fields that
 * builds with instance arrays add (instPrimID): Embree writes nothing beyond it. */
typedef struct {
    float org_x, org_y, org_z, tnear;
    float dir_x, dir_y, dir_z, time;
    float tfar;
    uint32_t mask, id, flags;
    float ng_x, ng_y, ng_z;
    float u, v;
    uint32_t prim_id, geom_id, inst_id[1];
    uint32_t spare[8];
} __attribute__((aligned(16))) ShRayHit;

typedef void (*sh_intersect1_fn)(void *scene, ShRayHit *rayhit, void *args);

/* Embree 4's RTCRayHit16 (structure of arrays), with room for instPrimID as above */
typedef struct {
    float org_x[16], org_y[16], org_z[16], tnear[16];
    float dir_x[16], dir_y[16], dir_z[16], time[16];
    float tfar[16];
    uint32_t mask[16], id[16], flags[16];
    float ng_x[16], ng_y[16], ng_z[16];
    float u[16], v[16];
    uint32_t prim_id[16], geom_id[16], inst_id[1][16];
    uint32_t spare[2][16];
} __attribute__((aligned(64))) ShRayHit16;

typedef void (*sh_intersect16_fn)(const int *valid, void *scene, ShRayHit16 *rayhit,
                                  void *args);

#define SH_INVALID_ID 0xFFFFFFFFu

/* The square roots of the tensor code's refraction and Fresnel term, over n values:
 * torch.sqrt on float32 is MKL's vsSqrt where torch is built with MKL (not correctly
 * rounded: ~20% of values differ from sqrtf by one ulp, independently of their neighbours),
 * so native.py hands that function over when torch.sqrt matches it; else NULL (sqrtf). */
typedef void (*sh_vsqrt_fn)(int n, const float *a, float *r);

typedef struct {
    int64_t n;            /* paths */
    int64_t max_events;   /* interfaces followed after the entry */
    int64_t greedy;       /* 1: reflect where F > 1/2 (the paper); 0: only under TIR */
    float ior;            /* float32(ior) */
    float inv_ior;        /* float32(1 / ior) (as torch rounds the Python double) */
    float eps;            /* float32(origin offset) */
    float pad0;
    const float *p;       /* (n, 3) entry points */
    const float *nrm;     /* (n, 3) outward shading normals there */
    const float *omega;   /* (n, 3) unit directions towards the viewer */
    const float *tri_n;   /* (F, 3, 3) unit shading normals at the corners */
    const float *g_n;     /* (F, 3) unit geometric normals (outward by winding) */
    void *scene;          /* RTCScene, committed */
    void *intersect1;     /* rtcIntersect1 */
    void *intersect16;    /* rtcIntersect16 (packets of 16 rays), or NULL: one by one */
    void *vsqrt;          /* sh_vsqrt_fn or NULL */
    float *direction;     /* (n, 3) out */
    float *length;        /* (n,) out */
    float *cos_exit;      /* (n,) out */
    float *throughput;    /* (n,) out */
    int64_t *events;      /* (n,) out */
    int64_t branches;     /* 1, or 2: also the reflected branch at the first exit */
    float *b_direction;   /* (n, 3) out (branches 2): the branch's, where it split */
    float *b_length;      /* (n,) out */
    float *b_cos_exit;    /* (n,) out */
    float *b_throughput;  /* (n,) out: its energy (0 where the path never split) */
    int64_t *b_events;    /* (n,) out: its interfaces after the split */
    uint8_t *b_split;     /* (n,) out: whether the path split (0: the branch outputs unset) */
    float *gain;          /* (n,) out: the rough-interface gain at the last exit */
    float *b_gain;        /* (n,) out (branches 2): the branch's */
} ShPathJob;

#define SH_GRAZING_COS 0.05f /* paths.GRAZING_COS */

/* optics.smooth.normalize */
static inline void normalize3p(float *v) {
    float l = norm3p(v);
    if (l < 1e-20f) l = 1e-20f;
    for (int t = 0; t < 3; t++) v[t] = v[t] / l;
}

static inline float clamp01(float x) { return x < 0.0f ? 0.0f : (x > 1.0f ? 1.0f : x); }

static void vsqrt(const ShPathJob *job, int n, const float *a, float *r) {
    if (n <= 0) return;
    if (job->vsqrt) {
        ((sh_vsqrt_fn)job->vsqrt)(n, a, r);
    } else {
        for (int i = 0; i < n; i++) r[i] = sqrtf(a[i]);
    }
}

/* 1 - sin^2 theta_t clamped at 0, and whether it is TIR (optics.smooth.refract and
 * fresnel_dielectric, which share it) */
static inline float cos_t_squared(float cos_i, float eta, int *tir) {
    float sin2_t = (eta * eta) * (1.0f - cos_i * cos_i);
    *tir = sin2_t >= 1.0f;
    float r = 1.0f - sin2_t;
    return r < 0.0f ? 0.0f : r;
}

/* optics.smooth.refract given cos_t: the unit transmitted direction */
static inline void refract_with(const float *d, const float *n, float eta, float cos_i,
                                float cos_t, float *out) {
    float a = eta * cos_i - cos_t;
    for (int t = 0; t < 3; t++) out[t] = eta * d[t] + a * n[t];
    normalize3p(out);
}

/* optics.smooth.fresnel_dielectric given cos_t */
static inline float fresnel_with(float cos_i, float eta, float cos_t, int tir) {
    if (tir) return 1.0f;
    float ec = eta * cos_i;
    float rs_den = ec + cos_t, rp_den = cos_i + eta * cos_t;
    if (rs_den < 1e-12f) rs_den = 1e-12f;
    if (rp_den < 1e-12f) rp_den = 1e-12f;
    float rs = (ec - cos_t) / rs_den;
    float rp = (cos_i - eta * cos_t) / rp_den;
    return clamp01(0.5f * (rs * rs + rp * rp));
}

/* paths.interface_gains: the rough-interface gain if the path refracts here (g_t) and if
 * it reflects (g_r), in its operations' order */
static inline void interface_gains(float eta, float cos_i, float cos_t, float *g_t,
                                   float *g_r) {
    const float ct = cos_t < SH_GRAZING_COS ? SH_GRAZING_COS : cos_t;
    const float turn = (eta * cos_i) / ct;
    const float e1 = eta - 1.0f;
    *g_t = 0.5f * ((turn - 1.0f) * (turn - 1.0f) + e1 * e1);
    *g_r = 2.0f * (1.0f + cos_i * cos_i);
}

#define SH_BLOCK 256
#define SH_CAP (2 * SH_BLOCK) /* live rays of a block: its paths and their branches */

/* The paths of one block, as a wavefront: the live ones compacted after every interface
 * (no scatter back), one vector square root per interface for them all. */
typedef struct {
    int64_t idx[SH_CAP];
    float org[SH_CAP][3], dir[SH_CAP][3];
    float length[SH_CAP], cos_exit[SH_CAP], thr[SH_CAP];
    float gain[SH_CAP], gain_exit[SH_CAP]; /* G so far; at the last exit so far */
    int inside[SH_CAP];
    int fork[SH_CAP];    /* 1: a reflected branch (branches 2) */
    int split[SH_CAP];   /* a main path that has split off its branch */
    int64_t events[SH_CAP];
    /* this interface's */
    float x[SH_CAP][3], ngf[SH_CAP][3], nsf[SH_CAP][3];
    float eta[SH_CAP], cos_i[SH_CAP], sq_in[SH_CAP], sq_out[SH_CAP];
    int leaving[SH_CAP], tir[SH_CAP];
    /* the nearest hits of the live rays */
    float hit_t[SH_CAP], hit_u[SH_CAP], hit_v[SH_CAP];
    int64_t hit_f[SH_CAP];
} ShBlock;

/* The nearest hits of the block's `live` rays (hit_f -1: none), as EmbreeScene.run fills
 * and reads its rays; in packets of 16 where the job has rtcIntersect16. */
static void cast_rays(const ShPathJob *job, ShBlock *b, int live) {
    if (job->intersect16) {
        const sh_intersect16_fn isect16 = (sh_intersect16_fn)job->intersect16;
        ShRayHit16 rh;
        int valid[16];
        for (int j0 = 0; j0 < live; j0 += 16) {
            const int m = live - j0 < 16 ? live - j0 : 16;
            for (int l = 0; l < 16; l++) {
                const int j = j0 + (l < m ? l : 0);
                valid[l] = l < m ? -1 : 0;
                rh.org_x[l] = b->org[j][0]; rh.org_y[l] = b->org[j][1];
                rh.org_z[l] = b->org[j][2];
                rh.tnear[l] = 0.0f;
                rh.dir_x[l] = b->dir[j][0]; rh.dir_y[l] = b->dir[j][1];
                rh.dir_z[l] = b->dir[j][2];
                rh.time[l] = 0.0f;
                rh.tfar[l] = 1e37f;
                rh.mask[l] = 0xFFFFFFFFu;
                rh.id[l] = 0;
                rh.flags[l] = 0;
                rh.geom_id[l] = SH_INVALID_ID;
                rh.prim_id[l] = SH_INVALID_ID;
                rh.inst_id[0][l] = SH_INVALID_ID;
            }
            isect16(valid, job->scene, &rh, NULL);
            for (int l = 0; l < m; l++) {
                const int j = j0 + l;
                const int hit = rh.geom_id[l] != SH_INVALID_ID && (int32_t)rh.prim_id[l] >= 0;
                b->hit_f[j] = hit ? (int64_t)rh.prim_id[l] : -1;
                b->hit_t[j] = rh.tfar[l];
                b->hit_u[j] = rh.u[l];
                b->hit_v[j] = rh.v[l];
            }
        }
        return;
    }
    const sh_intersect1_fn isect = (sh_intersect1_fn)job->intersect1;
    ShRayHit rh;
    for (int j = 0; j < live; j++) {
        rh.org_x = b->org[j][0]; rh.org_y = b->org[j][1]; rh.org_z = b->org[j][2];
        rh.tnear = 0.0f;
        rh.dir_x = b->dir[j][0]; rh.dir_y = b->dir[j][1]; rh.dir_z = b->dir[j][2];
        rh.time = 0.0f;
        rh.tfar = 1e37f;
        rh.mask = 0xFFFFFFFFu;
        rh.id = 0;
        rh.flags = 0;
        rh.geom_id = SH_INVALID_ID;
        rh.prim_id = SH_INVALID_ID;
        rh.inst_id[0] = SH_INVALID_ID;
        isect(job->scene, &rh, NULL);
        const int hit = rh.geom_id != SH_INVALID_ID && (int32_t)rh.prim_id >= 0;
        b->hit_f[j] = hit ? (int64_t)rh.prim_id : -1;
        b->hit_t[j] = rh.tfar;
        b->hit_u[j] = rh.u;
        b->hit_v[j] = rh.v;
    }
}

static void finish(const ShPathJob *job, const ShBlock *b, int j) {
    const int64_t i = b->idx[j];
    if (b->fork[j]) {
        for (int t = 0; t < 3; t++) job->b_direction[3 * i + t] = b->dir[j][t];
        job->b_length[i] = b->length[j];
        job->b_cos_exit[i] = b->cos_exit[j];
        job->b_throughput[i] = b->thr[j];
        job->b_events[i] = b->events[j];
        job->b_gain[i] = b->gain_exit[j];
        job->b_split[i] = 1;
        return;
    }
    for (int t = 0; t < 3; t++) job->direction[3 * i + t] = b->dir[j][t];
    job->length[i] = b->length[j];
    job->cos_exit[i] = b->cos_exit[j];
    job->throughput[i] = b->thr[j];
    job->events[i] = b->events[j];
    job->gain[i] = b->gain_exit[j];
}

static void copy_live(ShBlock *b, int to, int from) {
    if (to == from) return;
    b->idx[to] = b->idx[from];
    for (int t = 0; t < 3; t++) {
        b->org[to][t] = b->org[from][t];
        b->dir[to][t] = b->dir[from][t];
        b->x[to][t] = b->x[from][t];
        b->ngf[to][t] = b->ngf[from][t];
        b->nsf[to][t] = b->nsf[from][t];
    }
    b->length[to] = b->length[from];
    b->cos_exit[to] = b->cos_exit[from];
    b->thr[to] = b->thr[from];
    b->gain[to] = b->gain[from];
    b->gain_exit[to] = b->gain_exit[from];
    b->inside[to] = b->inside[from];
    b->fork[to] = b->fork[from];
    b->split[to] = b->split[from];
    b->events[to] = b->events[from];
    b->eta[to] = b->eta[from];
    b->cos_i[to] = b->cos_i[from];
    b->sq_in[to] = b->sq_in[from];
    b->leaving[to] = b->leaving[from];
    b->tir[to] = b->tir[from];
}

static void sh_paths_range(const void *vjob, int64_t begin, int64_t end) {
    const ShPathJob *job = (const ShPathJob *)vjob;
    const float eps = job->eps, ior = job->ior, inv_ior = job->inv_ior;
    ShBlock *b = (ShBlock *)malloc(sizeof(ShBlock));
    if (!b) return;
    for (int64_t b0 = begin; b0 < end; b0 += SH_BLOCK) {
        int live = (int)(end - b0 < SH_BLOCK ? end - b0 : SH_BLOCK);
        /* the entry: refraction into the object at the sample */
        for (int j = 0; j < live; j++) {
            const int64_t i = b0 + j;
            const float *n = job->nrm + 3 * i, *om = job->omega + 3 * i;
            float d0[3] = {-om[0], -om[1], -om[2]};
            int flip = dot3p(n, d0) > 0.0f; /* face_forward */
            for (int t = 0; t < 3; t++) {
                b->nsf[j][t] = flip ? -n[t] : n[t];
                b->dir[j][t] = d0[t];
            }
            b->cos_i[j] = clamp01(-dot3p(d0, b->nsf[j]));
            b->sq_in[j] = cos_t_squared(b->cos_i[j], inv_ior, &b->tir[j]);
        }
        vsqrt(job, live, b->sq_in, b->sq_out);
        for (int j = 0; j < live; j++) {
            const int64_t i = b0 + j;
            const float *p = job->p + 3 * i, *n = job->nrm + 3 * i;
            float d0[3] = {b->dir[j][0], b->dir[j][1], b->dir[j][2]};
            refract_with(d0, b->nsf[j], inv_ior, b->cos_i[j], b->sq_out[j], b->dir[j]);
            for (int t = 0; t < 3; t++) b->org[j][t] = p[t] - eps * n[t]; /* just inside */
            b->idx[j] = i;
            b->inside[j] = 1;
            b->length[j] = 0.0f;
            b->cos_exit[j] = 1.0f;
            b->thr[j] = 1.0f;
            b->gain[j] = 0.0f;
            b->gain_exit[j] = 0.0f;
            b->fork[j] = 0;
            b->split[j] = 0;
            b->events[j] = 0;
        }
        for (int64_t k = 0; k <= job->max_events && live > 0; k++) {
            /* nearest hits; misses end (outside: left for good; inside: a leak) */
            cast_rays(job, b, live);
            int kept = 0;
            for (int j = 0; j < live; j++) {
                if (b->hit_f[j] < 0) {
                    finish(job, b, j);
                    continue;
                }
                const int64_t f = b->hit_f[j];
                const float tt = b->hit_t[j], hu = b->hit_u[j], hv = b->hit_v[j];
                copy_live(b, kept, j);
                const int q = kept++;
                if (b->inside[q]) b->length[q] = b->length[q] + tt;
                const float *d = b->dir[q];
                for (int t = 0; t < 3; t++) b->x[q][t] = b->org[q][t] + tt * d[t];
                const float *ng = job->g_n + 3 * f, *cn = job->tri_n + 9 * f;
                float w0 = 1.0f - (hu + hv), w1 = hu, w2 = hv;
                float ns[3];
                for (int t = 0; t < 3; t++)
                    ns[t] = (w0 * cn[t] + w1 * cn[3 + t]) + w2 * cn[6 + t];
                normalize3p(ns);
                const int leaving = dot3p(d, ng) > 0.0f;
                float *ngf = b->ngf[q], *nsf = b->nsf[q];
                for (int t = 0; t < 3; t++) ngf[t] = leaving ? -ng[t] : ng[t];
                const int nflip = dot3p(ns, ngf) < 0.0f;
                for (int t = 0; t < 3; t++) nsf[t] = nflip ? -ns[t] : ns[t];
                if (dot3p(d, nsf) >= 0.0f) /* shading normal behind: the flat one */
                    for (int t = 0; t < 3; t++) nsf[t] = ngf[t];
                b->leaving[q] = leaving;
                b->eta[q] = leaving ? ior : inv_ior;
                b->cos_i[q] = clamp01(-dot3p(d, nsf));
                b->sq_in[q] = cos_t_squared(b->cos_i[q], b->eta[q], &b->tir[q]);
            }
            live = kept;
            vsqrt(job, live, b->sq_in, b->sq_out);
            const int last = k == job->max_events;
            int added = 0;
            for (int j = 0; j < live; j++) {
                const float *d = b->dir[j], *nsf = b->nsf[j];
                const float eta = b->eta[j], cos_i = b->cos_i[j], cos_t = b->sq_out[j];
                const float fr = fresnel_with(cos_i, eta, cos_t, b->tir[j]);
                float tdir[3], rdir[3];
                refract_with(d, nsf, eta, cos_i, cos_t, tdir);
                const float dn = dot3p(d, nsf);
                for (int t = 0; t < 3; t++) rdir[t] = d[t] - (2.0f * dn) * nsf[t];
                const int take_r = last ? 0 : (job->greedy ? fr > 0.5f : b->tir[j]);
                float g_t, g_r;
                interface_gains(eta, cos_i, cos_t, &g_t, &g_r);
                if (job->branches == 2 && !last && !take_r && b->leaving[j] && !b->fork[j]
                    && !b->split[j]) {
                    /* the first refraction out: the reflected branch joins the wavefront */
                    const int q = live + added++;
                    const float offr = eps * -1.0f;
                    for (int t = 0; t < 3; t++) {
                        b->org[q][t] = b->x[j][t] + offr * -b->ngf[j][t];
                        b->dir[q][t] = rdir[t];
                    }
                    normalize3p(b->dir[q]);
                    b->idx[q] = b->idx[j];
                    b->thr[q] = b->thr[j] * fr;
                    b->gain[q] = b->gain[j] + g_r;
                    b->gain_exit[q] = b->gain_exit[j];
                    b->length[q] = b->length[j];
                    b->cos_exit[q] = b->cos_exit[j];
                    b->inside[q] = b->inside[j];
                    b->fork[q] = 1;
                    b->split[q] = 0;
                    b->events[q] = 0;
                    b->split[j] = 1;
                }
                const float off = eps * (take_r ? -1.0f : 1.0f);
                for (int t = 0; t < 3; t++) {
                    b->org[j][t] = b->x[j][t] + off * -b->ngf[j][t];
                    b->dir[j][t] = take_r ? rdir[t] : tdir[t];
                }
                normalize3p(b->dir[j]);
                b->thr[j] = b->thr[j] * (take_r ? fr : 1.0f - fr);
                b->events[j] += 1;
                if (!take_r && b->leaving[j]) {
                    b->cos_exit[j] = cos_i;
                    b->gain_exit[j] = b->gain[j];
                }
                b->gain[j] = b->gain[j] + (take_r ? g_r : g_t);
                if (!take_r) b->inside[j] = !b->inside[j];
            }
            if (last)
                for (int j = 0; j < live; j++) finish(job, b, j);
            live += added;
        }
    }
    free(b);
}

int64_t torchrefract_sh_paths_job_size(void) { return (int64_t)sizeof(ShPathJob); }

int64_t torchrefract_sh_rayhit_size(void) { return (int64_t)sizeof(ShRayHit); }

int torchrefract_sh_paths(const ShPathJob *job, int threads) {
    if (job->n < 0 || job->max_events < 0 || !job->scene || !job->intersect1) return -2;
    return tr_parallel_for(sh_paths_range, job, job->n, 4096, threads);
}
