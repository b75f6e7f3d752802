/* The surface's gradients at the fibers as a sparse solve, K g = B v with K = C C^T in an envelope, instead
 * of the dense product (see gradient_solve.h and optitac_edge/core/gradient_solve.py). */
#include "gradient_solve.h"

#include <stdio.h>
#include <string.h>

#include "simd.h"

/* The gradient solve's indices and envelopes in range (the plan's arrays were sized by the caller). */
int ok_check_gradient_solve(const ok_plan *p, char *err, int err_len) {
    int32_t nf = p->n_fibers, m = 2 * nf;
    if (!p->tri_cols || !p->gs_diag || !p->gs_col_last
        || !p->gs_col_ptr || !p->gs_col_env || !p->gs_nbr_ptr || !p->gs_nbr || !p->gs_coef) {
        snprintf(err, err_len, "kernel plan: an incomplete gradient solve");
        return -1;
    }
    if (p->gs_col_ptr[0] != 0 || p->gs_nbr_ptr[0] != 0) {
        snprintf(err, err_len, "kernel plan: gradient solve offsets must start at 0");
        return -1;
    }
    for (int32_t r = 0; r < nf; r++)
        if (p->gs_fibers[r] < 0 || p->gs_fibers[r] >= nf) { snprintf(err, err_len, "kernel plan: gradient solve fiber out of range"); return -1; }
    for (int32_t q = 0; q < m; q++) {
        if (!(p->gs_diag[q] != 0.0f)
            || p->gs_col_last[q] <= q || p->gs_col_last[q] > m + OK_GS_PAD || (p->gs_col_last[q] - q - 1) % OK_GS_PAD
            || p->gs_col_ptr[q + 1] - p->gs_col_ptr[q] != p->gs_col_last[q] - q - 1) {
            snprintf(err, err_len, "kernel plan: gradient solve row %d out of range", q);
            return -1;
        }
    }
    for (int32_t i = 0; i < nf; i++)
        if (p->gs_nbr_ptr[i + 1] < p->gs_nbr_ptr[i]) { snprintf(err, err_len, "kernel plan: gradient solve neighbours out of order"); return -1; }
    for (int32_t e = 0; e < p->gs_nbr_ptr[nf]; e++)
        if (p->gs_nbr[e] < 0 || p->gs_nbr[e] >= nf) { snprintf(err, err_len, "kernel plan: gradient solve neighbour out of range"); return -1; }
    return 0;
}

/* y[i] -= s * a[i] for n a multiple of 8 (the envelopes are padded with zeros to it): no sum across
 * elements, so the same bits at every vector width (no contraction). */
static inline __attribute__((always_inline)) void axpy8_neg(float *restrict y, float s, const float *restrict a,
                                                            int64_t n) {
#if defined(__GNUC__) || defined(__clang__)
    const v4f s4 = {s, s, s, s};
    for (int64_t i = 0; i < n; i += 8) {
        v4f y0 = load4(y + i) - s4 * load4(a + i), y1 = load4(y + i + 4) - s4 * load4(a + i + 4);
        memcpy(y + i, &y0, sizeof y0);
        memcpy(y + i + 4, &y1, sizeof y1);
    }
#else
    for (int64_t i = 0; i < n; i++) y[i] -= s * a[i];
#endif
}

/* sum a[i] * x[i] for n a multiple of 8: lane l (of eight) sums the elements i = l mod 8 in order, the lanes
 * added in SUM8's tree: the same bits at every vector width. */
static inline __attribute__((always_inline)) float dot8(const float *restrict a, const float *restrict x, int64_t n) {
#if defined(__GNUC__) || defined(__clang__)
    v4f lo = {0.0f, 0.0f, 0.0f, 0.0f}, hi = {0.0f, 0.0f, 0.0f, 0.0f};
    for (int64_t i = 0; i < n; i += 8) {
        lo += load4(a + i) * load4(x + i);
        hi += load4(a + i + 4) * load4(x + i + 4);
    }
    return sum8_lanes(lo, hi);
#else
    float l[8] = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    for (int64_t i = 0; i < n; i += 8)
        for (int j = 0; j < 8; j++) l[j] += a[i + j] * x[i + j];
    return ((l[0] + l[1]) + (l[2] + l[3])) + ((l[4] + l[5]) + (l[6] + l[7]));
#endif
}

