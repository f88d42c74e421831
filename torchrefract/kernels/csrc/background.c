/* What the camera sees without the object (shading/background.py), fused: per pixel the
 * environment, or a sphere light the camera ray hits before the object. Without lights the
 * object's pixels are left at zero (the method shades them); with lights every pixel is
 * looked up, and a light in front of the object shows. */

#include "lighting.h"

typedef struct {
    int64_t b, hw;              /* views, pixels per view */
    const float *ray_dir;       /* (B*H*W, 3) */
    const float *eye;           /* (B, 3) */
    const uint8_t *front_mask;  /* (B*H*W,) */
    const float *front_dist;    /* (B*H*W,) */
    Lights lights;
    float *out;                 /* (B*H*W, 3) */
} BackgroundJob;

static void background_range(const void *job, int64_t begin, int64_t end) {
    const BackgroundJob *j = (const BackgroundJob *)job;
    int64_t b = begin / j->hw, next = (b + 1) * j->hw;  /* the view, without a division
                                                          * per pixel */
    for (int64_t p = begin; p < end; p++) {
        if (p == next) {
            b++;
            next += j->hw;
        }
        const float *d = j->ray_dir + 3 * p;
        float *o = j->out + 3 * p;
        int obj = j->front_mask[p];
        if (j->lights.nl == 0 && obj) {
            o[0] = o[1] = o[2] = 0.0f;
            continue;
        }
        env_lookup(&j->lights, b, d, o);
        if (j->lights.nl > 0) {
            int64_t l;
            float t = hit_light(&j->lights, b, j->eye + 3 * b, d, &l);
            if (isfinite(t) && (!obj || t < j->front_dist[p]))
                for (int c = 0; c < 3; c++) o[c] = j->lights.light_le[(b * j->lights.nl + l) * 3 + c];
        }
    }
}

int torchrefract_background(BackgroundJob *job, int threads) {
    return tr_parallel_for(background_range, job, job->b * job->hw, 4096, threads);
}

int64_t torchrefract_background_job_size(void) { return (int64_t)sizeof(BackgroundJob); }
