/* Contact motion: each tracked contact's least-squares velocity over its last few centroids and its slip
 * state (optitac_edge/core/motion.py's ContactMotion is the reference and holds the constants; this is the
 * same step, in the same order, in double). */
#ifndef OK_MOTION_H
#define OK_MOTION_H

#include <stdint.h>

#define OK_MOTION_MAX_WINDOW 16
#define OK_MOTION_MAX_TRACKS 16

typedef struct {
    int32_t id; /* 0: free */
    double t[OK_MOTION_MAX_WINDOW], x[OK_MOTION_MAX_WINDOW], y[OK_MOTION_MAX_WINDOW], s[OK_MOTION_MAX_WINDOW];
    int32_t n, head;
    double noise, strength, ax, ay; /* strength: the contact's strength its noise was measured at (NaN) */
    int32_t sliding, slide_frame;
    int32_t seen; /* the frame it was last updated in */
} ok_track;

typedef struct {
    int32_t window;
    double slip_sigmas, min_speed, min_shift, hold_fraction, noise_rate, steady_ratio;
    double min_span_fraction, period_s; /* a window spanning less than fraction x (n - 1) periods: no velocity */
    double prior, prior_strength; /* the last full contact's noise and the strength it was measured at */
    ok_track tracks[OK_MOTION_MAX_TRACKS];
} ok_motion;

/* The motion of one contact: out[0..1] velocity (NaN: none), out[2] sliding, out[3] slide frame. */
typedef struct {
    double vx, vy;
    int32_t sliding, slide_frame;
} ok_motion_out;

void ok_motion_reset(ok_motion *m);
/* The track of contact `id` (a new one when it touched in `frame` or is not known); NULL when every track
 * is taken by a contact of this frame. */
ok_track *ok_motion_track(ok_motion *m, int32_t id, int touched, int32_t frame);
void ok_motion_step(ok_motion *m, ok_track *track, double x, double y, double strength, int32_t frame,
                    double t_s, ok_motion_out *out);
/* After a frame's contacts: forget the tracks not updated in `frame` (keeping the noise of a full one). */
void ok_motion_forget(ok_motion *m, int32_t frame);

#endif
