/* The per-frame kernel: see frame_kernel.h. Each function names the numpy code it follows. */
#include "frame_kernel.h"
#include "gradient_solve.h"
#include "simd.h"

#include <float.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#if OK_AVX2
int ok_avx2; /* set by ok_kernel_init */
#endif

#define FWHM_PER_SIGMA 2.3548200450309493 /* 2 sqrt(2 ln 2), moments.FWHM_PER_SIGMA */
#define BOUND_MARGIN 1e-4                  /* TriangleSurface.BOUND_MARGIN */
#define COMMON_MODE_FRACTION 0.6           /* gain.COMMON_MODE_FRACTION */
#define OK_PI 3.141592653589793238462643383279502884197 /* as CPython's math.degrees */

/* ---------------------------------------------------------------- set-up */

static int init_rgb_chunks(ok_kernel *k);

static void *zalloc(size_t n, size_t size) { return calloc(n ? n : 1, size); }

/* The gray fiber pixels as 8-byte reads: each run of consecutive pixels in chunks of at most 8, each
 * read where 8 bytes lie within the frame (a chunk at the frame's end is read from 8 bytes before it)
 * and masked to its own bytes (the mask in memory order: any endianness). */
static int init_chunks(ok_kernel *k) {
    const ok_plan *p = &k->p;
    int32_t nf = p->n_fibers, n = 0;
    k->chunks_fit = 1;
    for (int32_t f = 0; f < nf; f++) { /* each fiber's chunks, padded to an even number (mask 0) */
        int32_t m = 0;
        for (int32_t r = k->fiber_run[f]; r < k->fiber_run[f + 1]; r++) m += (k->run_len[r] + 7) / 8;
        n += m + (m & 1);
        if (m > 128) k->chunks_fit = 0;
    }
    k->chunk_offset = zalloc((size_t)n, sizeof(int32_t));
    k->chunk_mask = zalloc((size_t)n, sizeof(uint64_t));
    k->fiber_chunk = zalloc((size_t)nf + 1, sizeof(int32_t));
    if (!k->chunk_offset || !k->chunk_mask || !k->fiber_chunk) return -1;
    int32_t c = 0;
    for (int32_t f = 0; f < nf; f++) {
        k->fiber_chunk[f] = c;
        for (int32_t r = k->fiber_run[f]; r < k->fiber_run[f + 1]; r++) {
            for (int32_t a = 0; a < k->run_len[r]; a += 8, c++) {
                int64_t first = (int64_t)k->run_start[r] + a;
                int32_t m = k->run_len[r] - a < 8 ? k->run_len[r] - a : 8;
                int64_t read = first + 8 <= p->frame_pixels ? first : p->frame_pixels - 8;
                uint8_t bytes[8] = {0};
                memset(bytes + (first - read), 0xFF, (size_t)m);
                k->chunk_offset[c] = (int32_t)read;
                memcpy(&k->chunk_mask[c], bytes, sizeof bytes);
            }
        }
        if ((c - k->fiber_chunk[f]) & 1) c++; /* the pad: offset 0, mask 0 (zeroed) */
    }
    k->fiber_chunk[nf] = c;
    return 0;
}

/* RGB: each run in chunks of up to four pixels, each read as 16 bytes from its first pixel (the pixels'
 * 12 bytes and 4 beyond); a chunk whose 16 bytes would pass the frame's end is read pixel by pixel. */
static int init_rgb_chunks(ok_kernel *k) {
    const ok_plan *p = &k->p;
    int32_t nf = p->n_fibers, n = 0;
    for (int32_t r = 0; r < k->fiber_run[nf]; r++) n += (k->run_len[r] + 3) / 4;
    k->chunk_offset = zalloc((size_t)n, sizeof(int32_t));
    k->chunk_pixels = zalloc((size_t)n, sizeof(int8_t));
    k->fiber_chunk = zalloc((size_t)nf + 1, sizeof(int32_t));
    if (!k->chunk_offset || !k->chunk_pixels || !k->fiber_chunk) return -1;
    int64_t bytes = 3 * p->frame_pixels;
    int32_t c = 0;
    for (int32_t f = 0; f < nf; f++) {
        k->fiber_chunk[f] = c;
        for (int32_t r = k->fiber_run[f]; r < k->fiber_run[f + 1]; r++) {
            for (int32_t a = 0; a < k->run_len[r]; a += 4, c++) {
                int64_t first = 3 * ((int64_t)k->run_start[r] + a);
                int32_t m = k->run_len[r] - a < 4 ? k->run_len[r] - a : 4;
                k->chunk_offset[c] = (int32_t)first;
                k->chunk_pixels[c] = (int8_t)(first + 16 <= bytes ? m : -m);
            }
        }
    }
    k->fiber_chunk[nf] = c;
    return 0;
}

int ok_kernel_init(ok_kernel *k, const ok_plan *plan, char *err, int err_len) {
    memset(k, 0, sizeof *k);
#if OK_AVX2
    __builtin_cpu_init();
    ok_avx2 = __builtin_cpu_supports("avx2");
#endif
    k->p = *plan;
    const ok_plan *p = &k->p;
    int32_t nf = p->n_fibers;
    if (nf < 1 || p->n < 2 || !p->pixel_index || !p->pixel_start || !p->means || !p->signal || !p->surface) {
        snprintf(err, err_len, "kernel plan: missing arrays or sizes");
        return -1;
    }
    for (int32_t i = 0; i < nf; i++) {
        if (p->pixel_start[i + 1] <= p->pixel_start[i]) {
            snprintf(err, err_len, "kernel plan: fiber %d owns no pixel", i);
            return -1;
        }
    }
    for (int64_t j = 0; j < p->pixel_start[nf]; j++) {
        if (p->pixel_index[j] < 0 || p->pixel_index[j] >= p->frame_pixels) {
            snprintf(err, err_len, "kernel plan: pixel index %d outside the frame", p->pixel_index[j]);
            return -1;
        }
    }
    for (int32_t i = 0; i < p->n_dead; i++)
        if (p->dead[i] < 0 || p->dead[i] >= nf) { snprintf(err, err_len, "kernel plan: dead fiber out of range"); return -1; }
    for (int32_t i = 0; i < p->n_live; i++)
        if (p->live[i] < 0 || p->live[i] >= nf) { snprintf(err, err_len, "kernel plan: live fiber out of range"); return -1; }
    for (int32_t i = 0; i < p->n_value_rows; i++)
        if (p->value_rows[i] < 0 || p->value_rows[i] >= nf) { snprintf(err, err_len, "kernel plan: value row out of range"); return -1; }
    int64_t cells = (int64_t)p->n * p->n;
    if (p->tri_cols) {
        for (int64_t i = 0; i < (int64_t)p->n_tri * OK_CELL_TERMS; i++)
            if (p->tri_cols[i] < 0 || p->tri_cols[i] >= 3 * nf) { snprintf(err, err_len, "kernel plan: triangle column out of range"); return -1; }
        for (int64_t i = 0; i < (int64_t)p->n_tri * p->width; i++)
            if (p->tri_cells[i] < 0 || p->tri_cells[i] >= cells) { snprintf(err, err_len, "kernel plan: triangle cell out of range"); return -1; }
        for (int32_t t = 0; t < p->n_tri; t++)
            if (p->tri_count[t] < 1 || p->tri_count[t] > p->width) { snprintf(err, err_len, "kernel plan: triangle cell count out of range"); return -1; }
        if (p->n_value_terms != 0 && p->n_value_terms != 3) { snprintf(err, err_len, "kernel plan: value terms must be 0 or 3"); return -1; }
    } else if (!p->dense) {
        snprintf(err, err_len, "kernel plan: neither surface factors nor a dense matrix");
        return -1;
    }
    if (p->gs_fibers && ok_check_gradient_solve(p, err, err_len) < 0) return -1;
    if (p->check_probe) {
        if (p->check_bytes != 1 && p->check_bytes != 3) { snprintf(err, err_len, "kernel plan: check_bytes must be 1 or 3"); return -1; }
        for (int64_t i = 0; i < (int64_t)p->check_pixels * p->check_bytes; i++)
            if (p->check_probe[i] < 0 || p->check_probe[i] >= p->frame_pixels * (p->rgb ? 3 : 1)) {
                snprintf(err, err_len, "kernel plan: check probe outside the frame");
                return -1;
            }
    }
    const ok_models *mo = &p->models;
    if ((mo->width && (mo->major.k < 2 || mo->minor.k < 2)) || (mo->depth && mo->depth_map.curve.k < 2)
        || (mo->force && mo->force_map.curve.k < 2)
        || (mo->shape_d && (mo->shape_k < 1 || mo->shape_c < 1 || mo->shape_d > 63 || mo->shape_c > 63))) {
        snprintf(err, err_len, "kernel plan: a calibration model without its arrays");
        return -1;
    }
    if (p->max_contacts < 1 || p->max_contacts > OK_MAX_CANDIDATES) { snprintf(err, err_len, "kernel plan: max_contacts out of range"); return -1; }
    size_t nn = (size_t)cells;
    k->w = zalloc(3 * (size_t)nf, sizeof(float));
    k->absw = zalloc(3 * (size_t)nf, sizeof(float));
    k->gs_y = zalloc(2 * (size_t)nf + 2 * OK_GS_PAD, sizeof(float));
    k->ratio = zalloc(nf, sizeof(float));
    k->sorted = zalloc(nf, sizeof(float));
    k->sort_scratch = zalloc(OK_SORT_SCRATCH(nf), sizeof(uint32_t));
    k->bound = zalloc(p->n_tri, sizeof(float));
    k->selected = zalloc(2 * (size_t)p->n_tri, sizeof(int32_t));
    k->tri_stamp = zalloc(p->n_tri, sizeof(uint32_t));
    k->blob = zalloc(nn, sizeof(float));
    /* a row of w cells holds at most (w + 1) / 2 runs (cells above the level and below it in turn):
     * h (w + 1) / 2 in all, more than nn / 2 for an odd side */
    size_t max_runs = (size_t)p->n * (((size_t)p->n + 1) / 2) + 2;
    k->cell_rc = zalloc(nn, sizeof(int32_t));
    k->tri_box = zalloc(4 * (size_t)p->n_tri, sizeof(int32_t));
    k->grad_w_t = zalloc(OK_CELL_TERMS * (size_t)p->n_tri, sizeof(float));
    k->run_y = zalloc(max_runs, sizeof(int32_t));
    k->run_x0 = zalloc(max_runs, sizeof(int32_t));
    k->run_x1 = zalloc(max_runs, sizeof(int32_t));
    k->run_label = zalloc(max_runs, sizeof(int32_t));
    k->seed_y = zalloc(max_runs, sizeof(int32_t));
    k->seed_x0 = zalloc(max_runs, sizeof(int32_t));
    k->seed_x1 = zalloc(max_runs, sizeof(int32_t));
    k->seed_label = zalloc(max_runs, sizeof(int32_t));
    k->part_y = zalloc(nn + 1, sizeof(int32_t));
    k->part_x0 = zalloc(nn + 1, sizeof(int32_t));
    k->part_x1 = zalloc(nn + 1, sizeof(int32_t));
    k->part_label = zalloc(nn + 1, sizeof(int32_t));
    k->seed_img = zalloc(nn, sizeof(int32_t));
    k->nearest = zalloc(nn, sizeof(int32_t));
    k->dist = zalloc(2 * ((size_t)p->n + 4) * ((size_t)p->n + 6), sizeof(int32_t));
    k->parent = zalloc(nn + 1, sizeof(int32_t));
    k->counts = zalloc(nn + 1, sizeof(int32_t));
    k->seed_counts = zalloc(nn + 1, sizeof(int32_t));
    k->order = zalloc(nn + 1, sizeof(int32_t));
    k->rect = zalloc(4 * (nn + 1), sizeof(int32_t));
    k->powers = zalloc(5 * (size_t)p->n + 8, sizeof(double));
    k->shape_y = zalloc((size_t)mo->shape_k * mo->shape_d, sizeof(double));
    k->shape_ll = zalloc((size_t)mo->shape_k + 1, sizeof(double));
    k->correct = 1;
    int64_t n_pixels = p->pixel_start[nf];
    k->run_start = zalloc((size_t)n_pixels, sizeof(int32_t));
    k->run_len = zalloc((size_t)n_pixels, sizeof(int32_t));
    k->fiber_run = zalloc((size_t)nf + 1, sizeof(int32_t));
    if (!k->shape_y || !k->shape_ll || !k->run_start || !k->run_len || !k->fiber_run || !k->absw || !k->gs_y || !k->w || !k->ratio || !k->sorted || !k->sort_scratch || !k->bound || !k->selected || !k->blob
        || !k->cell_rc || !k->tri_box || !k->tri_stamp || !k->grad_w_t || !k->run_y || !k->run_x0 || !k->run_x1 || !k->run_label
        || !k->seed_y || !k->seed_x0 || !k->seed_x1 || !k->seed_label || !k->part_y || !k->part_x0 || !k->part_x1 || !k->part_label || !k->seed_img
        || !k->nearest || !k->dist || !k->parent || !k->counts || !k->seed_counts
        || !k->order || !k->rect || !k->powers) {
        ok_kernel_free(k);
        snprintf(err, err_len, "kernel: out of memory");
        return -1;
    }
    int32_t runs = 0;
    for (int32_t f = 0; f < nf; f++) {
        k->fiber_run[f] = runs;
        for (int64_t j = p->pixel_start[f]; j < p->pixel_start[f + 1]; j++) {
            if (j > p->pixel_start[f] && p->pixel_index[j] == p->pixel_index[j - 1] + 1) {
                k->run_len[runs - 1]++;
            } else {
                k->run_start[runs] = p->pixel_index[j];
                k->run_len[runs++] = 1;
            }
        }
    }
    k->fiber_run[nf] = runs;
    if (!p->rgb ? p->frame_pixels >= 8 && init_chunks(k) < 0 : init_rgb_chunks(k) < 0) {
        ok_kernel_free(k);
        snprintf(err, err_len, "kernel: out of memory");
        return -1;
    }
    for (int32_t c = 0; c < p->n * p->n; c++) k->cell_rc[c] = (c / p->n) << 16 | (c % p->n);
    for (int32_t t = 0; p->tri_cols && t < p->n_tri; t++) /* the gradient weights triangle by triangle */
        for (int q = 0; q < OK_CELL_TERMS - p->n_value_terms; q++)
            k->grad_w_t[(int64_t)t * OK_CELL_TERMS + q] = p->grad_w[(int64_t)q * p->n_tri + t];
    for (int32_t t = 0; p->tri_cols && t < p->n_tri; t++) { /* each triangle's cells' box */
        int32_t *b = k->tri_box + 4 * (int64_t)t;
        b[0] = b[1] = p->n;
        b[2] = b[3] = -1;
        for (int32_t q = 0; q < p->tri_count[t]; q++) {
            int32_t cell = p->tri_cells[(int64_t)t * p->width + q], row = cell / p->n, col = cell % p->n;
            if (col < b[0]) b[0] = col;
            if (row < b[1]) b[1] = row;
            if (col > b[2]) b[2] = col;
            if (row > b[3]) b[3] = row;
        }
    }
    for (int32_t c = 0; c < p->n; c++) { /* powers[q * n + c] = c ** q */
        double v = 1.0;
        for (int q = 0; q < 5; q++, v *= c) k->powers[(int64_t)q * p->n + c] = v;
    }
    k->trunc = k->off = k->on = 1.0f;
    k->gain = k->frame_gain = k->reference = 1.0;
    return 0;
}

