/* The cone's four bounding rays after their march (methods/rousiers.py, sec. 4.3 of de
 * Rousiers et al. 2012), one pixel at a time: the screen footprint of their exits
 * (rousiers._footprint) and the angular spread they give the exit lobe
 * (rousiers._ray_spread).
 *
 * The same float32 operations in the same order as the tensor code (built with
 * -ffp-contract=off and no fast-math): camera.project, torch.where, max/min over the four
 * rays (NaN where any is), optics.face_forward, optics.refract and optics.normalize
 * (Tensor.norm's fused multiply-adds, common.h), optics.dot, a sum over the four rays in
 * order. The square roots of the refractions are left to torch between two passes
 * (native.spread): torch's vectorized sqrt is not correctly rounded on every CPU
 * (measured: AVX-512 with MKL, 4% of the values 1 ulp off the C library's), and this way
 * the images are the same bit for bit (tests/test_native.py). In tensor code
 * these are ~40 elementwise ops over (N, 4, 3) arrays, bound by memory traffic; here each
 * pixel's values stay in registers. Plain C (threads: common.h); built and loaded by native.py.
 */

#include "optics.h"
#include "sgtable.h"

typedef struct {
    int64_t n;
    const float *q;      /* (N, 4, 3) exits of the bounding rays */
    const uint8_t *ok;   /* (N, 4) exit found */
    const float *pc;     /* (N, 3) exit of the central ray */
    const float *proj;   /* (B, 16) camera.projection_params per view */
    const int64_t *batch; /* (N,) view of each pixel */
    float *xy;           /* out (N, 4, 2) the exits' pixel coordinates (the central one's
                          * where a ray found none) */
    float *xy_c;         /* out (N, 2) the central exit's */
    float *ext;          /* out (N, 2) the four's bounding box extent, x and y */
} FootprintJob;

typedef struct {
    int64_t n;
    const float *p;       /* (N, 3) the front lobe's axis (the central ray) */
    const float *n_c;     /* (N, 3) its exit normal */
    const float *dirs;    /* (N, 4, 3) the bounding rays */
    const float *n4;      /* (N, 4, 3) their exit normals */
    const uint8_t *ok;    /* (N, 4) exit found */
    const float *ior;     /* (N,) */
    const float *fallback; /* (N,) the variance where no bounding ray found its exit */
    float two_ln4;        /* 2 ln 4 as float32 (the tensor code divides by it) */
    int stage;            /* 0: write root_arg; 1: read root, write var */
    float *root_arg;      /* out of stage 0 (N, 5): 1 - sin^2 of each refracted ray */
    const float *root;    /* in of stage 1 (N, 5): their square roots, cos_t */
    float *var;           /* out (N,) */
} SpreadJob;

static void footprint_range(const void *job, int64_t begin, int64_t end) {
    const FootprintJob *j = (const FootprintJob *)job;
    for (int64_t i = begin; i < end; i++) {
        const float *pp = j->proj + 16 * j->batch[i];
        float c[2], xy[4][2];
        project1(j->pc + 3 * i, pp, c);
        for (int k = 0; k < 4; k++) {
            if (j->ok[4 * i + k]) project1(j->q + 12 * i + 3 * k, pp, xy[k]);
            else { xy[k][0] = c[0]; xy[k][1] = c[1]; }
        }
        for (int a = 0; a < 2; a++) {
            float mx = xy[0][a], mn = xy[0][a];
            for (int k = 1; k < 4; k++) {
                mx = tmax(mx, xy[k][a]);
                mn = tmin(mn, xy[k][a]);
            }
            j->ext[2 * i + a] = mx - mn;
            j->xy_c[2 * i + a] = c[a];
            for (int k = 0; k < 4; k++) j->xy[8 * i + 2 * k + a] = xy[k][a];
        }
    }
}

/* optics.refract(d, face_forward(-n, d), eta) up to its square root: the flipped normal
 * (n_out), cos_i, and the root's argument (returned). */
static inline float refract_arg(const float *d, const float *n_raw, float eta, float *n,
                                float *cos_i_out) {
    n[0] = -n_raw[0]; n[1] = -n_raw[1]; n[2] = -n_raw[2];
    if (dot3(n, d) > 0.0f) { n[0] = -n[0]; n[1] = -n[1]; n[2] = -n[2]; }
    float cos_i = -dot3(d, n);
    cos_i = cos_i < 0.0f ? 0.0f : (cos_i > 1.0f ? 1.0f : cos_i);
    float sin2_t = (eta * eta) * (1.0f - cos_i * cos_i);
    float r = 1.0f - sin2_t;
    *cos_i_out = cos_i;
    return r < 0.0f ? 0.0f : r;
}

/* The rest of optics.refract given cos_t, the root: the unit transmitted direction. */
static inline void refract_finish(const float *d, const float *n, float eta, float cos_i,
                                  float cos_t, float *out) {
    float b = eta * cos_i - cos_t;
    float t[3];
    for (int k = 0; k < 3; k++) t[k] = eta * d[k] + b * n[k];
    float len = norm3(t);
    if (len < 1e-20f) len = 1e-20f;
    for (int k = 0; k < 3; k++) out[k] = t[k] / len;
}

/* The five rays of pixel i: the central one (k = 0), then the four bounding ones. */
static inline void spread_ray(const SpreadJob *j, int64_t i, int k, const float **d,
                              const float **n) {
    *d = k == 0 ? j->p + 3 * i : j->dirs + 12 * i + 3 * (k - 1);
    *n = k == 0 ? j->n_c + 3 * i : j->n4 + 12 * i + 3 * (k - 1);
}

