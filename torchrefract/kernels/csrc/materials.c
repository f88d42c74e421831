/* materials.roughness_at over a batch of points (optics/materials.py): per point its
 * view's roughness at its UV (materials.h), the values of the tensor code's lookups. */

#include "materials.h"

typedef struct {
    int64_t n;
    const int64_t *batch;       /* (N,) each point's view */
    const float *uv;            /* (N, 2) */
    const float *alpha;         /* (B,) uniform roughness */
    const float *const *maps;   /* (B,) (H, W) map of each view, NULL where none */
    const int64_t *hw;          /* (B, 2) */
    const float *range;         /* (B, 2) */
    float *out;                 /* (N,) */
} RoughnessJob;

static void roughness_range(const void *job, int64_t begin, int64_t end) {
    const RoughnessJob *j = (const RoughnessJob *)job;
    for (int64_t i = begin; i < end; i++)
        j->out[i] = roughness_of(j->alpha, j->maps, j->hw, j->range, j->batch[i], j->uv + 2 * i);
}

/* Entry point (ctypes, native.py); 0, or -1 where a thread could not be started. */
int torchrefract_roughness(const RoughnessJob *job, int threads) {
    return tr_parallel_for(roughness_range, job, job->n, 16384, threads);
}

int64_t torchrefract_roughness_job_size(void) { return (int64_t)sizeof(RoughnessJob); }