void ok_kernel_free(ok_kernel *k) {
    void **bufs[] = {(void **)&k->w, (void **)&k->absw, (void **)&k->gs_y, (void **)&k->ratio, (void **)&k->sorted, (void **)&k->sort_scratch, (void **)&k->bound,
                     (void **)&k->selected, (void **)&k->blob,
                     (void **)&k->cell_rc, (void **)&k->tri_box, (void **)&k->tri_stamp, (void **)&k->grad_w_t, (void **)&k->run_y, (void **)&k->run_x0, (void **)&k->run_x1,
                     (void **)&k->run_label, (void **)&k->seed_y, (void **)&k->seed_x0, (void **)&k->seed_x1,
                     (void **)&k->seed_label, (void **)&k->part_y, (void **)&k->part_x0, (void **)&k->part_x1,
                     (void **)&k->part_label, (void **)&k->seed_img, (void **)&k->nearest, (void **)&k->dist,
                     (void **)&k->parent, (void **)&k->counts, (void **)&k->seed_counts, (void **)&k->order,
                     (void **)&k->rect, (void **)&k->powers, (void **)&k->shape_y, (void **)&k->shape_ll, (void **)&k->run_start, (void **)&k->run_len, (void **)&k->chunk_offset, (void **)&k->chunk_mask,
                     (void **)&k->fiber_chunk, (void **)&k->chunk_pixels,
                     (void **)&k->fiber_run};
    for (size_t i = 0; i < sizeof bufs / sizeof bufs[0]; i++) {
        free(*bufs[i]);
        *bufs[i] = NULL;
    }
}

void ok_set_levels(ok_kernel *k, float trunc, float off, float on, double gain_delta, double gain_tolerance,
                   double gain_significant) {
    k->trunc = trunc;
    k->off = off;
    k->on = on;
    k->gain_keep = 1.0 - gain_delta;
    k->gain_widen = 1.0 + gain_delta;
    k->gain_tolerance = gain_tolerance;
    k->gain_significant = gain_significant;
}

void ok_reset_gain(ok_kernel *k, int64_t now_ns) {
    k->reference = k->gain = 1.0;
    k->reference_ns = now_ns;
}

void ok_reset_bright(ok_kernel *k) { k->bright_since_set = 0; }

/* ---------------------------------------------------------------- sorting */

static void insertion_sort(float *a, int32_t n) {
    for (int32_t i = 1; i < n; i++) {
        float v = a[i];
        int32_t j = i - 1;
        while (j >= 0 && a[j] > v) {
            a[j + 1] = a[j];
            j--;
        }
        a[j + 1] = v;
    }
}

/* Ascending (the values are finite): quicksort with a median of three, insertion sort below 16. */
static void quicksort_floats(float *a, int32_t n) {
    while (n > 16) {
        float x = a[0], y = a[n / 2], z = a[n - 1];
        float pivot = x < y ? (y < z ? y : (x < z ? z : x)) : (x < z ? x : (y < z ? z : y));
        int32_t i = 0, j = n - 1;
        for (;;) {
            while (a[i] < pivot) i++;
            while (a[j] > pivot) j--;
            if (i >= j) break;
            float t = a[i];
            a[i] = a[j];
            a[j] = t;
            i++;
            j--;
        }
        /* [0, j] <= pivot <= [j + 1, n): recurse into the smaller part, loop on the larger */
        int32_t left = j + 1;
        if (left < n - left) {
            quicksort_floats(a, left);
            a += left;
            n -= left;
        } else {
            quicksort_floats(a + left, n - left);
            n = left;
        }
    }
    insertion_sort(a, n);
}

/* A float's bits as an unsigned key in the floats' order (negatives flipped, positives above them). */
static inline uint32_t float_key(float f) {
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    return (u & 0x80000000u) ? ~u : u | 0x80000000u;
}

