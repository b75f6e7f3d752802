/* The fibers' vibration, one frame at a time: see vibration.h and optitac_edge/core/vibration.py (the
 * reference: the same steps in the same order, in float32 for the filter and double for the sums). */
#include "vibration.h"

#include "simd.h"

#include <math.h>

#ifndef M_PI
#define M_PI 3.14159265358979323846
#endif

void ok_vibration_reset(ok_vibration *v) {
    v->designed = 0;
    v->unit = 0.0;
    v->learned = 0;
    v->k = 0;
    for (int32_t i = 0; i < v->window; i++) v->ring[i] = 0.0;
    v->level = NAN;
    v->quiet = 1.0;
    v->vibrating = v->began = 0;
}

/* the bilinear transform's second-order Butterworth high-pass, as butter2_highpass */
static void design(ok_vibration *v, double rate_hz) {
    double cutoff = v->cutoff_hz < v->rate_fraction * rate_hz ? v->cutoff_hz : v->rate_fraction * rate_hz;
    double k = tan(M_PI * cutoff / rate_hz);
    double norm = 1.0 / (1.0 + sqrt(2.0) * k + k * k);
    v->b0 = (float)norm;
    v->b1 = (float)(-2.0 * norm);
    v->b2 = (float)norm;
    v->a1 = (float)(2.0 * (k * k - 1.0) * norm);
    v->a2 = (float)((1.0 - sqrt(2.0) * k + k * k) * norm);
    float nb0 = (float)-norm;
    for (int32_t i = 0; i < v->n; i++) { /* at rest for this signal: a constant input gives 0 out */
        v->z1[i] = v->x[i] * nb0;
        v->z2[i] = v->x[i] * v->b2;
    }
    v->designed = 1;
}

static void learn(ok_vibration *v, double ms, int64_t dt_ns) {
    if (v->learned < v->learn_frames) {
        v->learned++;
        v->unit += (ms - v->unit) / v->learned;
    } else {
        double w = (double)dt_ns * 1e-9 / v->quiet_tau_s;
        v->unit += (ms - v->unit) * (w < 1.0 ? w : 1.0);
    }
}

static double judge(ok_vibration *v, double ratio, int32_t n_fibers, int64_t dt_ns) {
    int32_t w = v->window;
    if (isnan(v->level))
        for (int32_t i = 0; i < w; i++) v->ring[i] = ratio;
    v->ring[v->k] = ratio;
    v->k = (v->k + 1) % w;
    double sum = 0.0;
    for (int32_t i = 0; i < w; i++) sum += v->ring[i];
    double level = v->level = sum / w, quiet = v->quiet, tau;
    double excess = v->on_sigmas * sqrt(2.0 / ((double)n_fibers * w * 0.5));
    double top = quiet * (1.0 + excess); /* the on level; off below half its excess */
    if (v->vibrating) {
        if (level < quiet * (1.0 + 0.5 * excess)) v->vibrating = 0;
        tau = v->vibrating_tau_s;
    } else if (level > top) {
        v->vibrating = v->began = 1;
        tau = v->vibrating_tau_s;
    } else {
        tau = v->quiet_tau_s;
    }
    double rate = (double)dt_ns * 1e-9 / tau;
    v->quiet = quiet + ((level < top ? level : top) - quiet) * (rate < 1.0 ? rate : 1.0);
    return level;
}

double ok_vibration_step(ok_vibration *v, float trunc, int64_t dt_ns) {
    int32_t n = v->n, n4 = n & ~3;
    float *x = v->x, *z1 = v->z1, *z2 = v->z2, *mask = v->mask;
    for (int32_t i = 0; i < n; i++) x[i] = v->signal[v->live[i]];
    v->began = 0;
    if (!v->designed) {
        if (v->period_s > 0.0)
            design(v, 1.0 / v->period_s);
        else if (dt_ns > 0)
            design(v, 1e9 / (double)dt_ns);
        return v->level;
    }
    const float b0 = v->b0, b1 = v->b1, b2 = v->b2, a1 = v->a1, a2 = v->a2;
    /* the filter (direct form II transposed), four fibers at a time; x becomes the output, mask 1 where the
     * fiber is above the truncation level */
    const v4f vb0 = {b0, b0, b0, b0}, vb1 = {b1, b1, b1, b1}, vb2 = {b2, b2, b2, b2};
    const v4f va1 = {a1, a1, a1, a1}, va2 = {a2, a2, a2, a2}, vt = {trunc, trunc, trunc, trunc};
    const v4f one = {1.0f, 1.0f, 1.0f, 1.0f};
    v4f hsum = {0.0f, 0.0f, 0.0f, 0.0f};
    for (int32_t i = 0; i < n4; i += 4) {
        v4f xi = load4(x + i), h = xi * vb0 + load4(z1 + i);
        v4f n1 = (xi * vb1 + load4(z2 + i)) - h * va1, n2 = xi * vb2 - h * va2;
        v4f mk = (v4f)((v4i)(xi > vt) & (v4i)one);
        memcpy(z1 + i, &n1, sizeof n1);
        memcpy(z2 + i, &n2, sizeof n2);
        memcpy(x + i, &h, sizeof h);
        memcpy(mask + i, &mk, sizeof mk);
        hsum += h;
    }
    double mean = (double)hsum[0] + hsum[1] + hsum[2] + hsum[3];
    for (int32_t i = n4; i < n; i++) {
        float xi = x[i], h = xi * b0 + z1[i];
        z1[i] = (xi * b1 + z2[i]) - h * a1;
        z2[i] = xi * b2 - h * a2;
        x[i] = h;
        mask[i] = xi > trunc ? 1.0f : 0.0f;
        mean += h;
    }
    float m = (float)(mean / n);
    const v4f vm = {m, m, m, m};
    v4f tot4 = {0.0f, 0.0f, 0.0f, 0.0f}, on4 = tot4, cnt4 = tot4;
    for (int32_t i = 0; i < n4; i += 4) {
        v4f d = load4(x + i) - vm, sq = d * d, mk = load4(mask + i);
        tot4 += sq;
        on4 += sq * mk;
        cnt4 += mk;
    }
    double total = (double)tot4[0] + tot4[1] + tot4[2] + tot4[3];
    double on = (double)on4[0] + on4[1] + on4[2] + on4[3];
    int32_t n_on = (int32_t)(cnt4[0] + cnt4[1] + cnt4[2] + cnt4[3]);
    for (int32_t i = n4; i < n; i++) {
        float d = x[i] - m, sq = d * d;
        total += sq;
        if (mask[i] != 0.0f) {
            on += sq;
            n_on++;
        }
    }
    if (n - n_on >= v->min_fibers) learn(v, (total - on) / (n - n_on), dt_ns);
    if (v->learned < v->learn_frames) return v->level;
    if (n_on >= v->min_fibers) return judge(v, on / n_on / v->unit, n_on, dt_ns);
    return judge(v, total / n / v->unit, n, dt_ns);
}
