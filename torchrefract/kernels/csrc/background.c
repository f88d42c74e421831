/* What the camera sees without the object (shading/background.py), fused: per pixel the
 * environment, or a sphere light the camera ray hits before the object. Without lights the
 * object's pixels are left at zero (the method shades them); with lights every pixel is
 * looked up, and a light in front of the object shows. */

#include "lighting.h"

#include <string.h>

typedef struct {
    int64_t b, hw;              /* views, pixels per view */
    const float *ray_dir;       /* (B*H*W, 3) */
    const float *eye;           /* (B, 3) */
    const uint8_t *front_mask;  /* (B*H*W,) */
    const float *front_dist;    /* (B*H*W,) */
    Lights lights;
    float *out;                 /* (B*H*W, 3) */
} BackgroundJob;

/* A sphere light the camera ray of pixel p hits before the object replaces its
 * environment value o. */
static inline void background_light(const BackgroundJob *j, int64_t b, int64_t p, float *o) {
    if (j->lights.nl == 0) return;
    int64_t l;
    float t = hit_light(&j->lights, b, j->eye + 3 * b, j->ray_dir + 3 * p, &l);
    if (isfinite(t) && (!j->front_mask[p] || t < j->front_dist[p]))
        for (int c = 0; c < 3; c++) o[c] = j->lights.light_le[(b * j->lights.nl + l) * 3 + c];
}

/* One pixel of background_range: view b, pixel p. */
static inline void background_pixel(const BackgroundJob *j, int64_t b, int64_t p) {
    const float *d = j->ray_dir + 3 * p;
    float *o = j->out + 3 * p;
    int obj = j->front_mask[p];
    if (j->lights.nl == 0 && obj) {
        o[0] = o[1] = o[2] = 0.0f;
        return;
    }
    env_lookup(&j->lights, b, d, o);
    background_light(j, b, p, o);
}

static void background_range(const void *job, int64_t begin, int64_t end) {
    const BackgroundJob *j = (const BackgroundJob *)job;
    int64_t b = begin / j->hw, next = (b + 1) * j->hw;  /* the view, without a division
                                                          * per pixel */
    int64_t p = begin;
#ifdef TR_HAVE_ENV8
    /* 8 pixels of one view at a time (env_lookup8; a view's last few pixels, and a map
     * too large for 32-bit offsets, one at a time) */
    while (p < end) {
        if (p == next) {
            b++;
            next += j->hw;
        }
        int64_t stop = next < end ? next : end;
        if (env_view8_fits(&j->lights, b)) {
            EnvView8 e = env_view8(&j->lights, b);
            for (; p + 8 <= stop; p += 8) {
                /* the lanes the object covers (left at zero without lights) */
                __m256i cover = _mm256_cmpgt_epi32(
                    _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)(j->front_mask + p))),
                    _mm256_setzero_si256());
                int all = _mm256_movemask_ps(_mm256_castsi256_ps(cover)) == 0xff;
                float *o = j->out + 3 * p;
                if (j->lights.nl == 0 && all) {
                    __m256 zero = _mm256_setzero_ps();
                    _mm256_storeu_ps(o, zero);
                    _mm256_storeu_ps(o + 8, zero);
                    _mm256_storeu_ps(o + 16, zero);
                    continue;
                }
                __m256 dx, dy, dz, c[3];
                tr_load_xyz8(j->ray_dir + 3 * p, &dx, &dy, &dz);
                env_lookup8(&e, dx, dy, dz, c);
                if (j->lights.nl == 0)
                    for (int k = 0; k < 3; k++)
                        c[k] = _mm256_andnot_ps(_mm256_castsi256_ps(cover), c[k]);
                tr_store_xyz8(o, c[0], c[1], c[2]);
                if (j->lights.nl > 0)
                    for (int k = 0; k < 8; k++) background_light(j, b, p + k, o + 3 * k);
            }
        }
        for (; p < stop; p++) background_pixel(j, b, p);
    }
#endif
    for (; p < end; p++) {
        if (p == next) {
            b++;
            next += j->hw;
        }
        background_pixel(j, b, p);
    }
}