static inline float key_float(uint32_t k) {
    uint32_t u = (k & 0x80000000u) ? k & 0x7FFFFFFFu : ~k;
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

/* Ascending by the keys' bytes, least significant first (a byte all keys share is skipped); scratch:
 * OK_SORT_SCRATCH(n) words. */
static void radix_sort_floats(float *a, int32_t n, uint32_t *scratch) {
    uint32_t *src = scratch, *dst = scratch + n, *hist = scratch + 2 * (int64_t)n; /* hist: 4 x 256 */
    memset(hist, 0, 4 * 256 * sizeof(uint32_t));
    for (int32_t i = 0; i < n; i++) {
        uint32_t key = float_key(a[i]);
        src[i] = key;
        hist[key & 0xFF]++;
        hist[256 + ((key >> 8) & 0xFF)]++;
        hist[512 + ((key >> 16) & 0xFF)]++;
        hist[768 + (key >> 24)]++;
    }
    for (int d = 0; d < 4; d++) {
        uint32_t *h = hist + 256 * d, total = 0;
        int shift = 8 * d;
        if (h[(src[0] >> shift) & 0xFF] == (uint32_t)n) continue; /* every key has this byte */
        for (int b = 0; b < 256; b++) {
            uint32_t c = h[b];
            h[b] = total;
            total += c;
        }
        for (int32_t i = 0; i < n; i++) dst[h[(src[i] >> shift) & 0xFF]++] = src[i];
        uint32_t *t = src;
        src = dst;
        dst = t;
    }
    for (int32_t i = 0; i < n; i++) a[i] = key_float(src[i]);
}

void ok_sort_floats(float *a, int32_t n, uint32_t *scratch) {
    if (scratch && n >= OK_RADIX_MIN) radix_sort_floats(a, n, scratch);
    else quicksort_floats(a, n);
}

/* The k-th smallest of a[0 .. n-1] (finite), reordering a: Hoare's selection. */
static float select_kth(float *a, int32_t n, int32_t k) {
    int32_t lo = 0, hi = n - 1;
    while (hi > lo) {
        float x = a[lo], y = a[(lo + hi) / 2], z = a[hi];
        float pivot = x < y ? (y < z ? y : (x < z ? z : x)) : (x < z ? x : (y < z ? z : y));
        int32_t i = lo, j = hi;
        while (i <= j) {
            while (a[i] < pivot) i++;
            while (a[j] > pivot) j--;
            if (i <= j) {
                float t = a[i];
                a[i] = a[j];
                a[j] = t;
                i++;
                j--;
            }
        }
        /* [lo, j] <= pivot, (j, i) == pivot, [i, hi] >= pivot */
        if (k <= j) hi = j;
        else if (k >= i) lo = i;
        else return a[k];
    }
    return a[k];
}

/* ---------------------------------------------------------------- step 2: fiber means (FiberSampler) */

/* cv2.cvtColor(COLOR_RGB2GRAY) of one 8-bit pixel: BT.601 in 15-bit fixed point, rounded (exact). */
static inline uint32_t rgb_gray(const uint8_t *px, const uint32_t *w) {
    return ((uint32_t)px[0] * w[0] + (uint32_t)px[1] * w[1] + (uint32_t)px[2] * w[2] + 16384u) >> 15;
}

#define LANES16 0x00FF00FF00FF00FFull

/* The four 16-bit lanes of x added (exactly: into 32-bit lanes first, then the two). */
static inline uint32_t add_lanes16(uint64_t x) {
    x = (x & 0x0000FFFF0000FFFFull) + ((x >> 16) & 0x0000FFFF0000FFFFull);
    return (uint32_t)(x & 0xFFFFFFFFull) + (uint32_t)(x >> 32);
}

/* Gray (or yuv420's luminance plane): each fiber's pixels as 8-byte chunks, masked to the fiber's bytes
 * (precomputed), summed pairwise into four 16-bit lanes; the lanes added once per fiber (or every 128
 * chunks, before a lane can overflow: 128 * 510 < 65536), exactly (add_lanes16). */
static void gray_means(ok_kernel *k, const uint8_t *frame) {
    const ok_plan *p = &k->p;
    const int32_t *off = k->chunk_offset, *fc = k->fiber_chunk;
    const uint64_t *mask = k->chunk_mask;
    float *means = p->means;
    const float *inv = p->inv_count;
    int32_t nf = p->n_fibers;
#if defined(__GNUC__) || defined(__clang__)
    if (k->chunks_fit) { /* every fiber within 128 chunks (padded to pairs): two chunks per step, no flush */
        typedef uint64_t v2u64 __attribute__((vector_size(16)));
        const v2u64 lanes16 = {LANES16, LANES16};
        for (int32_t f = 0; f < nf; f++) {
            v2u64 acc = {0, 0};
            for (int32_t c = fc[f], end = fc[f + 1]; c < end; c += 2) {
                v2u64 x, m;
                memcpy(&x[0], frame + off[c], 8); /* (element stores into a local: two 8-byte loads) */
                uint64_t b;
                memcpy(&b, frame + off[c + 1], 8);
                x[1] = b;
                memcpy(&m, mask + c, sizeof m);
                x &= m;
                acc += (x & lanes16) + ((x >> 8) & lanes16);
            }
            means[f] = (float)(add_lanes16(acc[0]) + add_lanes16(acc[1])) * inv[f];
        }
        return;
    }
#endif
    for (int32_t f = 0; f < nf; f++) {
        uint64_t lanes = 0;
        uint32_t sum = 0;
        for (int32_t c = fc[f], end = fc[f + 1], n = 0; c < end; c++) {
            uint64_t x;
            memcpy(&x, frame + off[c], sizeof x);
            x &= mask[c];
            lanes += (x & LANES16) + ((x >> 8) & LANES16);
            if (++n == 128) {
                sum += add_lanes16(lanes);
                lanes = 0;
                n = 0;
            }
        }
        sum += add_lanes16(lanes);
        means[f] = (float)sum * inv[f];
    }
}

/* Frames of fewer than 8 bytes (tests): byte by byte. */
static void gray_means_bytes(ok_kernel *k, const uint8_t *frame) {
    const ok_plan *p = &k->p;
    for (int32_t f = 0; f < p->n_fibers; f++) {
        uint32_t sum = 0;
        for (int64_t j = p->pixel_start[f]; j < p->pixel_start[f + 1]; j++) sum += frame[p->pixel_index[j]];
        p->means[f] = (float)sum * p->inv_count[f];
    }
}

/* RGB: each fiber's chunks four pixels at a time: the 16 bytes from the chunk's first pixel shuffled so that
 * 32-bit lane i holds pixel i's r, g, b (and a byte that is masked off), the gray of each lane as rgb_gray
 * computes it, the lanes past the chunk's pixels zeroed; the sum is exact (integers), so it is rgb_gray's
 * sum to the bit. */
#if defined(__GNUC__) && !defined(__clang__)
typedef uint8_t v16u8 __attribute__((vector_size(16)));
typedef uint32_t v4u32 __attribute__((vector_size(16)));
CLONES_AVX2
static void rgb_means(ok_kernel *k, const uint8_t *frame, const uint32_t *w) {
    const ok_plan *p = &k->p;
    const int32_t *off = k->chunk_offset, *fc = k->fiber_chunk;
    const int8_t *pixels = k->chunk_pixels;
    const v16u8 pick = {0, 1, 2, 3, 3, 4, 5, 6, 6, 7, 8, 9, 9, 10, 11, 12};
    const v4u32 lanes[5] = {{0, 0, 0, 0}, {~0u, 0, 0, 0}, {~0u, ~0u, 0, 0}, {~0u, ~0u, ~0u, 0}, {~0u, ~0u, ~0u, ~0u}};
    const v4u32 w0 = {w[0], w[0], w[0], w[0]}, w1 = {w[1], w[1], w[1], w[1]}, w2 = {w[2], w[2], w[2], w[2]};
    const v4u32 byte = {0xFF, 0xFF, 0xFF, 0xFF}, half = {16384u, 16384u, 16384u, 16384u};
    for (int32_t f = 0; f < p->n_fibers; f++) {
        v4u32 acc = {0, 0, 0, 0};
        uint32_t sum = 0;
        for (int32_t c = fc[f], end = fc[f + 1]; c < end; c++) {
            const uint8_t *q = frame + off[c];
            int32_t m = pixels[c];
            if (m > 0) {
                v16u8 x;
                memcpy(&x, q, sizeof x);
                x = __builtin_shuffle(x, pick);
                v4u32 u;
                memcpy(&u, &x, sizeof u);
                v4u32 g = ((u & byte) * w0 + ((u >> 8) & byte) * w1 + ((u >> 16) & byte) * w2 + half) >> 15;
                acc += g & lanes[m];
            } else {
                for (int32_t i = 0; i < -m; i++) sum += rgb_gray(q + 3 * i, w);
            }
        }
        sum += (acc[0] + acc[1]) + (acc[2] + acc[3]);
        p->means[f] = (float)sum * p->inv_count[f];
    }
}
#endif

void ok_means(ok_kernel *k, const uint8_t *frame) {
    const ok_plan *p = &k->p;
    if (!p->rgb) {
        if (k->fiber_chunk) gray_means(k, frame);
        else gray_means_bytes(k, frame);
        return;
    }
    /* BT.601 (OpenCV's COLOR_RGB2GRAY to the bit) unless the plan gives another colour mix */
    uint32_t w[3] = {9798u, 19235u, 3735u};
    if (p->rgb_weights)
        for (int c = 0; c < 3; c++) w[c] = (uint32_t)p->rgb_weights[c];
#if defined(__GNUC__) && !defined(__clang__)
    rgb_means(k, frame, w);
#else
    const int32_t *start = k->run_start, *len = k->run_len, *fr = k->fiber_run;
    for (int32_t f = 0; f < p->n_fibers; f++) {
        uint32_t sum = 0;
        for (int32_t r = fr[f]; r < fr[f + 1]; r++) {
            const uint8_t *q = frame + 3 * (int64_t)start[r];
            for (int32_t i = 0; i < len[r]; i++) sum += rgb_gray(q + 3 * i, w);
        }
        p->means[f] = (float)sum * p->inv_count[f];
    }
#endif
}

/* ---------------------------------------------------------------- step 4: signal (Pipeline.compute_signal) */

/* Live ratios < value (<= with inclusive), compared in float32, on the sorted ratios. */
static int32_t count_below(const float *sorted, int32_t n, double value, int inclusive) {
    float probe = (float)value;
    int32_t lo = 0, hi = n; /* the first index whose value is not below */
    while (lo < hi) {
        int32_t mid = (lo + hi) / 2;
        int below = inclusive ? sorted[mid] <= probe : sorted[mid] < probe;
        if (below) lo = mid + 1;
        else hi = mid;
    }
    return lo;
}

/* GainCompensation.signal */
static void gain_signal(ok_kernel *k, int64_t now_ns) {
    const ok_plan *p = &k->p;
    int32_t nf = p->n_fibers, n = p->n_live;
    float black = p->black_level;
    float *ratio = k->ratio, *live = k->sorted;
    for (int32_t i = 0; i < nf; i++) ratio[i] = (p->means[i] - black) * p->inv_level[i];
    for (int32_t i = 0; i < n; i++) live[i] = ratio[p->live[i]];
    ok_sort_floats(live, n, k->sort_scratch);
    double g = live[(3 * (n - 1)) / 4];
    for (int it = 0; it < 2; it++) {
        int32_t j = count_below(live, n, g * k->gain_keep, 0);
        if (j >= n) break;
        g = 0.5 * ((double)live[(j + n - 1) / 2] + (double)live[(j + n) / 2]);
    }
    k->frame_gain = g;
    k->light_changed = 0;
    double band = k->gain_tolerance + p->gain_rate_per_ns * (double)(now_ns - k->reference_ns);
    double change = fabs(g - k->reference);
    k->held = 0;
    int32_t agree = count_below(live, n, g * k->gain_widen, 1) - count_below(live, n, g * k->gain_keep, 0);
    if (change > band && change > k->gain_significant && agree >= COMMON_MODE_FRACTION * n) {
        k->reference = g;
        k->reference_ns = now_ns;
        k->light_changed = 1;
        k->light_changes++;
    } else if (change > band) {
        g = g < k->reference ? k->reference - band : k->reference + band;
        k->held = change > k->gain_significant;
    }
    k->gain = g = g > 1e-3 ? g : 1e-3;
    float scale = (float)(-1.0 / g);
    float *out = p->signal;
    for (int32_t i = 0; i < nf; i++) {
        float v = ratio[i] * scale;
        v = v + 1.0f;
        out[i] = p->relative ? v : v * p->level[i];
    }
}

static void compute_signal(ok_kernel *k, int64_t now_ns) {
    const ok_plan *p = &k->p;
    int32_t nf = p->n_fibers;
    if (p->compensate_gain) {
        gain_signal(k, now_ns);
    } else {
        for (int32_t i = 0; i < nf; i++) {
            float v = p->baseline[i] - p->means[i];
            p->signal[i] = p->relative ? v * p->inv_level[i] : v;
        }
    }
    for (int32_t i = 0; i < p->n_dead; i++) p->signal[p->dead[i]] = 0.0f;
    if (p->band) { /* levels.banded: u = (|s| - shift)+, sign(s) max(u - c2 / u, 0) */
        const float *c2 = p->band, *shift = p->band + nf;
        float *s = p->signal;
        for (int32_t i = 0; i < nf; i++) {
            float v = s[i], u = fabsf(v) - shift[i];
            u = u > 0.0f ? u : 0.0f;
            float d = u > 1e-30f ? u : 1e-30f;
            float t = u - c2[i] / d;
            t = t > 0.0f ? t : 0.0f;
            s[i] = copysignf(t, v);
        }
    }
    if (p->support_nbr) { /* NeighbourSupport.peak: the frame's supported peak, a gate on its contacts */
        const float *s = p->signal;
        float top = -INFINITY;
        for (int32_t i = 0; i < nf; i++) {
            const int32_t *nb = p->support_nbr + 6 * (int64_t)i;
            float first = -INFINITY, second = -INFINITY;
            for (int j = 0; j < 6; j++) {
                float v = nb[j] >= 0 ? s[nb[j]] : 0.0f; /* a missing neighbour: at rest */
                if (v > first) {
                    second = first;
                    first = v;
                } else if (v > second) {
                    second = v;
                }
            }
            float limited = s[i] < second ? s[i] : second;
            if (limited > top) top = limited;
        }
        k->support_peak = top;
    }
}

/* ---------------------------------------------------------------- step 5: surface (TriangleSurface) */

#if defined(__GNUC__) || defined(__clang__)

/* Every matrix-vector product sums column c of a row into lane c mod 8, in column order, then adds the
 * lanes as ((0+1)+(2+3))+((4+5)+(6+7)) (sum8_lanes, simd.h), and the columns past a multiple of 8 last:
 * the same float32 sums on every machine, whatever its vector width. */

/* out[r] = sum_c op[r, c] * v[c]: four rows at a time, eight columns per step as two 4-lane halves
 * (SSE2 on x86-64, NEON on aarch64: both in their baseline). */
static void matvec4(const float *op, int32_t rows, int32_t cols, const float *v, float *out) {
    int32_t c8 = cols & ~7, r = 0;
    for (; r + 4 <= rows; r += 4) {
        const float *a = op + (int64_t)r * cols, *b = a + cols, *c = b + cols, *d = c + cols;
        v4f a0 = {0}, a1 = {0}, b0 = {0}, b1 = {0}, c0 = {0}, c1 = {0}, d0 = {0}, d1 = {0};
        for (int32_t j = 0; j < c8; j += 8) {
            v4f x0 = load4(v + j), x1 = load4(v + j + 4);
            a0 += load4(a + j) * x0;
            a1 += load4(a + j + 4) * x1;
            b0 += load4(b + j) * x0;
            b1 += load4(b + j + 4) * x1;
            c0 += load4(c + j) * x0;
            c1 += load4(c + j + 4) * x1;
            d0 += load4(d + j) * x0;
            d1 += load4(d + j + 4) * x1;
        }
        float ta = sum8_lanes(a0, a1), tb = sum8_lanes(b0, b1);
        float tc = sum8_lanes(c0, c1), td = sum8_lanes(d0, d1);
        for (int32_t j = c8; j < cols; j++) {
            ta += a[j] * v[j];
            tb += b[j] * v[j];
            tc += c[j] * v[j];
            td += d[j] * v[j];
        }
        out[r] = ta;
        out[r + 1] = tb;
        out[r + 2] = tc;
        out[r + 3] = td;
    }
    for (; r < rows; r++) {
        const float *a = op + (int64_t)r * cols;
        v4f a0 = {0}, a1 = {0};
        for (int32_t j = 0; j < c8; j += 8) {
            a0 += load4(a + j) * load4(v + j);
            a1 += load4(a + j + 4) * load4(v + j + 4);
        }
        float ta = sum8_lanes(a0, a1);
        for (int32_t j = c8; j < cols; j++) ta += a[j] * v[j];
        out[r] = ta;
    }
}

#if OK_AVX2
/* The same with the eight lanes in one AVX2 register (x86-64 machines that have it, chosen at init). */
__attribute__((target("avx2"))) static void matvec8(const float *op, int32_t rows, int32_t cols, const float *v,
                                                    float *out) {
    int32_t c8 = cols & ~7, r = 0;
    for (; r + 4 <= rows; r += 4) {
        const float *a = op + (int64_t)r * cols, *b = a + cols, *c = b + cols, *d = c + cols;
        v8f sa = {0}, sb = {0}, sc = {0}, sd = {0}, x, y;
        for (int32_t j = 0; j < c8; j += 8) {
            LOAD8(x, v + j);
            LOAD8(y, a + j);
            sa += y * x;
            LOAD8(y, b + j);
            sb += y * x;
            LOAD8(y, c + j);
            sc += y * x;
            LOAD8(y, d + j);
            sd += y * x;
        }
        float ta = SUM8(sa), tb = SUM8(sb), tc = SUM8(sc), td = SUM8(sd);
        for (int32_t j = c8; j < cols; j++) {
            ta += a[j] * v[j];
            tb += b[j] * v[j];
            tc += c[j] * v[j];
            td += d[j] * v[j];
        }
        out[r] = ta;
        out[r + 1] = tb;
        out[r + 2] = tc;
        out[r + 3] = td;
    }
    for (; r < rows; r++) {
        const float *a = op + (int64_t)r * cols;
        v8f sa = {0}, x, y;
        for (int32_t j = 0; j < c8; j += 8) {
            LOAD8(x, v + j);
            LOAD8(y, a + j);
            sa += y * x;
        }
        float ta = SUM8(sa);
        for (int32_t j = c8; j < cols; j++) ta += a[j] * v[j];
        out[r] = ta;
    }
}
#endif

static void matvec(const float *op, int32_t rows, int32_t cols, const float *v, float *out) {
#if OK_AVX2
    if (ok_avx2) {
        matvec8(op, rows, cols, v, out);
        return;
    }
#endif
    matvec4(op, rows, cols, v, out);
}
#else
/* The portable form: the same sums in the same order, one lane at a time. */
static void matvec(const float *op, int32_t rows, int32_t cols, const float *v, float *out) {
    int32_t c8 = cols & ~7;
    for (int32_t r = 0; r < rows; r++) {
        const float *a = op + (int64_t)r * cols;
        float s[8] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
        for (int32_t j = 0; j < c8; j += 8)
            for (int l = 0; l < 8; l++) s[l] += a[j + l] * v[j + l];
        float t = ((s[0] + s[1]) + (s[2] + s[3])) + ((s[4] + s[5]) + (s[6] + s[7]));
        for (int32_t j = c8; j < cols; j++) t += a[j] * v[j];
        out[r] = t;
    }
}
#endif

/* Keep a cell above the truncation level in the surface, the box and the peak. */
#define KEEP_CELL(cell, value)                                          \
    do {                                                                \
        int32_t rc_ = rc[cell], row_ = rc_ >> 16, col_ = rc_ & 0xFFFF;  \
        surface[cell] = (value);                                        \
        cells++;                                                        \
        if ((value) > peak) peak = (value);                             \
        if (col_ < x0) x0 = col_;                                       \
        if (col_ > x1) x1 = col_;                                       \
        if (row_ < y0) y0 = row_;                                       \
        if (row_ > y1) y1 = row_;                                       \
    } while (0)

/* A triangle's bound on |its surface|: the six gradient terms' |w| by their weights (gw: the triangle's
 * gradient weights), then the largest |vertex value| by the value weight, summed in that order. */
static inline float triangle_bound(const int32_t *cols, const float *gw, const float *aw, int32_t nv, float value_w) {
    float bound = 0.0f;
    if (nv == 3) { /* the usual factors: six gradient terms, a constant count the compiler writes out */
        for (int q = 0; q < 6; q++) bound += aw[cols[3 + q]] * gw[q];
    } else {
        for (int q = nv; q < OK_CELL_TERMS; q++) bound += aw[cols[q]] * gw[q - nv];
    }
    if (nv) {
        float a = aw[cols[0]], b = aw[cols[1]], c = aw[cols[2]];
        float vb = a > b ? a : b;
        vb = vb > c ? vb : c;
        bound += vb * value_w;
    }
    return bound;
}

#if OK_AVX2
#include <immintrin.h>
/* triangle_bound of the usual factors (three value terms) for eight triangles at a time, into bound[t]: each
 * lane the same multiplies and adds in the same order (so the same bits); the indices and weights gathered
 * at the triangles' stride. Returns how many triangles it did (a multiple of 8). */
__attribute__((target("avx2"))) static int32_t bounds8(const int32_t *tri_cols, const float *grad_w_t,
                                                      const float *aw, const float *value_w, int32_t T,
                                                      float *bound) {
    const __m256i stride = _mm256_setr_epi32(0, OK_CELL_TERMS, 2 * OK_CELL_TERMS, 3 * OK_CELL_TERMS,
                                             4 * OK_CELL_TERMS, 5 * OK_CELL_TERMS, 6 * OK_CELL_TERMS,
                                             7 * OK_CELL_TERMS);
    int32_t t = 0;
    for (; t + 8 <= T; t += 8) {
        const int32_t *cols = tri_cols + (int64_t)t * OK_CELL_TERMS;
        const float *gw = grad_w_t + (int64_t)t * OK_CELL_TERMS;
        __m256 b = _mm256_setzero_ps();
        for (int q = 0; q < 6; q++) {
            __m256i idx = _mm256_i32gather_epi32(cols + 3 + q, stride, 4);
            __m256 a = _mm256_i32gather_ps(aw, idx, 4);
            __m256 g = _mm256_i32gather_ps(gw + q, stride, 4);
            b = _mm256_add_ps(b, _mm256_mul_ps(a, g));
        }
        __m256 va = _mm256_i32gather_ps(aw, _mm256_i32gather_epi32(cols, stride, 4), 4);
        __m256 vb = _mm256_i32gather_ps(aw, _mm256_i32gather_epi32(cols + 1, stride, 4), 4);
        __m256 vc = _mm256_i32gather_ps(aw, _mm256_i32gather_epi32(cols + 2, stride, 4), 4);
        __m256 top = _mm256_max_ps(_mm256_max_ps(va, vb), vc); /* max_ps(x, y): x > y ? x : y, as the scalar */
        b = _mm256_add_ps(b, _mm256_mul_ps(top, _mm256_loadu_ps(value_w + t)));
        _mm256_storeu_ps(bound + t, b);
    }
    return t;
}
#endif

static int32_t triangle_surface(ok_kernel *k) {
    const ok_plan *p = &k->p;
    int32_t nf = p->n_fibers, n = p->n, T = p->n_tri, P = p->width, nv = p->n_value_terms;
    float *w = k->w, *surface = p->surface;
    int32_t *prev = k->selected + T, n_prev = k->n_selected; /* the last frame's triangles */
    memcpy(prev, k->selected, (size_t)n_prev * sizeof(int32_t));
    if (++k->stamp == 0) { /* wrapped (after 2^32 frames, 207 days at 240 fps): no triangle is current */
        memset(k->tri_stamp, 0, (size_t)T * sizeof(uint32_t));
        k->stamp = 1;
    }
    uint32_t stamp = k->stamp;
    memcpy(w, p->signal, (size_t)nf * sizeof(float));
    for (int32_t r = 0; r < p->n_value_rows; r++) {
        const float *row = p->value_op + (int64_t)r * nf;
        float s = 0.0f;
        for (int32_t c = 0; c < nf; c++) s += row[c] * p->signal[c];
        w[p->value_rows[r]] = s;
    }
    if (p->gs_fibers) ok_gradient_solve(p, w, k->gs_y + OK_GS_PAD, w + nf);
    else matvec(p->grad_op, 2 * nf, nf, p->signal, w + nf);
    float level = (float)((double)k->trunc * (1.0 - BOUND_MARGIN));
    float trunc = k->trunc;
    int32_t n_sel = 0, cells = 0;
    int32_t x0 = n, y0 = n, x1 = -1, y1 = -1; /* the kept triangles' boxes, shrunk to the cells after */
    float peak = 0.0f;
    for (int32_t i = 0; i < 3 * nf; i++) k->absw[i] = fabsf(w[i]);
    int32_t t_done = 0; /* triangles whose bound is in k->bound already (eight at a time with AVX2) */
#if OK_AVX2
    if (ok_avx2 && nv == 3) t_done = bounds8(p->tri_cols, k->grad_w_t, k->absw, p->value_w, T, k->bound);
#endif
    const float *aw = k->absw;
    for (int32_t t = 0; t < T; t++) {
        float bound;
        if (t < t_done) {
            bound = k->bound[t];
        } else {
            bound = triangle_bound(p->tri_cols + (int64_t)t * OK_CELL_TERMS, k->grad_w_t + (int64_t)t * OK_CELL_TERMS,
                                   aw, nv, nv ? p->value_w[t] : 0.0f);
        }
        if (!(bound > level)) continue;
        const int32_t *cols = p->tri_cols + (int64_t)t * OK_CELL_TERMS;
        k->selected[n_sel++] = t;
        k->tri_stamp[t] = stamp;
        float terms[OK_CELL_TERMS];
        for (int q = 0; q < OK_CELL_TERMS; q++) terms[q] = w[cols[q]];
        const float *wt = p->tri_weights + (int64_t)t * OK_CELL_TERMS * P;
        const int32_t *cl = p->tri_cells + (int64_t)t * P;
        int32_t cnt = p->tri_count[t], q = 0, kept = 0;
#if defined(__GNUC__) || defined(__clang__)
        const v4f tv = {trunc, trunc, trunc, trunc};
        v4i kept4 = {0, 0, 0, 0};
        v4f top4 = {0.0f, 0.0f, 0.0f, 0.0f};
        for (; q + 4 <= cnt; q += 4) { /* four cells at a time: lane j sums cell q + j's terms in order */
            v4f v = {0};
            for (int m = 0; m < OK_CELL_TERMS; m++) v += terms[m] * load4(wt + (int64_t)m * P + q);
            v4i above = v > tv, bits; /* -1 where kept: the value's bits, else 0.0f */
            memcpy(&bits, &v, sizeof bits);
            bits &= above;
            memcpy(&v, &bits, sizeof v);
            kept4 -= above;
            v4i more = v > top4, tb, vb; /* top4 = max(top4, v) by bits */
            memcpy(&tb, &top4, sizeof tb);
            memcpy(&vb, &v, sizeof vb);
            tb = (vb & more) | (tb & ~more);
            memcpy(&top4, &tb, sizeof top4);
            surface[cl[q]] = v[0];
            surface[cl[q + 1]] = v[1];
            surface[cl[q + 2]] = v[2];
            surface[cl[q + 3]] = v[3];
        }
        kept += (kept4[0] + kept4[1]) + (kept4[2] + kept4[3]);
        for (int j = 0; j < 4; j++) peak = top4[j] > peak ? top4[j] : peak;
#endif
        for (; q < cnt; q++) {
            float v = 0.0f;
            for (int m = 0; m < OK_CELL_TERMS; m++) v += terms[m] * wt[(int64_t)m * P + q];
            int above = v > trunc;
            surface[cl[q]] = above ? v : 0.0f;
            kept += above;
            peak = above && v > peak ? v : peak;
        }
        if (!kept) continue;
        cells += kept;
        const int32_t *b = k->tri_box + 4 * (int64_t)t;
        if (b[0] < x0) x0 = b[0];
        if (b[1] < y0) y0 = b[1];
        if (b[2] > x1) x1 = b[2];
        if (b[3] > y1) y1 = b[3];
    }
    for (int32_t s_ = 0; s_ < n_prev; s_++) { /* the last frame's triangles not evaluated now back to 0 */
        int32_t t = prev[s_];
        if (k->tri_stamp[t] == stamp) continue;
        const int32_t *cl = p->tri_cells + (int64_t)t * P;
        for (int32_t q = 0; q < p->tri_count[t]; q++) surface[cl[q]] = 0.0f;
    }
    if (cells) { /* the triangles' box shrunk to the cells above the level */
        const float *sf = surface;
        for (;; y0++) { int any = 0; for (int32_t x = x0; x <= x1; x++) any |= sf[(int64_t)y0 * n + x] > 0.0f; if (any) break; }
        for (;; y1--) { int any = 0; for (int32_t x = x0; x <= x1; x++) any |= sf[(int64_t)y1 * n + x] > 0.0f; if (any) break; }
        for (;; x0++) { int any = 0; for (int32_t y = y0; y <= y1; y++) any |= sf[(int64_t)y * n + x0] > 0.0f; if (any) break; }
        for (;; x1--) { int any = 0; for (int32_t y = y0; y <= y1; y++) any |= sf[(int64_t)y * n + x1] > 0.0f; if (any) break; }
    }
    k->n_selected = n_sel;
    k->evaluated = n_sel;
    k->peak = peak;
    k->box_x = x0;
    k->box_y = y0;
    k->box_w = x1 - x0 + 1;
    k->box_h = y1 - y0 + 1;
    return cells;
}

static int32_t dense_surface(ok_kernel *k) {
    const ok_plan *p = &k->p;
    int32_t n = p->n, cells = 0;
    float *surface = p->surface;
    float trunc = k->trunc, peak = 0.0f;
    const int32_t *rc = k->cell_rc;
    int32_t x0 = n, y0 = n, x1 = -1, y1 = -1;
    matvec(p->dense, n * n, p->n_fibers, p->signal, surface);
    for (int32_t c = 0; c < n * n; c++) {
        float v = surface[c];
        if (v > trunc) KEEP_CELL(c, v);
        else surface[c] = 0.0f;
    }
    k->peak = peak;
    k->box_x = x0;
    k->box_y = y0;
    k->box_w = x1 - x0 + 1;
    k->box_h = y1 - y0 + 1;
    return cells;
}

int32_t ok_surface(ok_kernel *k, int64_t now_ns) {
    compute_signal(k, now_ns);
    k->cells = k->p.tri_cols ? triangle_surface(k) : dense_surface(k);
    return k->cells;
}

/* ---------------------------------------------------------------- step 7: moments (BlobMeasurer) */

/* log_hu_value */
static double log_hu_value(double h) {
    if (h == 0.0) return 0.0;
    if (isnan(h)) return NAN;
    return -copysign(1.0, h) * log10(fabs(h));
}

/* BinaryShapeMoments.hu_q4 of img > level: hu_q4[0..6] the log-Hu invariants, [7] q4; NaN if empty. */
#if defined(__GNUC__) || defined(__clang__)
typedef double v4d __attribute__((vector_size(32)));
typedef int64_t v4l __attribute__((vector_size(32)));
#endif

/* One row of a binary shape img > level: r[p] = sum of x ** p over its cells (exact integers, in any
 * order), four cells at a time. xp: the powers, xp[p * n + x]. */
CLONES_AVX2
static void binary_row(const float *row, int32_t w, float level, const double *xp, int32_t n, double *r) {
    int32_t x = 0;
    double t[5] = {0, 0, 0, 0, 0};
#if defined(__GNUC__) || defined(__clang__)
    v4d acc[5] = {{0}, {0}, {0}, {0}, {0}};
    const v4f lv = {level, level, level, level};
    for (; x + 4 <= w; x += 4) {
        v4f f;
        memcpy(&f, row + x, sizeof f);
        v4l keep = __builtin_convertvector(f > lv, v4l); /* all ones where the cell is in */
        for (int q = 0; q < 5; q++) {
            v4l bits;
            memcpy(&bits, xp + (int64_t)q * n + x, sizeof bits);
            bits &= keep;
            v4d v;
            memcpy(&v, &bits, sizeof v);
            acc[q] += v;
        }
    }
    for (int q = 0; q < 5; q++) t[q] = (acc[q][0] + acc[q][1]) + (acc[q][2] + acc[q][3]);
#endif
    for (; x < w; x++)
        if (row[x] > level)
            for (int q = 0; q < 5; q++) t[q] += xp[(int64_t)q * n + x];
    for (int q = 0; q < 5; q++) r[q] = t[q];
}

void ok_hu_q4(const float *img, int32_t h, int32_t w, int32_t stride, float level, const double *xp, int32_t n,
              double *hu_q4) {
    double m[5][5] = {{0}}; /* m[q][p]: y power q, x power p */
    for (int32_t y = 0; y < h; y++) {
        double r[5];
        binary_row(img + (int64_t)y * stride, w, level, xp, n, r);
        if (r[0] == 0.0) continue;
        for (int q = 0; q < 5; q++)
            for (int pp = 0; pp + q < 5; pp++) m[q][pp] += xp[(int64_t)q * n + y] * r[pp];
    }
    double m00 = m[0][0];
    if (!(m00 > 0.0)) {
        for (int i = 0; i < 8; i++) hu_q4[i] = NAN;
        return;
    }
    double m10 = m[0][1], m20 = m[0][2], m30 = m[0][3], m40 = m[0][4];
    double m01 = m[1][0], m11 = m[1][1], m21 = m[1][2], m31 = m[1][3];
    double m02 = m[2][0], m12 = m[2][1], m22 = m[2][2];
    double m03 = m[3][0], m13 = m[3][1], m04 = m[4][0];
    double cx = m10 / m00, cy = m01 / m00;
    double mu20 = m20 - cx * m10, mu11 = m11 - cx * m01, mu02 = m02 - cy * m01;
    double mu30 = m30 - cx * (3.0 * m20 - 2.0 * cx * m10);
    double mu21 = m21 - 2.0 * cx * m11 - cy * m20 + 2.0 * cx * cx * m01;
    double mu12 = m12 - 2.0 * cy * m11 - cx * m02 + 2.0 * cy * cy * m10;
    double mu03 = m03 - cy * (3.0 * m02 - 2.0 * cy * m01);
    double s2 = m00 * m00, s3 = s2 * sqrt(m00);
    double n20 = mu20 / s2, n11 = mu11 / s2, n02 = mu02 / s2;
    double n30 = mu30 / s3, n21 = mu21 / s3, n12 = mu12 / s3, n03 = mu03 / s3;
    /* hu_from_normalized */
    double t0 = n30 + n12, t1 = n21 + n03;
    double q0 = n30 - 3.0 * n12, q1 = 3.0 * n21 - n03;
    double hu[7] = {n20 + n02,
                    (n20 - n02) * (n20 - n02) + 4.0 * n11 * n11,
                    q0 * q0 + q1 * q1,
                    t0 * t0 + t1 * t1,
                    q0 * t0 * (t0 * t0 - 3.0 * t1 * t1) + q1 * t1 * (3.0 * t0 * t0 - t1 * t1),
                    (n20 - n02) * (t0 * t0 - t1 * t1) + 4.0 * n11 * t0 * t1,
                    q1 * t0 * (t0 * t0 - 3.0 * t1 * t1) - q0 * t1 * (3.0 * t0 * t0 - t1 * t1)};
    for (int i = 0; i < 7; i++) hu_q4[i] = log_hu_value(hu[i]);
    /* q4: c40 = z4 - 4 c z3 + 6 c^2 z2 - 3 c^4 m00 with c = cx + i cy (complex, as Python) */
    double z2r = m20 - m02, z2i = 2.0 * m11;
    double z3r = m30 - 3.0 * m12, z3i = 3.0 * m21 - m03;
    double z4r = m40 - 6.0 * m22 + m04, z4i = 4.0 * (m31 - m13);
    double c2r = cx * cx - cy * cy, c2i = cx * cy + cy * cx;
    double a_r = 4.0 * cx, a_i = 4.0 * cy;                         /* 4.0 * c */
    double cz3r = a_r * z3r - a_i * z3i, cz3i = a_r * z3i + a_i * z3r; /* (4c) z3 */
    double b_r = 6.0 * c2r, b_i = 6.0 * c2i;                       /* 6.0 * c2 */
    double cz2r = b_r * z2r - b_i * z2i, cz2i = b_r * z2i + b_i * z2r;
    double c4r = c2r * c2r - c2i * c2i, c4i = c2r * c2i + c2i * c2r; /* c2 * c2 */
    double d_r = 3.0 * c4r, d_i = 3.0 * c4i;                       /* 3.0 * c2 * c2 */
    double e_r = d_r * m00, e_i = d_i * m00;
    double c40r = z4r - cz3r + cz2r - e_r, c40i = z4i - cz3i + cz2i - e_i;
    hu_q4[7] = hypot(c40r, c40i) / (s2 * m00);
}

/* BlobMeasurer.ellipse: cv2.moments of a float32 box's cells above `above` (float64 sums; their number
 * into cells), into out; 0 when it holds nothing. */
/* One row of the weighted moments: s[0..2] = sum of v, v x, v x^2 over the cells above `above` (the others
 * weigh 0), float64, four cells at a time; their number. xs: the column coordinates. */
CLONES_AVX2
static int32_t ellipse_row(const float *row, int32_t w, float above, const double *xs, double *s) {
    int32_t x = 0, count = 0;
    double s0 = 0, s1 = 0, s2 = 0;
#if defined(__GNUC__) || defined(__clang__)
    v4d a0 = {0}, a1 = {0}, a2 = {0};
    v4i kept = {0};
    const v4f av = {above, above, above, above};
    for (; x + 4 <= w; x += 4) {
        v4f f;
        memcpy(&f, row + x, sizeof f);
        v4i keep = f > av, bits; /* cv2.threshold TOZERO */
        memcpy(&bits, &f, sizeof bits);
        bits &= keep;
        memcpy(&f, &bits, sizeof f);
        kept -= keep;
        v4d v = __builtin_convertvector(f, v4d), xv;
        memcpy(&xv, xs + x, sizeof xv);
        v4d vx = v * xv;
        a0 += v;
        a1 += vx;
        a2 += vx * xv;
    }
    s0 = (a0[0] + a0[1]) + (a0[2] + a0[3]);
    s1 = (a1[0] + a1[1]) + (a1[2] + a1[3]);
    s2 = (a2[0] + a2[1]) + (a2[2] + a2[3]);
    count = (kept[0] + kept[1]) + (kept[2] + kept[3]);
#endif
    for (; x < w; x++) {
        int keep = row[x] > above;
        double v = keep ? row[x] : 0.0f;
        double vx = v * x;
        count += keep;
        s0 += v;
        s1 += vx;
        s2 += vx * x;
    }
    s[0] = s0;
    s[1] = s1;
    s[2] = s2;
    return count;
}

static int ellipse(const ok_kernel *k, const float *img, int32_t h, int32_t w, int32_t stride, float above,
                   int32_t *cells, int32_t bx, int32_t by, double *out) {
    double m00 = 0, m10 = 0, m01 = 0, m20 = 0, m11 = 0, m02 = 0;
    int32_t count = 0;
    const double *xs = k->powers + k->p.n; /* powers[1 * n + x] = x */
    for (int32_t y = 0; y < h; y++) {
        double r[3];
        count += ellipse_row(img + (int64_t)y * stride, w, above, xs, r);
        double s0 = r[0], s1 = r[1], s2 = r[2];
        m00 += s0;
        m10 += s1;
        m01 += s0 * y;
        m20 += s2;
        m11 += s1 * y;
        m02 += s0 * y * y;
    }
    *cells = count;
    if (!(m00 > 0.0)) return 0;
    double cx = m10 / m00, cy = m01 / m00;
    double step = k->p.step_mm, area = k->p.cell_area_mm2, scale = step * step * area;
    double mu20 = (m20 - m10 * cx) * scale, mu11 = (m11 - m10 * cy) * scale, mu02 = (m02 - m01 * cy) * scale;
    double s = m00 * area;
    /* ellipse_from_central */
    double a = mu20 / s, b = mu11 / s, c = mu02 / s;
    double half_trace = 0.5 * (a + c);
    double half_root = 0.5 * sqrt(4.0 * b * b + (a - c) * (a - c));
    double lam1 = half_trace + half_root, lam2 = half_trace - half_root;
    double angle = 0.5 * (atan2(2.0 * b, a - c) * (180.0 / OK_PI));
    if (angle <= -90.0) angle += 180.0;
    out[OK_STRENGTH] = s;
    out[OK_X_MM] = k->p.x0_mm + step * (bx + m10 / m00);
    out[OK_Y_MM] = k->p.y0_mm + step * (by + m01 / m00);
    out[OK_MAJOR_MM] = FWHM_PER_SIGMA * sqrt(lam1 > 0.0 ? lam1 : 0.0);
    out[OK_MINOR_MM] = FWHM_PER_SIGMA * sqrt(lam2 > 0.0 ? lam2 : 0.0);
    out[OK_ANGLE_DEG] = angle;
    return 1;
}

/* BlobMeasurer.measure: one blob (img, h x w, rows stride apart, first cell at mesh column bx, row by)
 * into out; whether it is a contact. */
static int measure(ok_kernel *k, const float *img, int32_t h, int32_t w, int32_t stride, double peak, double cells,
                   float level, int32_t bx, int32_t by, double *out) {
    const ok_plan *p = &k->p;
    if (!(peak > (double)level) || cells * p->cell_area_mm2 < p->min_area_mm2) return 0;
    double trunc = k->trunc, t = trunc;
    if (p->peak_fraction > 0.0 && p->peak_fraction * peak > t) t = (float)(p->peak_fraction * peak);
    double shape_level = t;
    if (p->shape_fraction > 0.0) shape_level = trunc > p->shape_fraction * peak ? trunc : p->shape_fraction * peak;
    int32_t count;
    if (!ellipse(k, img, h, w, stride, (float)t, &count, bx, by, out)) return 0;
    if (t > trunc) cells = count; /* the cells above the weighting level */
    out[OK_AREA_MM2] = cells * p->cell_area_mm2;
    out[OK_PEAK] = peak;
    ok_hu_q4(img, h, w, stride, (float)shape_level, k->powers, p->n, out + OK_HU0);
    return 1;
}

/* ---------------------------------------------------------------- step 7: the split (Segmenter) */

static int32_t find_root(int32_t *parent, int32_t a) {
    while (parent[a] != a) {
        parent[a] = parent[parent[a]];
        a = parent[a];
    }
    return a;
}

static int32_t unite(int32_t *parent, int32_t a, int32_t b) {
    a = find_root(parent, a);
    b = find_root(parent, b);
    if (a < b) { parent[b] = a; return a; }
    parent[a] = b;
    return b;
}

int32_t ok_label_runs(const int32_t *y, const int32_t *x0, const int32_t *x1, int32_t n, int32_t *label,
                      int32_t *parent, int32_t *map) {
    int32_t cur_start = 0, prev_start = 0, prev_end = 0; /* this row's runs from cur_start; the row above's */
    for (int32_t i = 0; i < n; i++) {
        parent[i] = i;
        if (i > 0 && y[i] != y[i - 1]) { /* the runs [cur_start, i) were a row: the row above if adjacent */
            prev_start = y[i] == y[i - 1] + 1 ? cur_start : i;
            prev_end = i;
            cur_start = i;
        }
        /* runs of the row above that touch this one (8-connected: one column of slack either side) */
        for (int32_t j = prev_start; j < prev_end; j++) {
            if (x1[j] < x0[i] - 1) continue;
            if (x0[j] > x1[i] + 1) break;
            unite(parent, i, j);
        }
    }
    int32_t final = 1;
    for (int32_t i = 0; i < n; i++) map[i] = 0;
    for (int32_t i = 0; i < n; i++) {
        int32_t r = find_root(parent, i);
        if (!map[r]) map[r] = final++;
        label[i] = map[r];
    }
    return final;
}

/* Indices 0 .. n-1 of keys, stably ordered by decreasing key (insertion sort: a handful of entries). */
static void order_decreasing(const double *keys, int32_t *order, int32_t n, int32_t stride) {
    for (int32_t i = 0; i < n; i++) {
        int32_t v = order[i];
        int32_t j = i - 1;
        while (j >= 0 && keys[(int64_t)order[j] * stride] < keys[(int64_t)v * stride]) {
            order[j + 1] = order[j];
            j--;
        }
        order[j + 1] = v;
    }
}

/* Contacts from labelled runs of the box's cells above the truncation level (run i: row y[i], columns
 * x0[i] .. x1[i], label lab[i] in 1 .. n_labels - 1): each label's cells, largest first (ties in label
 * order), at least min_cells, measured alone in its own box (Segmenter._largest_first, contact_surface).
 * Candidates into k->cand; their number. */
static int32_t measure_parts(ok_kernel *k, float level, const int32_t *y, const int32_t *x0, const int32_t *x1,
                             const int32_t *lab, int32_t nr, int32_t n_labels) {
    const ok_plan *p = &k->p;
    int32_t stride = p->n;
    const float *box = p->surface + (int64_t)k->box_y * stride + k->box_x;
    int32_t *counts = k->counts, *rect = k->rect, *order = k->order;
    for (int32_t l = 0; l < n_labels; l++) {
        counts[l] = 0;
        rect[4 * l] = rect[4 * l + 1] = INT32_MAX;
        rect[4 * l + 2] = rect[4 * l + 3] = -1;
    }
    for (int32_t i = 0; i < nr; i++) {
        int32_t l = lab[i], *r = rect + 4 * l;
        counts[l] += x1[i] - x0[i] + 1;
        if (x0[i] < r[0]) r[0] = x0[i];
        if (y[i] < r[1]) r[1] = y[i];
        if (x1[i] > r[2]) r[2] = x1[i];
        if (y[i] > r[3]) r[3] = y[i];
    }
    double min_cells = p->min_cells - 1e-9;
    int32_t m = 0;
    for (int32_t l = 1; l < n_labels; l++)
        if (counts[l] > 0 && counts[l] >= min_cells) order[m++] = l;
    for (int32_t i = 1; i < m; i++) { /* stable insertion sort by decreasing count */
        int32_t v = order[i], j = i - 1;
        while (j >= 0 && counts[order[j]] < counts[v]) {
            order[j + 1] = order[j];
            j--;
        }
        order[j + 1] = v;
    }
    int32_t n_cand = 0;
    for (int32_t i = 0; i < m && n_cand < OK_MAX_CANDIDATES; i++) {
        int32_t l = order[i];
        const int32_t *r = rect + 4 * l;
        int32_t rw = r[2] - r[0] + 1, rh = r[3] - r[1] + 1;
        float *blob = k->blob, top = 0.0f; /* blob is all 0 between contacts */
        for (int32_t j = 0; j < nr; j++) {
            if (lab[j] != l) continue;
            const float *src = box + (int64_t)y[j] * stride;
            float *dst = blob + (int64_t)(y[j] - r[1]) * rw - r[0];
            for (int32_t x = x0[j]; x <= x1[j]; x++) {
                dst[x] = src[x];
                if (src[x] > top) top = src[x];
            }
        }
        n_cand += measure(k, blob, rh, rw, rw, top, counts[l], level, k->box_x + r[0], k->box_y + r[1],
                          k->cand + (int64_t)n_cand * OK_FIELDS);
        for (int32_t j = 0; j < nr; j++) /* back to 0, run by run written */
            if (lab[j] == l)
                memset(blob + (int64_t)(y[j] - r[1]) * rw + (x0[j] - r[0]), 0,
                       (size_t)(x1[j] - x0[j] + 1) * sizeof(float));
    }
    return n_cand;
}

/* The chamfer weights of OpenCV's labelled distance transform (DIST_L2; with labels its mask is 5 x 5:
 * 1, 1.4 and 2.1969 as float32, times 2^16, rounded). */
#define DT_HV 65536
#define DT_DIAG 91750
#define DT_LONG 143976
#define DT_FAR (INT32_MAX >> 2)

/* See frame_kernel.h. A forward and a backward pass of a 5 x 5 chamfer in 16.16 fixed point, the first of
 * equally near neighbours winning in OpenCV's order (its distanceTransformEx_5x5). */
/* The best of a row's seven neighbours in the rows above (mirror = 0: from DT_FAR) or below (mirror = 1:
 * from the cell's own distance), for every cell of the row: the first strictly nearest wins, as OpenCV
 * checks them. t, l: the row's distances and labels (a border of 2 around); off: the seven offsets. */
static void dt_best_scalar(const int32_t *t, const int32_t *l, const int32_t *off, const int32_t *cost, int32_t j,
                           int32_t bw, int mirror, int32_t *best_t, int32_t *best_l) {
    for (; j < bw; j++) {
        int32_t t0 = mirror ? t[j] : DT_FAR, l0 = mirror ? l[j] : 0;
        for (int q = 0; q < 7; q++) {
            int32_t o = mirror ? -off[q] : off[q], v = t[j + o] + cost[q];
            if (t0 > v) {
                t0 = v;
                l0 = l[j + o];
            }
        }
        best_t[j] = t0;
        best_l[j] = l0;
    }
}

#if defined(__GNUC__) || defined(__clang__)
/* Four cells at a time (SSE2, NEON): exact integer minima, the same winners as one at a time. */
static void dt_best4(const int32_t *t, const int32_t *l, const int32_t *off, const int32_t *cost, int32_t bw,
                     int mirror, int32_t *best_t, int32_t *best_l) {
    int32_t j = 0;
    for (; j + 4 <= bw; j += 4) {
        v4i t0 = {DT_FAR, DT_FAR, DT_FAR, DT_FAR}, l0 = {0, 0, 0, 0};
        if (mirror) {
            memcpy(&t0, t + j, sizeof t0);
            memcpy(&l0, l + j, sizeof l0);
        }
        for (int q = 0; q < 7; q++) {
            int32_t o = mirror ? -off[q] : off[q];
            v4i v, lv;
            memcpy(&v, t + j + o, sizeof v);
            memcpy(&lv, l + j + o, sizeof lv);
            v += cost[q];
            v4i m = t0 > v; /* strictly nearer: the first of equals stays */
            t0 = (v & m) | (t0 & ~m);
            l0 = (lv & m) | (l0 & ~m);
        }
        memcpy(best_t + j, &t0, sizeof t0);
        memcpy(best_l + j, &l0, sizeof l0);
    }
    dt_best_scalar(t, l, off, cost, j, bw, mirror, best_t, best_l);
}
#endif

#if OK_AVX2
typedef int32_t v8i __attribute__((vector_size(32)));
/* Eight cells at a time (AVX2). */
__attribute__((target("avx2"))) static void dt_best8(const int32_t *t, const int32_t *l, const int32_t *off,
                                                     const int32_t *cost, int32_t bw, int mirror, int32_t *best_t,
                                                     int32_t *best_l) {
    int32_t j = 0;
    for (; j + 8 <= bw; j += 8) {
        v8i t0 = {DT_FAR, DT_FAR, DT_FAR, DT_FAR, DT_FAR, DT_FAR, DT_FAR, DT_FAR}, l0 = {0};
        if (mirror) {
            memcpy(&t0, t + j, sizeof t0);
            memcpy(&l0, l + j, sizeof l0);
        }
        for (int q = 0; q < 7; q++) {
            int32_t o = mirror ? -off[q] : off[q];
            v8i v, lv;
            memcpy(&v, t + j + o, sizeof v);
            memcpy(&lv, l + j + o, sizeof lv);
            v += cost[q];
            v8i m = t0 > v;
            t0 = (v & m) | (t0 & ~m);
            l0 = (lv & m) | (l0 & ~m);
        }
        memcpy(best_t + j, &t0, sizeof t0);
        memcpy(best_l + j, &l0, sizeof l0);
    }
    dt_best_scalar(t, l, off, cost, j, bw, mirror, best_t, best_l);
}
#endif

static void dt_best(const int32_t *t, const int32_t *l, const int32_t *off, const int32_t *cost, int32_t bw,
                    int mirror, int32_t *best_t, int32_t *best_l) {
#if OK_AVX2
    if (ok_avx2) {
        dt_best8(t, l, off, cost, bw, mirror, best_t, best_l);
        return;
    }
#endif
#if defined(__GNUC__) || defined(__clang__)
    dt_best4(t, l, off, cost, bw, mirror, best_t, best_l);
#else
    dt_best_scalar(t, l, off, cost, 0, bw, mirror, best_t, best_l);
#endif
}

CLONES_AVX2
void ok_nearest_seed(const int32_t *seed_label, int32_t bh, int32_t bw, int32_t *d, int32_t *nearest) {
    /* d: distances, then labels, each (bh + 4) x (bw + 4) with a border of 2 (DT_FAR, label 0), then two
     * rows of bw + 4 for the best of the seven neighbours of the rows above (below) */
    int32_t W = bw + 4;
    int64_t cells = (int64_t)(bh + 4) * W;
    int32_t *lab = d + cells, *best_t = lab + cells, *best_l = best_t + W;
    for (int32_t i = 0; i < bh + 4; i++) { /* the border (the passes write every inner cell) */
        int32_t *dr = d + (int64_t)i * W, *lr = lab + (int64_t)i * W;
        if (i < 2 || i >= bh + 2) {
            for (int32_t j = 0; j < W; j++) {
                dr[j] = DT_FAR;
                lr[j] = 0;
            }
        } else {
            dr[0] = dr[1] = dr[W - 2] = dr[W - 1] = DT_FAR;
            lr[0] = lr[1] = lr[W - 2] = lr[W - 1] = 0;
        }
    }
    static const int dy_f[7] = {-2, -2, -1, -1, -1, -1, -1}, dx_f[7] = {-1, 1, -2, -1, 0, 1, 2};
    static const int32_t cost[7] = {DT_LONG, DT_LONG, DT_LONG, DT_DIAG, DT_HV, DT_DIAG, DT_LONG};
    int32_t off[7];
    for (int q = 0; q < 7; q++) off[q] = dy_f[q] * W + dx_f[q];
    for (int32_t i = 0; i < bh; i++) { /* forward: the seven above, in order, then the one to the left */
        int32_t *t = d + (int64_t)(i + 2) * W + 2, *l = lab + (int64_t)(i + 2) * W + 2;
        const int32_t *sl = seed_label + (int64_t)i * bw;
        dt_best(t, l, off, cost, bw, 0, best_t, best_l);
        for (int32_t j = 0; j < bw; j++) {
            if (sl[j]) {
                t[j] = 0;
                l[j] = sl[j];
                continue;
            }
            int32_t t0 = best_t[j], l0 = best_l[j], v = t[j - 1] + DT_HV;
            if (t0 > v) {
                t0 = v;
                l0 = l[j - 1];
            }
            t[j] = t0;
            l[j] = l0;
        }
    }
    for (int32_t i = bh - 1; i >= 0; i--) { /* backward: the seven below (mirrored), then the one to the right */
        int32_t *t = d + (int64_t)(i + 2) * W + 2, *l = lab + (int64_t)(i + 2) * W + 2;
        dt_best(t, l, off, cost, bw, 1, best_t, best_l);
        for (int32_t j = bw - 1; j >= 0; j--) {
            if (t[j] <= DT_HV) continue; /* a seed, or next to one */
            int32_t t0 = best_t[j], l0 = best_l[j], v = t[j + 1] + DT_HV;
            if (t0 > v) {
                t0 = v;
                l0 = l[j + 1];
            }
            t[j] = t0;
            l[j] = l0;
        }
    }
    for (int32_t i = 0; i < bh; i++)
        memcpy(nearest + (int64_t)i * bw, lab + (int64_t)(i + 2) * W + 2, (size_t)bw * sizeof(int32_t));
}

/* Segmenter.partition, then ContactFinder's measuring of each contact, from the runs ok_find made:
 * one blob holding one seed is one contact; blobs holding at most one seed each are one contact each;
 * otherwise every cell above the truncation level goes to its nearest seed (the strong blobs, and the
 * blobs without one). Candidates into k->cand; their number. */
static int32_t split_blobs(ok_kernel *k, float level, double peak) {
    const ok_plan *p = &k->p;
    int32_t bw = k->box_w, bh = k->box_h, nr = k->n_runs, ns = k->n_seed_runs;
    int32_t stride = p->n;
    const float *box = p->surface + (int64_t)k->box_y * stride + k->box_x;
    int32_t n_parts = ok_label_runs(k->run_y, k->run_x0, k->run_x1, nr, k->run_label, k->parent, k->order);
    int32_t n_seeds = ok_label_runs(k->seed_y, k->seed_x0, k->seed_x1, ns, k->seed_label, k->parent, k->order) - 1;
    if (n_parts == 2 && n_seeds == 1) /* one blob holding one seed: one contact */
        return k->cells >= p->min_cells - 1e-9
            && measure(k, box, bh, bw, stride, peak, k->cells, level, k->box_x, k->box_y, k->cand);
    int32_t *seed_counts = k->seed_counts;
    for (int32_t l = 0; l < n_parts; l++) seed_counts[l] = 0;
    /* each seed run lies in one run of the mask (the seeds are above the mask's level): its blob */
    for (int32_t i = 0, j = 0; i < ns; i++) {
        while (k->run_y[j] < k->seed_y[i] || (k->run_y[j] == k->seed_y[i] && k->run_x1[j] < k->seed_x0[i])) j++;
        seed_counts[k->run_label[j]] += k->seed_x1[i] - k->seed_x0[i] + 1;
    }
    int32_t seeded = 0;
    for (int32_t l = 1; l < n_parts; l++) seeded += seed_counts[l] > 0;
    if (seeded == n_seeds) /* no blob holds two seeds: every blob is one contact */
        return measure_parts(k, level, k->run_y, k->run_x0, k->run_x1, k->run_label, nr, n_parts);
    /* the seeds: the strong cells, and the blobs without one, painted with their components' labels */
    int32_t nz = 0, *zy = k->part_y, *zx0 = k->part_x0, *zx1 = k->part_x1, *zl = k->part_label;
    for (int32_t i = 0, j = 0; i < nr || j < ns;) { /* merged in raster order */
        int take_seed = j < ns && (i >= nr || k->seed_y[j] < k->run_y[i]
                                   || (k->seed_y[j] == k->run_y[i] && k->seed_x0[j] < k->run_x0[i]));
        if (take_seed) {
            zy[nz] = k->seed_y[j];
            zx0[nz] = k->seed_x0[j];
            zx1[nz++] = k->seed_x1[j++];
        } else {
            if (!seed_counts[k->run_label[i]]) {
                zy[nz] = k->run_y[i];
                zx0[nz] = k->run_x0[i];
                zx1[nz++] = k->run_x1[i];
            }
            i++;
        }
    }
    ok_label_runs(zy, zx0, zx1, nz, zl, k->parent, k->order);
    int32_t *seed_img = k->seed_img, *nearest = k->nearest; /* seed_img is all 0 between frames */
    int32_t n_labels = 1;
    for (int32_t i = 0; i < nz; i++) {
        for (int32_t x = zx0[i]; x <= zx1[i]; x++) seed_img[(int64_t)zy[i] * bw + x] = zl[i];
        if (zl[i] >= n_labels) n_labels = zl[i] + 1;
    }
    ok_nearest_seed(seed_img, bh, bw, k->dist, nearest);
    for (int32_t i = 0; i < nz; i++) /* back to 0, cell by cell painted */
        memset(seed_img + (int64_t)zy[i] * bw + zx0[i], 0, (size_t)(zx1[i] - zx0[i] + 1) * sizeof(int32_t));
    /* the mask's runs cut where the nearest seed changes */
    int32_t np_ = 0;
    for (int32_t i = 0; i < nr; i++) {
        const int32_t *row = nearest + (int64_t)k->run_y[i] * bw;
        for (int32_t x = k->run_x0[i]; x <= k->run_x1[i]; x++) {
            int32_t a = x;
            while (x + 1 <= k->run_x1[i] && row[x + 1] == row[a]) x++;
            zy[np_] = k->run_y[i];
            zx0[np_] = a;
            zx1[np_] = x;
            zl[np_++] = row[a];
        }
    }
    return measure_parts(k, level, zy, zx0, zx1, zl, np_, n_labels);
}

/* The sum of the box's cells (the strength above the truncation level of a frame without contact). */
static double box_sum(const ok_kernel *k) {
    double total = 0.0;
    for (int32_t y = 0; y < k->box_h; y++) {
        const float *src = k->p.surface + (int64_t)(k->box_y + y) * k->p.n + k->box_x;
        double row = 0.0;
        for (int32_t x = 0; x < k->box_w; x++) row += src[x];
        total += row;
    }
    return total;
}

/* The runs of the box's cells above the truncation level (the mask) and above the split level. */
static void box_runs(ok_kernel *k, float split) {
    int32_t bw = k->box_w, bh = k->box_h, nr = 0, ns = 0;
    for (int32_t y = 0; y < bh; y++) {
        const float *row = k->p.surface + (int64_t)(k->box_y + y) * k->p.n + k->box_x;
        for (int32_t x = 0; x < bw; x++) {
            if (!(row[x] > 0.0f)) continue;
            int32_t a = x;
            while (x + 1 < bw && row[x + 1] > 0.0f) x++;
            k->run_y[nr] = y;
            k->run_x0[nr] = a;
            k->run_x1[nr++] = x;
            for (int32_t s = a; s <= x; s++) { /* the seed runs within it */
                if (!(row[s] > split)) continue;
                int32_t b = s;
                while (s + 1 <= x && row[s + 1] > split) s++;
                k->seed_y[ns] = y;
                k->seed_x0[ns] = b;
                k->seed_x1[ns++] = s;
            }
        }
    }
    k->n_runs = nr;
    k->n_seed_runs = ns;
}

int32_t ok_find(ok_kernel *k, float level) {
    const ok_plan *p = &k->p;
    int32_t bw = k->box_w, bh = k->box_h;
    int multi = p->max_contacts > 1;
    float peak = k->peak;
    if (multi) {
        double split = (double)k->trunc > p->split_fraction * peak ? (double)k->trunc : p->split_fraction * peak;
        box_runs(k, (float)split);
    }
    int32_t n_cand;
    if (!multi) {
        n_cand = measure(k, p->surface + (int64_t)k->box_y * p->n + k->box_x, bh, bw, p->n, peak, k->cells, level,
                         k->box_x, k->box_y, k->cand);
    } else {
        n_cand = split_blobs(k, level, peak);
    }
    k->n_candidates = n_cand;
    if (n_cand == 0) {
        k->clear_strength = box_sum(k) * p->cell_area_mm2;
        k->clear_area = k->cells * p->cell_area_mm2;
        return 0;
    }
    int32_t order[OK_MAX_CANDIDATES];
    for (int32_t i = 0; i < n_cand; i++) order[i] = i;
    order_decreasing(k->cand + OK_STRENGTH, order, n_cand, OK_FIELDS); /* strongest first, ties in order */
    int32_t out = n_cand < p->max_contacts ? n_cand : p->max_contacts;
    for (int32_t i = 0; i < out; i++) {
        double *c = p->contacts + (int64_t)i * OK_FIELDS;
        memcpy(c, k->cand + (int64_t)order[i] * OK_FIELDS, OK_FIELDS * sizeof(double));
        c[OK_DEPTH_MM] = c[OK_FORCE_N] = c[OK_CONFIDENCE] = NAN;
        c[OK_SHAPE] = -1.0;
        if (k->correct) ok_correct(k, c);
    }
    return out;
}

/* ---------------------------------------------------------------- steps 9, 10 (Pipeline._follow_light) */

/* GainCompensation.rest_means, or the means themselves: the light the baseline takes, into plan.rest. */
static void rest_light(ok_kernel *k) {
    const ok_plan *p = &k->p;
    if (!p->compensate_gain) {
        memcpy(p->rest, p->means, (size_t)p->n_fibers * sizeof(float));
        return;
    }
    float g = (float)k->gain;
    for (int32_t i = 0; i < p->n_fibers; i++) {
        float v = k->ratio[i] * p->level[i];
        v = v / g;
        p->rest[i] = v + p->black_level;
    }
}

/* Baseline._updated */
static void baseline_updated(ok_kernel *k) {
    const ok_plan *p = &k->p;
    for (int32_t i = 0; i < p->n_fibers; i++) {
        float v = p->baseline[i] - p->black_level;
        v = v > 1.0f ? v : 1.0f;
        p->level[i] = v;
        p->inv_level[i] = 1.0f / v;
    }
}

/* Baseline.track */
static void track(ok_kernel *k, int64_t now_ns, int64_t dt_ns, int32_t contact_ended, int64_t contact_end_ns) {
    const ok_plan *p = &k->p;
    int32_t nf = p->n_fibers;
    if (contact_ended && (double)(now_ns - contact_end_ns) < p->holdoff_ns) return;
    memcpy(k->sorted, p->signal, (size_t)nf * sizeof(float));
    float common = select_kth(k->sorted, nf, nf / 2);
    float most = 0.0f;
    for (int32_t i = 0; i < nf; i++) {
        float d = fabsf(p->signal[i] - common);
        if (d > most) most = d;
    }
    if ((double)most >= (double)k->off) return;
    double dt = (double)dt_ns < p->tau_ns ? (double)dt_ns : p->tau_ns;
    float alpha = (float)(1.0 - exp(-dt / p->tau_ns));
    rest_light(k);
    for (int32_t i = 0; i < nf; i++) {
        float diff = p->rest[i] - p->baseline[i];
        diff = diff * alpha;
        p->baseline[i] = p->baseline[i] + diff;
    }
    baseline_updated(k);
}

/* BrightFibers.check */
static int bright_check(ok_kernel *k, int64_t now_ns, int contact_free) {
    const ok_plan *p = &k->p;
    int32_t nf = p->n_fibers;
    double lowest;
    if (p->bright_from_common) {
        memcpy(k->sorted, p->signal, (size_t)nf * sizeof(float));
        k->common = select_kth(k->sorted, nf, nf / 2);
        float lo = k->sorted[0]; /* the selection left the lowest half before the median */
        for (int32_t i = 1; i < nf / 2; i++) if (k->sorted[i] < lo) lo = k->sorted[i];
        lowest = lo;
    } else {
        float lo = p->signal[0];
        for (int32_t i = 1; i < nf; i++) if (p->signal[i] < lo) lo = p->signal[i];
        lowest = lo;
    }
    if (lowest > k->common - (double)k->off) {
        k->bright_since_set = 0;
        return 0;
    }
    if (!k->bright_since_set) {
        k->bright_since_set = 1;
        k->bright_since_ns = now_ns;
    }
    if (!contact_free || (double)(now_ns - k->bright_since_ns) < p->bright_hold_ns) return 0;
    k->bright_since_set = 0;
    return 1;
}

void ok_follow(ok_kernel *k, int32_t n, int64_t now_ns, int64_t dt_ns) {
    const ok_plan *p = &k->p;
    if (n > 0) {
        k->in_contact = 1;
    } else if (k->in_contact) {
        k->in_contact = 0;
        k->contact_ended = 1;
        k->contact_end_ns = now_ns;
    }
    k->raise_pending = bright_check(k, now_ns, n == 0);
    if (k->raise_pending) {
        rest_light(k);
        return;
    }
    if (n == 0 && p->compensate_gain && !k->held) { /* GainCompensation.contact_free */
        k->reference = k->frame_gain;
        k->reference_ns = now_ns;
    }
    if (n == 0 && p->track_baseline && dt_ns > 0) track(k, now_ns, dt_ns, k->contact_ended, k->contact_end_ns);
}

void ok_reset_contact(ok_kernel *k) {
    k->in_contact = k->contact_ended = k->raise_pending = 0;
    k->bright_since_set = 0;
}

int32_t ok_check(ok_kernel *k, const uint8_t *frame) {
    const ok_plan *p = &k->p;
    int32_t n_sat = 0, n_bright = 0, nb = p->check_bytes;
    uint8_t sat = (uint8_t)p->check_saturated_level, dark = (uint8_t)p->check_dark_level;
    for (int32_t i = 0; i < p->check_pixels; i++) { /* a pixel counts when any of its bytes does */
        const int32_t *o = p->check_probe + (int64_t)i * nb;
        int s = 0, b = 0;
        for (int32_t j = 0; j < nb; j++) {
            uint8_t v = frame[o[j]];
            s |= v >= sat;
            b |= v > dark;
        }
        n_sat += s;
        n_bright += b;
    }
    k->saturated = 0;
    if (n_sat > p->check_saturated_fraction * p->check_pixels) return 2;
    if (n_bright < p->check_dark_fraction * p->check_pixels) return 1;
    k->saturated = n_sat > 0;
    return 0;
}

static int p_gated(const ok_kernel *k, float level) {
    return k->p.support_nbr && !(k->support_peak > level);
}

int32_t ok_frame(ok_kernel *k, const uint8_t *frame, int64_t now_ns, int64_t dt_ns, int means_ready) {
    if (!means_ready) ok_means(k, frame);
    int32_t n = 0;
    k->clear_strength = k->clear_area = 0.0;
    if (ok_surface(k, now_ns) > 0) {
        float level = k->in_contact ? k->off : k->on;
        /* neighbour support: a frame whose supported peak stays below the level has no contact */
        n = ok_find(k, p_gated(k, level) ? INFINITY : level);
    }
    ok_follow(k, n, now_ns, dt_ns);
    return n;
}

/* ---------------------------------------------------------------- the calibration models (ContactCorrector) */

/* Python's max(v, 0.0): v unless 0.0 > v (NaN stays NaN) */
static double max0(double v) { return 0.0 > v ? 0.0 : v; }

/* AxisMap.__call__: interpolation through the knots, linear beyond the ends, clipped at 0. */
static double axis_map(const ok_axis *a, double x) {
    const double *km = a->km, *kt = a->kt;
    int32_t n = a->k, j;
    if (isnan(x)) return NAN;
    if (x <= km[0]) {
        j = 0;
    } else if (x >= km[n - 1]) {
        j = n - 2;
    } else {
        int32_t lo = 0, hi = n; /* bisect_right(km, x) */
        while (lo < hi) {
            int32_t mid = (lo + hi) / 2;
            if (x < km[mid]) hi = mid;
            else lo = mid + 1;
        }
        j = lo - 1;
        if (x == km[j]) return max0(kt[j]);
    }
    double slope = (kt[j + 1] - kt[j]) / (km[j + 1] - km[j]);
    return max0(kt[j] + slope * (x - km[j]));
}

/* width_model.rim_rho2: min(r^2 / R^2, 1) as Python's min (NaN stays NaN) */
static double rim_rho2(double x, double y, double radius) {
    double v = (x * x + y * y) / (radius * radius);
    return 1.0 < v ? 1.0 : v;
}

/* depth_model.depth_feature of a raw contact (DEPTH_FEATURES order) */
static double depth_feature(const double *c, int32_t feature) {
    double width = 0.5 * (c[OK_MAJOR_MM] + c[OK_MINOR_MM]);
    switch (feature) {
    case 0: return width;
    case 1: return c[OK_STRENGTH];
    case 2: return c[OK_PEAK];
    case 3: return c[OK_AREA_MM2];
    case 4: return c[OK_STRENGTH] / c[OK_PEAK];
    case 5: return pow(c[OK_STRENGTH], 1.0) * width;
    case 6: return pow(c[OK_STRENGTH], 0.5) * width;
    case 7: return pow(c[OK_STRENGTH] / c[OK_PEAK], 1.0) * width;
    default: return NAN;
    }
}

/* RadialMonotoneMap.__call__ */
static double radial_map(const ok_radial_map *m, double feature, double x, double y) {
    double rho2 = rim_rho2(x, y, m->radius_mm), term = rho2;
    for (int32_t k = 1; k < m->power; k++)
        term *= rho2;
    double v = feature * (1.0 + m->radial * term);
    return isnan(v) ? NAN : axis_map(&m->curve, v);
}

/* ShapeClassifier.classify: the class index (-1: a used feature is NaN) and its confidence. */
static void classify(const ok_kernel *k, const double *features, double *shape, double *confidence) {
    const ok_models *m = &k->p.models;
    int32_t d = m->shape_d, K = m->shape_k, C = m->shape_c, kd = K * d;
    double z[64];
    double cap = m->shape_cap;
    for (int32_t j = 0; j < d; j++) {
        double x = features[m->shape_sel[j]], f;
        int32_t rule = m->shape_rule[j];
        if (isnan(x)) {
            *shape = -1.0;
            *confidence = NAN;
            return;
        }
        if (rule & 4) { /* q4: ln(min(max(x, 0), Q4_MAX) + floor), Python's min and max */
            double v = 0.0 > x ? 0.0 : x;
            v = m->shape_q4_max < v ? m->shape_q4_max : v;
            f = log(v + m->shape_q4_floor);
        } else if (rule & 1) { /* signed: symmetric log */
            double a = fabs(x);
            f = a >= cap ? 0.0 : (x > 0 ? cap - a : (x < 0 ? a - cap : 0.0));
        } else if (x == 0.0 && (rule & 2)) {
            f = cap;
        } else {
            double v = -cap > x ? -cap : x;
            f = cap < v ? cap : v;
        }
        z[j] = (f - m->shape_mean[j]) / m->shape_std[j];
    }
    z[d] = 1.0;
    double *y = k->shape_y, *ll = k->shape_ll;
    for (int32_t i = 0; i < kd; i++) y[i] = 0.0;
    for (int32_t j = 0; j <= d; j++) { /* y = z @ proj1 */
        const double *row = m->shape_proj1 + (int64_t)j * kd;
        for (int32_t i = 0; i < kd; i++) y[i] += z[j] * row[i];
    }
    double top = -INFINITY;
    for (int32_t c = 0; c < K; c++) { /* ll = (y * y) @ (block sums * -0.5) + const */
        double s = 0.0;
        for (int32_t i = c * d; i < (c + 1) * d; i++) s += (y[i] * y[i]) * -0.5;
        ll[c] = s + m->shape_const[c];
        if (ll[c] > top || c == 0) top = ll[c];
    }
    double p[64] = {0};
    for (int32_t c = 0; c < K; c++) { /* p = exp(ll - top) @ map1 */
        double e = exp(ll[c] - top);
        const double *row = m->shape_map1 + (int64_t)c * (C + 1);
        for (int32_t j = 0; j <= C; j++) p[j] += e * row[j];
    }
    int32_t best = 0;
    for (int32_t c = 1; c < C; c++)
        if (p[c] > p[best]) best = c;
    *shape = best;
    *confidence = p[best] / p[C];
}

void ok_correct(const ok_kernel *k, double *c) {
    const ok_models *m = &k->p.models;
    double x = c[OK_X_MM], y = c[OK_Y_MM];
    if (m->depth) { /* first: it reads the raw widths and position it was fitted on */
        c[OK_DEPTH_MM] = radial_map(&m->depth_map, depth_feature(c, m->depth_map.feature), x, y);
        c[OK_FORCE_N] = m->force ? radial_map(&m->force_map, depth_feature(c, m->force_map.feature), x, y) : NAN;
    }
    if (m->width) { /* before the centroid map: it reads the raw position */
        if (m->radial_major == 0.0 && m->radial_minor == 0.0) {
            c[OK_MAJOR_MM] = axis_map(&m->major, c[OK_MAJOR_MM]);
            c[OK_MINOR_MM] = axis_map(&m->minor, c[OK_MINOR_MM]);
        } else {
            double rho2 = rim_rho2(x, y, m->width_radius_mm);
            if (isnan(rho2)) rho2 = 0.0;
            c[OK_MAJOR_MM] = axis_map(&m->major, c[OK_MAJOR_MM] * (1.0 + m->radial_major * rho2));
            c[OK_MINOR_MM] = axis_map(&m->minor, c[OK_MINOR_MM] * (1.0 + m->radial_minor * rho2));
        }
    }
    if (m->cmap_n) { /* the nearest cell, rounded half to even as Python's round */
        int32_t n = m->cmap_n;
        double jj = nearbyint((x - m->cmap_x0) / m->cmap_step), ii = nearbyint((y - m->cmap_y0) / m->cmap_step);
        int32_t j = jj < 0 ? 0 : (jj > n - 1 ? n - 1 : (int32_t)jj);
        int32_t i = ii < 0 ? 0 : (ii > n - 1 ? n - 1 : (int32_t)ii);
        c[OK_X_MM] = x - (double)m->cmap_ex[(int64_t)i * n + j];
        c[OK_Y_MM] = y - (double)m->cmap_ey[(int64_t)i * n + j];
    }
    if (m->shape_d) classify(k, c + OK_HU0, &c[OK_SHAPE], &c[OK_CONFIDENCE]);
}
