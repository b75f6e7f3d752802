/* The fibers' vibration: a second-order high-pass per live fiber and the mean square of its output over
 * a contact's fibers, in units of the noise (optitac_edge/core/vibration.py is the reference and holds the
 * constants; this is its per-frame step, the same arithmetic). */
#ifndef OK_VIBRATION_H
#define OK_VIBRATION_H

#include <stdint.h>

#define OK_VIB_MAX_WINDOW 64

typedef struct {
    /* given */
    int32_t n;             /* live fibers */
    const int32_t *live;   /* (n,) their indices into signal */
    const float *signal;   /* (N,) the pipeline's signal buffer */
    float *x, *z1, *z2;    /* (n,) scratch and the filter's state */
    float *mask;           /* (n,) scratch: 1 where the fiber is above the truncation level */
    double cutoff_hz, rate_fraction, on_sigmas, quiet_tau_s, vibrating_tau_s;
    double period_s; /* the camera's nominal frame period the filter is designed for (0: the first interval) */
    int32_t window, learn_frames, min_fibers;
    /* state */
    int designed;
    float b0, b1, b2, a1, a2;
    double unit;
    int32_t learned, k;
    double ring[OK_VIB_MAX_WINDOW];
    double level, quiet;
    char vibrating, began; /* 0 or 1 (read as bools) */
} ok_vibration;

/* Start again: the filter from the next frame's signal, the noise learned again. */
void ok_vibration_reset(ok_vibration *v);

/* One frame of the signal; the level (NaN while the noise is learned), with v->vibrating and v->began. */
double ok_vibration_step(ok_vibration *v, float trunc, int64_t dt_ns);

#endif