/* The two triangular solves C z = y (column by column, axpys down each column) and C^T x = z (each x[q]
 * from the same column as a dot product with the x already found), in place on y: the factor is read by
 * columns only, so a frame reads it once (the second pass finds it in the caches). */
#define GS_SOLVES(AXPY, DOT)                                                                                  \
    do {                                                                                                      \
        for (int32_t q = 0; q < m; q++) { /* C z = y, column by column */                                    \
            float yq = y[q] / p->gs_diag[q];                                                                  \
            y[q] = yq;                                                                                        \
            AXPY(y + q + 1, yq, p->gs_col_env + p->gs_col_ptr[q], p->gs_col_last[q] - q - 1);                 \
        }                                                                                                     \
        for (int32_t q = m - 1; q >= 0; q--) { /* C^T x = z: x[q] = (z[q] - C[q+1:, q] . x[q+1:]) / C[q, q] */ \
            float s = DOT(p->gs_col_env + p->gs_col_ptr[q], y + q + 1, p->gs_col_last[q] - q - 1);           \
            y[q] = (y[q] - s) / p->gs_diag[q];                                                                \
        }                                                                                                     \
    } while (0)

static void gs_solves4(const ok_plan *p, float *restrict y, int32_t m) { GS_SOLVES(axpy8_neg, dot8); }

#if OK_AVX2
__attribute__((target("avx2"), always_inline)) static inline void axpy8_neg_avx2(float *restrict y, float s,
                                                                                 const float *restrict a, int64_t n) {
    const v8f s8 = {s, s, s, s, s, s, s, s};
    int64_t i = 0;
    for (; i + 16 <= n; i += 16) { /* two vectors a step: half the loop's own instructions */
        v8f y0, y1, a0, a1;
        LOAD8(y0, y + i);
        LOAD8(a0, a + i);
        LOAD8(y1, y + i + 8);
        LOAD8(a1, a + i + 8);
        y0 -= s8 * a0;
        y1 -= s8 * a1;
        memcpy(y + i, &y0, sizeof y0);
        memcpy(y + i + 8, &y1, sizeof y1);
    }
    if (i < n) {
        v8f yv, av;
        LOAD8(yv, y + i);
        LOAD8(av, a + i);
        yv -= s8 * av;
        memcpy(y + i, &yv, sizeof yv);
    }
}

