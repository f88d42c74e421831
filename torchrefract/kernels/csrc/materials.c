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

/* cone.level_coverage: per back-layer pixel its roughness as hat weights on the n levels
 * spanning its view's range (linear between the two nearest), zero where the layer is
 * empty; the tensor code's float32 steps. */
typedef struct {
    RoughnessJob r;             /* views' materials; uv: the back layer's (B*H*W, 2) */
    int64_t hw;                 /* pixels a view */
    int64_t levels;             /* n */
    const uint8_t *mask;        /* (B*H*W,) the back layer */
    float *out;                 /* (B*H*W, n) */
} CoverageJob;

static void coverage_range(const void *job, int64_t begin, int64_t end) {
    const CoverageJob *j = (const CoverageJob *)job;
    const RoughnessJob *r = &j->r;
    int64_t n = j->levels;
    for (int64_t p = begin; p < end; p++) {
        float *o = j->out + p * n;
        if (!j->mask[p]) {
            for (int64_t k = 0; k < n; k++) o[k] = 0.0f;
            continue;
        }
        int64_t b = p / j->hw;
        float alpha = roughness_of(r->alpha, r->maps, r->hw, r->range, b, r->uv + 2 * p);
        float lo = r->range[2 * b], hi = r->range[2 * b + 1], span = hi - lo;
        span = span < 1e-12f ? 1e-12f : span;
        float pos = (alpha - lo) / span;
        pos = (pos < 0.0f ? 0.0f : (pos > 1.0f ? 1.0f : pos)) * (float)(n - 1);
        for (int64_t k = 0; k < n; k++) {
            float w = 1.0f - fabsf(pos - (float)k);
            o[k] = w < 0.0f ? 0.0f : w;
        }
    }
}

int torchrefract_level_coverage(const CoverageJob *job, int threads) {
    return tr_parallel_for(coverage_range, job, job->r.n, 16384, threads);
}

int64_t torchrefract_level_coverage_job_size(void) { return (int64_t)sizeof(CoverageJob); }