/* Stage 0: the five square roots' arguments (root_arg, N x 5). */
static void spread_args_range(const void *job, int64_t begin, int64_t end) {
    const SpreadJob *j = (const SpreadJob *)job;
    for (int64_t i = begin; i < end; i++)
        for (int k = 0; k < 5; k++) {
            const float *d, *nr;
            float n[3], cos_i;
            spread_ray(j, i, k, &d, &nr);
            j->root_arg[5 * i + k] = refract_arg(d, nr, j->ior[i], n, &cos_i);
        }
}

/* Stage 1, given the roots (torch.sqrt of stage 0's, as the tensor code takes them): the
 * refracted rays, their squared chords to the central one, the mean over those found. */
static void spread_range(const void *job, int64_t begin, int64_t end) {
    const SpreadJob *j = (const SpreadJob *)job;
    for (int64_t i = begin; i < end; i++) {
        float eta = j->ior[i], t[5][3];
        for (int k = 0; k < 5; k++) {
            const float *d, *nr;
            float n[3], cos_i;
            spread_ray(j, i, k, &d, &nr);
            refract_arg(d, nr, eta, n, &cos_i);
            refract_finish(d, n, eta, cos_i, j->root[5 * i + k], t[k]);
        }
        float sum = 0.0f;
        int cnt = 0;
        for (int k = 0; k < 4; k++) {
            float dk[3];
            for (int m = 0; m < 3; m++) dk[m] = t[k + 1][m] - t[0][m];
            float chord2 = dot3(dk, dk);
            int ok = j->ok[4 * i + k] != 0;
            sum = k == 0 ? (ok ? chord2 : 0.0f) : sum + (ok ? chord2 : 0.0f);
            cnt += ok;
        }
        j->var[i] = cnt > 0 ? (sum / (float)cnt) / j->two_ln4 : j->fallback[i];
    }
}

/* optics.h's refract_x4 against four scalar refract calls, for tests/test_native.py: the
 * lanes must give the scalar code's bits (groups of four rays, each group its own eta). */
typedef struct {
    int64_t n;                  /* groups */
    const float *d, *nrm;       /* (n, 4, 3) */
    const float *eta;           /* (n,) */
    float *lanes, *scalar;      /* out (n, 4, 3) */
} RefractX4Job;

static void refract_x4_range(const void *job, int64_t begin, int64_t end) {
    const RefractX4Job *j = (const RefractX4Job *)job;
    for (int64_t g = begin; g < end; g++) {
        const float (*d)[3] = (const float (*)[3])(j->d + 12 * g);
        const float (*nr)[3] = (const float (*)[3])(j->nrm + 12 * g);
        refract_x4(d, nr, j->eta[g], (float (*)[3])(j->lanes + 12 * g));
        for (int q = 0; q < 4; q++) refract(d[q], nr[q], j->eta[g], j->scalar + 12 * g + 3 * q);
    }
}

/* sgtable.h's sg_theta_n and fresnel_n on a spread's three cosines (one partial group of
 * lanes where built for them) against sg_theta and fresnel, for tests/test_native.py: the
 * same bits. */
typedef struct {
    int64_t n;                  /* triples */
    const float *cs;            /* (n, 3) cosines */
    const float *eta;           /* (n,) */
    float *lanes, *scalar;      /* out (n, 2, 3): sg_theta, then fresnel */
} Theta3Job;

static void theta3_range(const void *job, int64_t begin, int64_t end) {
    const Theta3Job *j = (const Theta3Job *)job;
    for (int64_t g = begin; g < end; g++) {
        const float *cs = j->cs + 3 * g;
        float *lanes = j->lanes + 6 * g, *scalar = j->scalar + 6 * g;
        const float etas[3] = {j->eta[g], j->eta[g], j->eta[g]};
        sg_theta_n(cs, 3, lanes);
        fresnel_n(cs, etas, 3, lanes + 3);
        for (int i = 0; i < 3; i++) {
            scalar[i] = sg_theta(cs[i]);
            scalar[3 + i] = fresnel(cs[i], j->eta[g]);
        }
    }
}

int torchrefract_theta3(const Theta3Job *job, int threads) {
    return tr_parallel_for(theta3_range, job, job->n, 16384, threads);
}

int64_t torchrefract_theta3_job_size(void) { return (int64_t)sizeof(Theta3Job); }

/* Entry points (ctypes, native.py); 0, or -1 where a thread could not be started. */
int torchrefract_refract_x4(const RefractX4Job *job, int threads) {
    return tr_parallel_for(refract_x4_range, job, job->n, 16384, threads);
}

int torchrefract_footprint(const FootprintJob *job, int threads) {
    return tr_parallel_for(footprint_range, job, job->n, 16384, threads);
}

int torchrefract_spread(const SpreadJob *job, int threads) {
    return tr_parallel_for(job->stage == 0 ? spread_args_range : spread_range, job, job->n,
                           8192, threads);
}

int64_t torchrefract_footprint_job_size(void) { return (int64_t)sizeof(FootprintJob); }
int64_t torchrefract_spread_job_size(void) { return (int64_t)sizeof(SpreadJob); }
int64_t torchrefract_refract_x4_job_size(void) { return (int64_t)sizeof(RefractX4Job); }