__attribute__((target("avx2"), always_inline)) static inline float dot8_avx2(const float *restrict a,
                                                                            const float *restrict x, int64_t n) {
    v8f acc = {0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    for (int64_t i = 0; i < n; i += 8) {
        v8f av, xv;
        LOAD8(av, a + i);
        LOAD8(xv, x + i);
        acc += av * xv;
    }
    return SUM8(acc);
}

__attribute__((target("avx2"))) static void gs_solves8(const ok_plan *p, float *restrict y, int32_t m) {
    GS_SOLVES(axpy8_neg_avx2, dot8_avx2);
}
#endif

/* The gradients at the fibers, g (2N: d/dx then d/dy), of the values v (N) as K g = B v solved with
 * K = C C^T (optitac_edge/core/gradient_solve.py, whose solve_gradients computes the same in the same
 * order). y: the unknowns in the factor's order (fiber gs_fibers[r]'s d/dx at 2 r, d/dy at 2 r + 1), with
 * OK_GS_PAD zeros either side for the padded rows and columns. */
#if OK_AVX2
#include <immintrin.h>
/* The right side of eight fibers at a time (gs_fibers[r .. r + 7]) where none has more than six neighbours:
 * each lane the scalar loop's multiplies and adds in its order for its own neighbours (the same bits), the
 * lanes of a fiber with fewer left as they are (masked gathers: nothing past a fiber's neighbours is read).
 * Returns the first fiber (rank) it did not do; y as ok_gradient_solve's. */
__attribute__((target("avx2"))) static int32_t right_side8(const ok_plan *p, const float *v, float *restrict y,
                                                          int32_t r) {
    const __m256i seven = _mm256_set1_epi32(7);
    int32_t nf = p->n_fibers;
    for (; r + 8 <= nf; r += 8) {
        __m256i fib = _mm256_loadu_si256((const __m256i *)(p->gs_fibers + r));
        __m256i e0 = _mm256_i32gather_epi32(p->gs_nbr_ptr, fib, 4);
        __m256i ne = _mm256_sub_epi32(_mm256_i32gather_epi32(p->gs_nbr_ptr + 1, fib, 4), e0);
        if (_mm256_movemask_epi8(_mm256_cmpgt_epi32(seven, ne)) != -1) break; /* a fiber of 7 or more */
        __m256 vi = _mm256_i32gather_ps(v, fib, 4), sx = _mm256_setzero_ps(), sy = _mm256_setzero_ps();
        __m256i c0 = _mm256_add_epi32(e0, e0); /* the coefficients of edge e0: 2 e0, 2 e0 + 1 */
        for (int e = 0; e < 6; e++) {
            __m256i in = _mm256_cmpgt_epi32(ne, _mm256_set1_epi32(e)); /* the lanes with an edge e */
            __m256 inf = _mm256_castsi256_ps(in);
            __m256i nb = _mm256_mask_i32gather_epi32(_mm256_setzero_si256(), p->gs_nbr + e, e0, in, 4);
            __m256 d = _mm256_sub_ps(_mm256_mask_i32gather_ps(vi, v, nb, inf, 4), vi);
            __m256 cx = _mm256_mask_i32gather_ps(_mm256_setzero_ps(), p->gs_coef + 2 * e, c0, inf, 4);
            __m256 cy = _mm256_mask_i32gather_ps(_mm256_setzero_ps(), p->gs_coef + 2 * e + 1, c0, inf, 4);
            sx = _mm256_blendv_ps(sx, _mm256_add_ps(sx, _mm256_mul_ps(cx, d)), inf);
            sy = _mm256_blendv_ps(sy, _mm256_add_ps(sy, _mm256_mul_ps(cy, d)), inf);
        }
        __m256 lo = _mm256_unpacklo_ps(sx, sy), hi = _mm256_unpackhi_ps(sx, sy); /* x0 y0 x1 y1 | x4 y4 x5 y5 */
        _mm256_storeu_ps(y + 2 * r, _mm256_permute2f128_ps(lo, hi, 0x20));
        _mm256_storeu_ps(y + 2 * r + 8, _mm256_permute2f128_ps(lo, hi, 0x31));
    }
    return r;
}
#endif

void ok_gradient_solve(const ok_plan *p, const float *v, float *restrict y, float *restrict g) {
    int32_t nf = p->n_fibers, m = 2 * nf;
    for (int32_t r = 0; r < nf; r++) { /* the right side */
#if OK_AVX2
        if (ok_avx2 && (r & 7) == 0) { /* eight inner fibers at a time where they are */
            r = right_side8(p, v, y, r);
            if (r >= nf) break;
        }
#endif
        int32_t i = p->gs_fibers[r], e0 = p->gs_nbr_ptr[i], ne = p->gs_nbr_ptr[i + 1] - e0;
        const int32_t *nb = p->gs_nbr + e0;
        const float *c = p->gs_coef + 2 * (int64_t)e0;
        float sx = 0.0f, sy = 0.0f, vi = v[i];
        if (ne == 6) { /* a fiber inside the array: a constant count, which the compiler writes out */
            for (int32_t e = 0; e < 6; e++) {
                float d = v[nb[e]] - vi;
                sx += c[2 * e] * d;
                sy += c[2 * e + 1] * d;
            }
        } else {
            for (int32_t e = 0; e < ne; e++) {
                float d = v[nb[e]] - vi;
                sx += c[2 * e] * d;
                sy += c[2 * e + 1] * d;
            }
        }
        y[2 * r] = sx;
        y[2 * r + 1] = sy;
    }
#if OK_AVX2
    if (ok_avx2) gs_solves8(p, y, m);
    else gs_solves4(p, y, m);
#else
    gs_solves4(p, y, m);
#endif
    for (int32_t r = 0; r < nf; r++) {
        int32_t i = p->gs_fibers[r];
        g[i] = y[2 * r];
        g[nf + i] = y[2 * r + 1];
    }
}
