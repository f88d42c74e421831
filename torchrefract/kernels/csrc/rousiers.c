/* Entry points of the fused shading of ``rousiers`` (its steps: rousiers_core.h). */

#include "rousiers_core.h"

/* Entry point (ctypes, shading/fused.py): shade all object pixels of ``job`` on
 * ``threads`` threads (frame.h's run_shading). */
int torchrefract_rousiers(RousJob *job, int threads) {
    if (job->levels > MAX_LEVELS) return -1;
    return run_shading(job, &job->f, NAXES, rous_axes, shade_block, threads);
}

int64_t torchrefract_rousiers_job_size(void) { return (int64_t)sizeof(RousJob); }
