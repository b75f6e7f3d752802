/* The per-frame kernel of optitac-edge: camera frame -> fiber means -> signal -> surface -> contacts.
 *
 * Plain C99, no Python: the CPython module (module.c) wraps it for the service, and
 * tools/kernel_aarch64.sh compiles it on its own for aarch64 with a small C harness.
 *
 * It does exactly what the numpy pipeline (optitac_edge/core/pipeline.py and the parts it names)
 * does, step for step, in float32 where that does and float64 where that does, so the results
 * agree: the fiber means, the signal and the selection of the surface's triangles bit for bit; the
 * surface's gradients and the moments to rounding (the sums are taken in another order).
 *
 * Memory: the plan's arrays belong to the caller (numpy arrays the module keeps alive); the
 * kernel's scratch is allocated once by ok_kernel_init and freed by ok_kernel_free. A frame
 * allocates nothing.
 */
#ifndef OPTITAC_FRAME_KERNEL_H
#define OPTITAC_FRAME_KERNEL_H

#include <stdint.h>

#define OK_MAX_CANDIDATES 8 /* contact_finder.MAX_CANDIDATES */
#define OK_GS_PAD 8
/* The sort goes by bytes (4 passes at most, linear) from this many values; below, a quicksort is fewer steps. */
#define OK_RADIX_MIN 256
#define OK_SORT_SCRATCH(n) (2 * (size_t)(n) + 4 * 256)
#define OK_CELL_TERMS 9     /* surface.CELL_TERMS */

/* One contact's measures, in this order, in ok_kernel.contacts[k * OK_FIELDS + ...] (float64). */
enum {
    OK_STRENGTH, OK_X_MM, OK_Y_MM, OK_MAJOR_MM, OK_MINOR_MM, OK_ANGLE_DEG, OK_AREA_MM2, OK_PEAK,
    OK_HU0, /* .. OK_HU0 + 6: the log-Hu invariants */
    OK_Q4 = OK_HU0 + 7,
    OK_DEPTH_MM, OK_FORCE_N, /* NaN without a depth (force) model */
    OK_SHAPE,                /* the class's index in the shape model, -1: none */
    OK_CONFIDENCE,
    OK_FIELDS
};

/* The calibration models (ContactCorrector), each optional (NULL knots / n = 0: absent). */
typedef struct {
    const double *km, *kt; /* AxisMap knots, increasing measured */
    int32_t k;             /* number of knots, >= 2 */
} ok_axis;

typedef struct {
    int32_t feature;       /* depth_model.DEPTH_FEATURES index */
    int32_t power;         /* the radial term's power of rho^2, 1..4 */
    double radial, radius_mm;
    ok_axis curve;
} ok_radial_map;

typedef struct {
    /* centroid error map */
    int32_t cmap_n;
    double cmap_x0, cmap_y0, cmap_step;
    const float *cmap_ex, *cmap_ey; /* (n, n) */
    /* width model */
    int32_t width;
    ok_axis major, minor;
    double radial_major, radial_minor, width_radius_mm;
    /* depth and force */
    int32_t depth, force;
    ok_radial_map depth_map, force_map;
    /* shape classifier (ShapeClassifier.classify) */
    int32_t shape_d, shape_k, shape_c; /* features used, components, classes */
    const int32_t *shape_sel, *shape_rule; /* (d,): input index; 1 signed, 2 zero is null, 4 q4 */
    const double *shape_mean, *shape_std;  /* (d,) */
    double shape_cap, shape_q4_floor, shape_q4_max;
    const double *shape_proj1;  /* (d + 1, K * d) */
    const double *shape_const;  /* (K,) */
    const double *shape_map1;   /* (K, C + 1) */
} ok_models;


