/* The jobs of method sh's eq. 2 kernels (sh_eval.c), shared with its fused shading
 * (sh_shade.c, another translation unit: the two include different helpers under the
 * same names). */

#ifndef TORCHREFRACT_SH_JOBS_H
#define TORCHREFRACT_SH_JOBS_H

#include <stdint.h>

typedef struct {
    int64_t n;              /* points */
    int64_t e;              /* directions per point (<= 5) */
    int64_t order;          /* highest band L (<= 8) */
    int64_t c;              /* channels written for direction 0 (<= 8) */
    int64_t c_rest;         /* channels written for directions 1.. (<= c) */
    const float *omega;     /* (n, e, 3) unit view directions, object space; with `spread`:
                             * (n, 1, 3), the other e - 1 = 4 made here */
    const int64_t *samples; /* (n, 3) surface samples, or NULL: from faces and bary */
    const float *s_w;       /* (n, 3) their weights (with samples) */
    const int64_t *faces;   /* (n,) mesh-local faces (without samples) */
    const float *bary;      /* (n, 3) barycentrics (without samples) */
    const int64_t *lattice; /* (F, P) layout.lattice (without samples) */
    int64_t rate;           /* layout.rate */
    const float *spread;    /* (n,) offset angle r of the 4 extra directions, or NULL */
    const float *frame;     /* (S, 3, 3) rows t, b, n */
    const void *coeffs;     /* (S, 45, 8) float16 (SH_HALF) or float32, channels zero-padded */
    const float *weights;   /* (K,) window */
    float *out;             /* (n, e, c); channels >= c_rest of directions 1.. set to 0 */
} ShEvalJob;

/* shade._map_pixels for the object pixels of the batch items sharing one table: per pixel
 * its front face and barycentrics from the G-buffer, the view in object space, eq. 2 at
 * the view (and, for an item with rough pixels, the four views around it), then the exit
 * direction back in world space, the length, exit cosine, throughput and the variance of
 * the exit directions (the geometric spread), written at the pixel's position. */
typedef struct {
    ShEvalJob eval;          /* the table and basis (n, e, omega, samples, faces, bary,
                              * spread and out unused) */
    int64_t n;               /* positions mapped */
    const int64_t *sel;      /* (n,) positions in the per-pixel arrays */
    const int64_t *pix;      /* (N,) flat G-buffer pixel of each position */
    const int64_t *item;     /* (N,) batch item of each position */
    const int32_t *tri;      /* (B H W,) front faces, ids over the batch's meshes */
    const float *gbary;      /* (B H W, 3) front barycentrics */
    const int64_t *face_offset; /* (B,) first face of each item's mesh */
    const float *view;       /* (N, 3) unit view directions (world, towards the viewer) */
    const float *var_view;   /* (N,) variance of the view directions the lobe spans */
    const float *alpha;      /* (N,) front roughness */
    const float *rotation;   /* (B, 3, 3) object -> world rotation R (omega = view R) */
    const float *scale;      /* (B,) the items' uniform scale */
    const uint8_t *rough;    /* (B,) 1: the four offset views are read (the item's choice) */
    float radius;            /* the table's length unit */
    float max_spread;        /* largest offset angle */
    float *direction;        /* (N, 3) outputs, at the positions sel */
    float *length, *cos_exit, *throughput, *var_geo; /* (N,) */
} ShMapJob;

/* What every point of a call shares (the basis's constants and the window: sh_eval.c's
 * ShShared, 32-byte aligned), its size and its making for ``job``'s order and window. */
int64_t torchrefract_sh_shared_size(void);
void torchrefract_sh_shared_init(const ShMapJob *job, void *shared);

/* shade._map_pixels for the positions [begin, end) of ``job`` (sh_eval.c), one thread,
 * with ``shared`` made for it. */
void torchrefract_sh_map_range(const ShMapJob *job, const void *shared, int64_t begin,
                               int64_t end);

#endif
