/* The march kernel's entry points (march_core.h holds the march itself). */

#include "march_core.h"

static void march_range(const void *job, int64_t begin, int64_t end) {
    const Job *j = (const Job *)job;
    float lo[BLOCK], hi[BLOCK];
    for (int64_t r = begin; r < end; r += BLOCK) {
        int m = end - r < BLOCK ? (int)(end - r) : BLOCK;
#ifdef HAVE_AVX2_PATH
        if (j->simd && m == BLOCK) search_block_avx2(j, r, lo, hi);
        else search_block(j, r, m, lo, hi);
#else
        search_block(j, r, m, lo, hi);
#endif
        for (int i = 0; i < m; i++) exit_ray(j, r + i, lo[i], hi[i]);
    }
}

/* Entry point (ctypes, native.py): march all rays of ``job`` on ``threads`` threads.
 * Returns 0, or -1 where a thread could not be started (then nothing is guaranteed).
 * The AVX2 search runs where ``job->simd`` asks for it (native.py: only where the plane
 * indices fit its 32-bit gathers) and the CPU has AVX2. */
int torchrefract_march(Job *job, int threads) {
#ifdef HAVE_AVX2_PATH
    job->simd = job->simd && __builtin_cpu_supports("avx2");
#endif
    return tr_parallel_for(march_range, job, job->n, 4096, threads);
}

/* The layout of Job, for native.py's check that its ctypes mirror matches. */
int64_t torchrefract_march_job_size(void) { return (int64_t)sizeof(Job); }