/* Everything fixed for a bundle and its options. Arrays are borrowed. */
typedef struct {
    /* step 2: the fiber table */
    int32_t n_fibers;          /* N */
    int32_t rgb;               /* 1: (H, W, 3) frames; 0: gray or yuv420 (the luminance plane first) */
    const int32_t *rgb_weights; /* (3,) Q15 weights of the colour mix, summing to 32768 (NULL: BT.601) */
    const int32_t *pixel_index; /* (P,) flat pixel indices grouped by fiber */
    const int64_t *pixel_start; /* (N + 1,) */
    const float *inv_count;     /* (N,) float32(1 / pixels of the fiber) */
    int64_t frame_pixels;       /* H * W (indices are checked against it at init) */
    /* step 4 */
    const int32_t *dead;        /* (n_dead,) */
    int32_t n_dead;
    const int32_t *live;        /* (n_live,): the fibers the LED gain is measured on */
    int32_t n_live;
    int32_t relative, compensate_gain, track_baseline, bright_from_common;
    float black_level;
    double gain_rate_per_ns, tau_ns, holdoff_ns, bright_hold_ns;
    /* step 5: the factored surface (tri_cols != NULL) or the dense matrix */
    int32_t n_value_rows;
    const int32_t *value_rows;  /* (n_value_rows,) */
    const float *value_op;      /* (n_value_rows, N) */
    const float *grad_op;       /* (2N, N) */
    int32_t n_tri, width, n_value_terms;
    const int32_t *tri_cols;    /* (T, 9) */
    const int32_t *tri_cells;   /* (T, width): padded with the first cell */
    const int32_t *tri_count;   /* (T,): the cells of each triangle before the padding */
    const float *tri_weights;   /* (T, 9, width) */
    const float *value_w;       /* (T,) */
    const float *grad_w;        /* (9 - n_value_terms, T) */
    const float *dense;         /* (n*n, N), when there are no factors */
    /* the frame check (FrameCheck), when check_probe != NULL */
    const int32_t *check_probe; /* (check_pixels * check_bytes,) byte offsets into the frame */
    int32_t check_pixels, check_bytes;
    double check_dark_level, check_dark_fraction, check_saturated_level, check_saturated_fraction;
    /* the gradients as a sparse solve instead of grad_op's product (gs_fibers != NULL; see
     * optitac_edge/core/gradient_solve.py): m = 2N unknowns, K = C C^T, C lower triangular in an envelope */
    const int32_t *gs_fibers;   /* (N,) the fiber whose d/dx, d/dy are unknowns 2 r, 2 r + 1 of the factor */
    /* rows and columns are padded with zeros to multiples of OK_GS_PAD entries, reaching up to OK_GS_PAD
     * positions before 0 and after m - 1 */
    const float *gs_diag;       /* (m,) C[p, p] */
    const int32_t *gs_col_last; /* (m,) one past the last row of column p */
    const int64_t *gs_col_ptr;  /* (m + 1,) gs_col_env[col_ptr[p]:col_ptr[p + 1]] = C[p + 1:col_last[p], p] */
    const float *gs_col_env;
    const int32_t *gs_nbr_ptr;  /* (N + 1,) */
    const int32_t *gs_nbr;      /* (E,) each fiber's neighbours */
    const float *gs_coef;       /* (E, 2) 6 e / L^3 */
    /* steps 6, 7: the mesh, levels and fractions */
    int32_t n;                  /* mesh side */
    double x0_mm, y0_mm, step_mm, cell_area_mm2;
    double min_area_mm2, min_cells;
    double peak_fraction, shape_fraction, split_fraction;
    int32_t max_contacts;
    /* buffers shared with the numpy pipeline (writable) */
    float *means;               /* (N,) */
    float *signal;              /* (N,) */
    float *surface;             /* (n*n,) */
    float *baseline;            /* (N,) Baseline.values */
    float *level;               /* (N,) Baseline.level */
    float *inv_level;           /* (N,) Baseline.inv_level */
    const float *band;          /* (2, N) ContactLevels.bands: c^2, shift per fiber (NULL: none) */
    const int32_t *support_nbr; /* (N, 6) each fiber's neighbours, -1 for none (NULL: no neighbour support) */
    float *rest;                /* (N,) the rest light of the last frame, for a raise (see ok_follow) */
    double *contacts;           /* (max_contacts, OK_FIELDS) the frame's contacts, strongest first */
    ok_models models;           /* applied to each contact when ok_kernel.correct is set */
} ok_plan;

