/* The kernel's vector unit, shared by its files: the AVX2 choice on x86-64 and the 4- and 8-lane float
 * types (GCC vector extensions: SSE2/AVX2 on x86-64, NEON on aarch64). */
#ifndef OK_SIMD_H
#define OK_SIMD_H

#include <stdint.h>
#include <string.h>

/* x86-64 (GCC, Linux): the widest loops have an AVX2 form beside the baseline one (SSE2, as NEON on
 * aarch64: four float32 lanes), chosen once at init where the CPU has AVX2. -DOK_NO_CLONES builds the
 * baseline alone (a 4-lane machine's instruction mix, as the Pi's). */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && defined(__linux__) && !defined(OK_NO_CLONES)
#define OK_AVX2 1
#define CLONES_AVX2 __attribute__((target_clones("avx2", "default")))
extern int ok_avx2; /* set by ok_kernel_init (frame_kernel.c) */
#else
#define OK_AVX2 0
#define CLONES_AVX2
#endif

#if defined(__GNUC__) || defined(__clang__)
/* Four float32 lanes: SSE2 on x86-64, NEON on aarch64 (both in their baseline), from the same code. */
typedef float v4f __attribute__((vector_size(16)));
typedef int32_t v4i __attribute__((vector_size(16)));
static inline v4f load4(const float *p) {
    v4f v;
    memcpy(&v, p, sizeof v); /* an unaligned load */
    return v;
}
#if OK_AVX2
typedef float v8f __attribute__((vector_size(32)));
#define LOAD8(dst, src) memcpy(&(dst), (src), sizeof(v8f))
#endif
#endif

/* The eight lanes of v added in one fixed tree (the same bits from one 8-lane vector or two 4-lane ones). */
#define SUM8(v) ((((v)[0] + (v)[1]) + ((v)[2] + (v)[3])) + (((v)[4] + (v)[5]) + ((v)[6] + (v)[7])))

#if defined(__GNUC__) || defined(__clang__)
#if defined(__aarch64__)
#include <arm_neon.h>
/* SUM8's tree over lo (lanes 0-3) and hi (4-7) in three pairwise adds (NEON faddp: each pair one rounded
 * float add, as the tree's), instead of six lane moves and seven adds. */
static inline float sum8_lanes(v4f lo, v4f hi) {
    float32x4_t t = vpaddq_f32((float32x4_t)lo, (float32x4_t)hi); /* 0+1, 2+3, 4+5, 6+7 */
    t = vpaddq_f32(t, t);                                          /* (0+1)+(2+3), (4+5)+(6+7), ... */
    return vpadds_f32(vget_low_f32(t));
}
#else
/* SUM8's tree over lo (lanes 0-3) and hi (4-7). */
static inline float sum8_lanes(v4f lo, v4f hi) {
    return ((lo[0] + lo[1]) + (lo[2] + lo[3])) + ((hi[0] + hi[1]) + (hi[2] + hi[3]));
}
#endif
#endif

#endif
