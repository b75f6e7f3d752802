/* Contact motion, one contact at a time: see motion.h and optitac_edge/core/motion.py (the reference: the
 * same sums in the same order, so the two agree to the last bit but for the compiler's choices). */
#include "motion.h"

#include <math.h>
#include <string.h>

void ok_motion_reset(ok_motion *m) {
    for (int32_t i = 0; i < OK_MOTION_MAX_TRACKS; i++) m->tracks[i].id = 0;
}


static void start(ok_motion *m, ok_track *track, int32_t id, int32_t frame) {
    memset(track, 0, sizeof *track);
    track->id = id;
    track->noise = m->prior;
    track->ax = track->ay = NAN;
    track->strength = m->prior_strength;
    track->slide_frame = -1;
    track->seen = frame;
}

ok_track *ok_motion_track(ok_motion *m, int32_t id, int touched, int32_t frame) {
    ok_track *free_slot = NULL;
    for (int32_t i = 0; i < OK_MOTION_MAX_TRACKS; i++) {
        ok_track *track = &m->tracks[i];
        if (track->id == id) {
            if (touched) start(m, track, id, frame);
            track->seen = frame;
            return track;
        }
        if (!free_slot && (track->id == 0 || track->seen != frame)) free_slot = track;
    }
    if (free_slot) start(m, free_slot, id, frame);
    return free_slot;
}

void ok_motion_forget(ok_motion *m, int32_t frame) {
    double prior = -1.0, strength = NAN;
    for (int32_t i = 0; i < OK_MOTION_MAX_TRACKS; i++) {
        ok_track *track = &m->tracks[i];
        if (track->id == 0 || track->seen == frame) continue;
        if (track->n >= m->window && track->noise > prior) {
            prior = track->noise;
            strength = track->strength;
        }
        track->id = 0;
    }
    if (prior >= 0.0) {
        m->prior = prior;
        m->prior_strength = strength;
    }
}

void ok_motion_step(ok_motion *m, ok_track *track, double x, double y, double strength, int32_t frame,
                    double t_s, ok_motion_out *out) {
    int32_t w = m->window, h = track->head;
    track->t[h] = t_s;
    track->x[h] = x;
    track->y[h] = y;
    track->s[h] = strength;
    track->head = (h + 1) % w;
    int32_t n = track->n = track->n < w ? track->n + 1 : w;
    if (n < 2) {
        out->vx = out->vy = NAN;
        out->sliding = 0;
        out->slide_frame = -1;
        track->ax = x;
        track->ay = y;
        return;
    }
    const double *ts = track->t, *xs = track->x, *ys = track->y;
    double st = 0.0, sx = 0.0, sy = 0.0, t_lo = ts[0], t_hi = ts[0];
    for (int32_t k = 0; k < n; k++) {
        st += ts[k];
        t_lo = ts[k] < t_lo ? ts[k] : t_lo;
        t_hi = ts[k] > t_hi ? ts[k] : t_hi;
    }
    for (int32_t k = 0; k < n; k++) sx += xs[k];
    for (int32_t k = 0; k < n; k++) sy += ys[k];
    if (t_hi - t_lo < m->min_span_fraction * (n - 1) * m->period_s) { /* bunched frame times: no velocity */
        out->vx = out->vy = NAN;
        out->sliding = track->sliding;
        out->slide_frame = track->slide_frame;
        return;
    }
    double tm = st / n, xm = sx / n, ym = sy / n;
    double stt = 0.0, stx = 0.0, sty = 0.0, sxx = 0.0, syy = 0.0;
    for (int32_t k = 0; k < n; k++) {
        double dt = ts[k] - tm, dx = xs[k] - xm, dy = ys[k] - ym;
        stt += dt * dt;
        stx += dt * dx;
        sty += dt * dy;
        sxx += dx * dx;
        syy += dy * dy;
    }
    if (!(stt > 0.0)) { /* frames with one time: no velocity */
        out->vx = out->vy = NAN;
        out->sliding = track->sliding;
        out->slide_frame = track->slide_frame;
        return;
    }
    double vx = stx / stt, vy = sty / stt;
    out->vx = vx;
    out->vy = vy;
    if (n < w) {
        track->ax = xm;
        track->ay = ym;
        out->sliding = 0;
        out->slide_frame = -1;
        return;
    }
    double speed = sqrt(vx * vx + vy * vy);
    /* a fainter contact's centroid is the noisier in proportion: the noise scaled by the strength it was
     * measured at (or the window's strongest) over the window's faintest */
    double weakest = track->s[0], strongest = track->s[0], noise = track->noise;
    for (int32_t k = 1; k < w; k++) {
        if (track->s[k] < weakest) weakest = track->s[k];
        if (track->s[k] > strongest) strongest = track->s[k];
    }
    if (track->strength > strongest) strongest = track->strength;
    double ratio = weakest > 0.0 ? strongest / weakest : strongest > 0.0 ? INFINITY : 1.0; /* 1: none known */
    if (!(ratio <= m->steady_ratio)) { /* pressed in or lifted: no slip judged, nothing learned */
        if (!track->sliding) {
            track->ax = xm;
            track->ay = ym;
        }
        out->sliding = track->sliding;
        out->slide_frame = track->slide_frame;
        return;
    }
    noise *= ratio;
    double level = m->slip_sigmas * noise / sqrt(stt);
    if (level < m->min_speed) level = m->min_speed;
    if (track->sliding) {
        if (speed < m->hold_fraction * level) {
            track->sliding = 0;
            track->slide_frame = -1;
            track->ax = xm;
            track->ay = ym;
        }
    } else {
        double dx = x - track->ax, dy = y - track->ay, shift = sqrt(dx * dx + dy * dy);
        double least = m->slip_sigmas * noise;
        if (least < m->min_shift) least = m->min_shift;
        if (speed > level && shift > least) {
            track->sliding = 1;
            track->slide_frame = frame;
        } else { /* held: the scatter about the line is its centroid noise; where it rests follows */
            double ss = sxx - vx * stx + syy - vy * sty;
            if (ss < 0.0) ss = 0.0;
            track->noise += m->noise_rate * (sqrt(ss / (2 * (w - 2))) - track->noise);
            track->strength = isnan(track->strength) ? strength
                                                     : track->strength + m->noise_rate * (strength - track->strength);
            track->ax += m->noise_rate * (xm - track->ax);
            track->ay += m->noise_rate * (ym - track->ay);
        }
    }
    out->sliding = track->sliding;
    out->slide_frame = track->slide_frame;
}