typedef struct {
    ok_plan p;
    /* levels (float32, as ContactLevels) and the gain's (GainCompensation.set_levels) */
    float trunc, off, on;
    double gain_keep, gain_widen, gain_tolerance, gain_significant;
    /* the LED gain's state */
    double gain, frame_gain, reference;
    int64_t reference_ns;
    int32_t held, light_changed;
    int64_t light_changes;
    /* BrightFibers */
    int32_t bright_since_set;
    int64_t bright_since_ns;
    double common;
    /* the last frame */
    int32_t saturated; /* ok_check: a probed pixel at full scale */
    int32_t cells, evaluated;
    int32_t box_x, box_y, box_w, box_h;
    double clear_strength, clear_area;
    int32_t n_candidates;
    int32_t correct;   /* apply plan.models to the contacts */
    double *shape_y, *shape_ll; /* (K * d,), (K,) */
    /* contact state (Pipeline._in_contact, _contact_end_ns) and a raise found by the last ok_follow */
    int32_t in_contact, contact_ended, raise_pending;
    int64_t contact_end_ns;
    /* the fiber pixels as runs of consecutive bytes (of pixels for rgb) */
    int32_t *run_start; /* (runs,) first pixel */
    int32_t *run_len;   /* (runs,) */
    /* gray: the runs as masked 8-byte reads (NULL for rgb and frames under 8 bytes) */
    int32_t *chunk_offset; /* (chunks,) */
    uint64_t *chunk_mask;  /* (chunks,) */
    int32_t *fiber_chunk;  /* (N + 1,) each fiber's chunks, padded to an even number */
    int32_t chunks_fit;    /* every fiber has at most 128 chunks (no 16-bit lane can overflow) */
    /* rgb: the runs as 16-byte reads of up to four pixels (chunk_offset: the first pixel's byte), each
     * chunk's pixels (1..4; -1..-4: so near the frame's end that they are read one by one) */
    int8_t *chunk_pixels;  /* (chunks,) */
    int32_t *fiber_run; /* (N + 1,) fiber f owns runs fiber_run[f] .. fiber_run[f + 1] - 1 */
    /* scratch */
    float *w;          /* (3N,) */
    float *absw;       /* (3N,) |w| */
    float *gs_y;       /* (2N,) the gradient solve's unknowns in the factor's order */
    float *ratio;      /* (N,) */
    float support_peak;        /* NeighbourSupport.peak of the last frame's signal */
    float *sorted;     /* (max(N, 1),) */
    uint32_t *sort_scratch; /* OK_SORT_SCRATCH(N) */
    float *bound;      /* (T,) */
    int32_t *selected; /* (2T,) triangles evaluated by the last frame; the frame before's */
    uint32_t *tri_stamp; /* (T,) the frame each triangle was last evaluated in */
    uint32_t stamp;
    float *grad_w_t;   /* (T, 9) the gradient weights triangle by triangle */
    int32_t n_selected;
    int32_t *rect;     /* (n*n + 1, 4): x0, y0, x1, y1 of each label */
    float *blob;       /* (n*n,) */
    int32_t *cell_rc;  /* (n*n,) row << 16 | column of each mesh cell (the dense surface's box) */
    int32_t *tri_box;  /* (T, 4) x0, y0, x1, y1 of each triangle's cells */
    float peak;        /* the largest value above the truncation level */
    /* runs of the box's cells above the level (mask) and above the split level (seeds): row, first and
     * last column, and the run's label */
    int32_t *run_y, *run_x0, *run_x1, *run_label; /* (n*n / 2 + 1,) each */
    int32_t *seed_y, *seed_x0, *seed_x1, *seed_label;
    int32_t n_runs, n_seed_runs;
    /* the split of joined presses: the seeds' runs, then the mask's runs cut by nearest seed; the seeds'
     * labels and each cell's nearest seed (box-sized), and the chamfer distances (box + a border of 2) */
    int32_t *part_y, *part_x0, *part_x1, *part_label; /* (n*n + 1,) each */
    int32_t *seed_img, *nearest; /* (n*n,) */
    int32_t *dist;               /* (2 (n + 4) (n + 6),) distances and labels, and two rows */
    int32_t *parent;   /* (n*n + 1,) union-find */
    int32_t *counts;   /* (n*n + 1,) */
    int32_t *seed_counts; /* (n*n + 1,) */
    int32_t *order;    /* (n*n + 1,) */
    double *powers;    /* (5, n): powers[q * n + c] = c ** q */
    double cand[OK_MAX_CANDIDATES * OK_FIELDS];
} ok_kernel;