int torchrefract_background(BackgroundJob *job, int threads) {
    return tr_parallel_for(background_range, job, job->b * job->hw, 4096, threads);
}

int64_t torchrefract_background_job_size(void) { return (int64_t)sizeof(BackgroundJob); }

/* A checked entry point for the tests (tests/test_native.py): lighting.h's i0e over n
 * doubles, as sg light coverage evaluates it, to hold it to torch.special.i0e. */
typedef struct {
    int64_t n;
    const double *x;
    double *out;
} I0eJob;

static void i0e_range(const void *job, int64_t begin, int64_t end) {
    const I0eJob *j = (const I0eJob *)job;
    i0e_n(j->x + begin, end - begin, j->out + begin);
}

int torchrefract_i0e(const I0eJob *job, int threads) {
    return tr_parallel_for(i0e_range, job, job->n, 4096, threads);
}

int64_t torchrefract_i0e_job_size(void) { return (int64_t)sizeof(I0eJob); }

/* lights.sg_light_coverage over N lobes (the tensor code's callers: ``sh``, the matte
 * passes' lookups): lighting.h's light_coverage with each lobe's own lights, (N, L). */
typedef struct {
    int64_t n, nl;              /* lobes, lights each */
    const float *o, *d, *k;     /* (N, 3) origins, (N, 3) unit axes, (N,) sharpness */
    const float *pos, *r;       /* (N, L, 3), (N, L): each lobe's lights */
    const double *gl_x, *gl_w;  /* the Gauss-Legendre rule (lights._GL_X, _GL_W) */
    int64_t gl_n;
    float *out;                 /* (N, L) */
} CoverJob;

static void cover_range(const void *job, int64_t begin, int64_t end) {
    const CoverJob *j = (const CoverJob *)job;
    Lights L;
    memset(&L, 0, sizeof(L));
    L.nl = j->nl;  /* lobe i as "view" i: its lights at (i L + l) */
    L.light_pos = j->pos;
    L.light_r = j->r;
    L.gl_x = j->gl_x;
    L.gl_w = j->gl_w;
    L.gl_n = j->gl_n;
    for (int64_t i = begin; i < end; i++)
        for (int64_t l = 0; l < j->nl; l++)
            j->out[i * j->nl + l] =
                (float)light_coverage(&L, i, l, j->o + 3 * i, j->d + 3 * i, j->k[i]);
}

int torchrefract_light_coverage(const CoverJob *job, int threads) {
    return tr_parallel_for(cover_range, job, job->n, 1024, threads);
}

int64_t torchrefract_light_coverage_job_size(void) { return (int64_t)sizeof(CoverJob); }

/* lights.incident_radiance_sg over N lobes (the tensor code's lookups where ``sh`` shades):
 * lighting.h's incident_sg, the fused kernels' own: the environment's SG pyramid around
 * each lobe, the sphere lights' share of it (sharpness inf: a plain lookup). */
typedef struct {
    Lights lights;
    SgEnv env;
    int64_t n;
    const int64_t *batch;       /* (N,) each lobe's view */
    const float *o, *d, *k;     /* (N, 3) origins, (N, 3) unit axes, (N,) sharpness */
    float *out;                 /* (N, 3) */
} IncidentJob;

static void incident_range(const void *job, int64_t begin, int64_t end) {
    const IncidentJob *j = (const IncidentJob *)job;
    for (int64_t i0 = begin; i0 < end; i0 += 8) { /* eight taps found in lanes, then read */
        const int n = end - i0 < 8 ? (int)(end - i0) : 8;
        SgTap taps[8];
        sg_env_tap8(&j->lights, &j->env, n, j->batch + i0, j->d + 3 * i0, j->k + i0, taps);
        for (int t = 0; t < n; t++) {
            const int64_t i = i0 + t;
            incident_sg_at(&j->lights, j->batch[i], j->o + 3 * i, j->d + 3 * i, j->k[i],
                           taps + t, j->out + 3 * i);
        }
    }
}

int torchrefract_incident_sg(const IncidentJob *job, int threads) {
    return tr_parallel_for(incident_range, job, job->n, 2048, threads);
}

int64_t torchrefract_incident_sg_job_size(void) { return (int64_t)sizeof(IncidentJob); }
