/* Entry points of the fused shading of ``rousiers`` (its steps: rousiers_core.h). */

#include "rousiers_core.h"

/* Entry point (ctypes, shading/fused.py): shade all object pixels of ``job`` on
 * ``threads`` threads (frame.h's run_shading). */
int torchrefract_rousiers(RousJob *job, int threads) {
    if (job->levels > MAX_LEVELS) return -1;
    return run_shading(job, &job->f, NAXES, rous_axes, shade_block, threads);
}

int64_t torchrefract_rousiers_job_size(void) { return (int64_t)sizeof(RousJob); }

/* The SG table's lobes for N points of the tensor code's callers (``sh``): each point's
 * own table axes at its (eta, alpha) and (eta, alpha_min) (sg_axes), then the fused
 * kernels' own steps. ``lobes.front_lobes`` (front 1: step 1, eqs. 8-9: the reflected
 * and transmitted lobes at cos) or, front 0, an exit's: the transmitted lobe's sharpness
 * and, with ``e_t``, ``lobes.spread_energies`` over a lobe of variance var. */
typedef struct {
    SgTable table;
    int64_t n;
    int front;
    const float *view, *n1;         /* (N, 3): front only */
    const float *cos, *eta, *alpha, *var;  /* (N,); var: exit only */
    const int64_t *dist;            /* (N,) */
    float *e_r, *k_r, *axis_r;      /* out (N,), (N,), (N, 3): front only */
    float *e_t, *k_t, *p_t;         /* out (N,), (N,), (N, 3) (p_t: front only; e_t,
                                     * with e_r, exit: NULL where not wanted) */
} LobesJob;

#define SLICE_RUN 64 /* points at one axes from which their slices are made */

/* Whether points i and k share their table axes (eta, alpha, distribution). */
static inline int same_axes(const LobesJob *j, int64_t i, int64_t k) {
    return j->eta[i] == j->eta[k] && j->alpha[i] == j->alpha[k] && j->dist[i] == j->dist[k];
}

static void lobes_range(const void *job, int64_t begin, int64_t end) {
    const LobesJob *j = (const LobesJob *)job;
    const SgTable *t = &j->table;
    /* A run of points at one (eta, alpha) (a view without a roughness map) reads the
     * axes' slices (sg_slices: the same values, two loads a channel instead of eight) */
    const size_t per = (size_t)(SG_SLICES * t->nt);
    float *buf = (float *)malloc(sizeof(float) * 2 * per);
    SgAxes ax, ax0;
    for (int64_t i = begin; i < end; i++) {
        if (i == begin || !same_axes(j, i, i - 1)) {
            sg_axes(t, j->eta[i], j->alpha[i], &ax);
            sg_axes(t, j->eta[i], t->alpha_min, &ax0);
            int run = buf != NULL && i + SLICE_RUN < end;
            for (int64_t k = i + 1; run && k <= i + SLICE_RUN; k++) run = same_axes(j, i, k);
            if (run) {
                sg_slices(t, j->dist[i], &ax, buf);
                sg_slices(t, j->dist[i], &ax0, buf + per);
            }
        }
        int64_t d = j->dist[i];
        float z = sg_theta(j->cos[i]), angle, e;
        if (j->front) {
            const float *v = j->view + 3 * i, *n = j->n1 + 3 * i;
            sg_lobe_at(t, &ax, &ax0, d, 1, z, j->k_r + i, &angle, j->e_r + i);
            lobe_axis(v, n, angle, 1.0f, j->axis_r + 3 * i);
            sg_lobe_at(t, &ax, &ax0, d, 0, z, j->k_t + i, &angle, j->e_t + i);
            lobe_axis(v, n, angle, -1.0f, j->p_t + 3 * i);
            normalize3(j->p_t + 3 * i);
            continue;
        }
        sg_lobe_at(t, &ax, &ax0, d, 0, z, j->k_t + i, &angle, &e);
        if (j->e_t)
            spread_table_energies(t, &ax, &ax0, d, j->cos[i], j->var[i], j->e_t + i,
                                  j->e_r + i);
    }
    free(buf);
}

int torchrefract_lobes(const LobesJob *job, int threads) {
    return tr_parallel_for(lobes_range, job, job->n, 2048, threads);
}

int64_t torchrefract_lobes_job_size(void) { return (int64_t)sizeof(LobesJob); }