/* 0, or -1 with a message in err (plan out of range). Allocates the scratch. */
int ok_kernel_init(ok_kernel *k, const ok_plan *plan, char *err, int err_len);
void ok_kernel_free(ok_kernel *k);

/* The levels (ContactLevels) and the gain's band (GainCompensation.set_levels). */
void ok_set_levels(ok_kernel *k, float trunc, float off, float on, double gain_delta, double gain_tolerance,
                   double gain_significant);
/* GainCompensation.reset */
void ok_reset_gain(ok_kernel *k, int64_t now_ns);
/* BrightFibers.reset */
void ok_reset_bright(ok_kernel *k);

/* Step 2: the fiber means of a frame (plan.means). frame: the whole frame, C-contiguous. */
void ok_means(ok_kernel *k, const uint8_t *frame);
/* Steps 4-6 after ok_means: signal, surface, truncation; the cells above the truncation level. */
int32_t ok_surface(ok_kernel *k, int64_t now_ns);
/* FrameCheck after ok_means (the probed pixels are then in the caches): 0 to process the frame, 1 dark,
 * 2 saturated (optitac_edge/core/frame_check.py); k->saturated: a probed pixel at full scale. Changes
 * nothing else. Needs the plan's check arrays. */
int32_t ok_check(ok_kernel *k, const uint8_t *frame);
/* One frame after the baseline is ready: ok_means (unless means_ready: ok_means ran on this frame),
 * ok_surface, ok_find at the on level (the off level while in contact), ok_follow. Returns the number
 * of contacts. */
int32_t ok_frame(ok_kernel *k, const uint8_t *frame, int64_t now_ns, int64_t dt_ns, int means_ready);
/* Pipeline.reset_baseline's part: no contact, none ended, no raise pending, nothing bright. */
void ok_reset_contact(ok_kernel *k);
/* Step 7 after ok_surface found cells: the contacts (plan.contacts, strongest first), their number
 * (at most max_contacts; 0: clear_strength and clear_area say what was above the truncation level).
 * level: the on level, or the off level while in contact. */
int32_t ok_find(ok_kernel *k, float level);
/* Steps 9, 10 after a frame with n contacts: k->raise_pending when fibers are to be raised (plan.rest
 * holds the rest light and k->common the level brightness was measured from; the caller raises them
 * and calls ok_set_levels), else the LED gain and the baseline followed the light. */
void ok_follow(ok_kernel *k, int32_t n, int64_t now_ns, int64_t dt_ns);

/* Every cell of an h x w box to its nearest seed component, as cv2.distanceTransformWithLabels(non-seed
 * cells, DIST_L2, 3, labelType=DIST_LABEL_CCOMP) labels them: seed_label holds the seeds' component labels
 * (0 elsewhere); nearest receives each cell's; dist is scratch of 2 (h + 4) (w + 4) + 2 (w + 4). */
void ok_nearest_seed(const int32_t *seed_label, int32_t h, int32_t w, int32_t *dist, int32_t *nearest);

/* ContactCorrector.apply on one contact's fields (OK_FIELDS values), in place. */
void ok_correct(const ok_kernel *k, double *c);

/* Helpers the tests reach through the module. */
/* Sorts a ascending (finite values): by the floats' bytes when scratch (OK_SORT_SCRATCH(n) words) is
 * given and n >= OK_RADIX_MIN, else a quicksort. */
void ok_sort_floats(float *a, int32_t n, uint32_t *scratch);
/* 8-connected components of runs (row y[i], columns x0[i] .. x1[i], in raster order) into label[i]
 * (1 .. in raster order of each component's first run); the number of labels including the background
 * (as cv2.connectedComponents). parent and map need n + 1 entries. */
int32_t ok_label_runs(const int32_t *y, const int32_t *x0, const int32_t *x1, int32_t n, int32_t *label,
                      int32_t *parent, int32_t *map);
void ok_hu_q4(const float *img, int32_t h, int32_t w, int32_t stride, float level, const double *xp, int32_t n,
              double *hu_q4);

#endif
