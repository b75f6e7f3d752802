/* optitac_edge.core._frame_kernel: the CPython face of frame_kernel.c.
 *
 * Kernel(plan) takes a dict of numpy arrays and numbers (optitac_edge/core/compiled.py builds it from
 * a Pipeline's parts, sharing their buffers), checks every array's type and size, keeps the arrays
 * alive, and runs a frame with the GIL released (several sensors on several cores).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>

#include "frame_kernel.h"

int ok_add_vibration_type(PyObject *module); /* vibration_type.c */
int ok_add_motion_type(PyObject *module);    /* motion_type.c */

#define MAX_BUFFERS 64

/* The names of a contact's fields (frame_kernel.h's enum), in order: the module's FIELD_NAMES. */
static const char *const field_names[] = {"strength", "x_mm", "y_mm", "major_mm", "minor_mm", "angle_deg",
                                          "area_mm2", "peak", "hu0", "hu1", "hu2", "hu3", "hu4", "hu5", "hu6",
                                          "q4", "depth_mm", "force_n", "shape", "confidence"};
_Static_assert(sizeof field_names / sizeof field_names[0] == OK_FIELDS, "a name for every contact field");

typedef struct {
    PyObject_HEAD
    ok_kernel k;
    int initialised;
    Py_ssize_t frame_bytes;
    Py_buffer bufs[MAX_BUFFERS];
    int n_bufs;
    int busy; /* a frame runs without the GIL: set and read with it held, so one thread at a time */
} KernelObject;

/* ---------------------------------------------------------------- the plan */

/* The keys the plan's reading looked up and found (Kernel_init runs with the GIL held: one at a time); a
 * key of the plan outside them is refused (a misspelt or stale key would otherwise be ignored). */
#define MAX_PLAN_KEYS 256
#define MAX_PLAN_KEY 64
static char plan_read[MAX_PLAN_KEYS][MAX_PLAN_KEY]; /* copies: some names are built on the caller's stack */
static int n_plan_read;

static PyObject *plan_item(PyObject *plan, const char *name, int optional) {
    PyObject *v = PyDict_GetItemString(plan, name); /* borrowed */
    if (!v && !optional) PyErr_Format(PyExc_KeyError, "kernel plan: missing %s", name);
    if (v && n_plan_read < MAX_PLAN_KEYS) snprintf(plan_read[n_plan_read++], MAX_PLAN_KEY, "%s", name);
    return v;
}

/* 0 when every key of the plan was read; else -1 with KeyError naming the first one that was not. */
static int plan_all_read(PyObject *plan) {
    PyObject *key, *value;
    Py_ssize_t pos = 0;
    while (PyDict_Next(plan, &pos, &key, &value)) {
        const char *name = PyUnicode_Check(key) ? PyUnicode_AsUTF8(key) : NULL;
        if (!name) {
            PyErr_Clear();
            PyErr_SetString(PyExc_KeyError, "kernel plan: a key that is not a string");
            return -1;
        }
        int known = 0;
        for (int i = 0; i < n_plan_read && !known; i++) known = strcmp(plan_read[i], name) == 0;
        if (!known) {
            PyErr_Format(PyExc_KeyError, "kernel plan: unknown key %s", name);
            return -1;
        }
    }
    return 0;
}

/* A C-contiguous array of `plan[name]` of items of `itemsize` bytes whose format is one of `kinds`,
 * with at least `min_items` items; NULL (no error) when optional and absent or None. */
static void *plan_array(KernelObject *self, PyObject *plan, const char *name, const char *kinds, Py_ssize_t itemsize,
                        Py_ssize_t min_items, int writable, int optional, Py_ssize_t *n_items) {
    PyObject *v = plan_item(plan, name, optional);
    if (!v || v == Py_None) return NULL;
    if (self->n_bufs >= MAX_BUFFERS) {
        PyErr_SetString(PyExc_RuntimeError, "kernel plan: too many arrays");
        return NULL;
    }
    Py_buffer *b = &self->bufs[self->n_bufs];
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(v, b, flags) < 0) {
        PyErr_Format(PyExc_ValueError, "kernel plan: %s is not a %scontiguous array", name, writable ? "writable " : "");
        return NULL;
    }
    self->n_bufs++;
    const char *fmt = b->format ? b->format : "B";
    char kind = fmt[strlen(fmt) - 1];
    if (b->itemsize != itemsize || !strchr(kinds, kind) || b->len / itemsize < min_items) {
        PyErr_Format(PyExc_ValueError, "kernel plan: %s must hold at least %zd items of %zd bytes ('%s'), got %zd of %zd ('%s')",
                     name, min_items, itemsize, kinds, b->len / b->itemsize, b->itemsize, fmt);
        return NULL;
    }
    if (n_items) *n_items = b->len / itemsize;
    return b->buf;
}

static int plan_double(PyObject *plan, const char *name, double *out) {
    PyObject *v = plan_item(plan, name, 0);
    if (!v) return -1;
    *out = PyFloat_AsDouble(v);
    return (*out == -1.0 && PyErr_Occurred()) ? -1 : 0;
}

static int plan_int(PyObject *plan, const char *name, long long lo, long long hi, long long *out) {
    PyObject *v = plan_item(plan, name, 0);
    if (!v) return -1;
    *out = PyLong_AsLongLong(v);
    if (*out == -1 && PyErr_Occurred()) return -1;
    if (*out < lo || *out > hi) {
        PyErr_Format(PyExc_ValueError, "kernel plan: %s = %lld outside %lld..%lld", name, *out, lo, hi);
        return -1;
    }
    return 0;
}

#define F32 "f"
#define F64 "d"
#define I32 "i"
#define I64 "lq"

/* An AxisMap's knots plan[prefix + "_km"], [prefix + "_kt"] (float64, same length >= 2). */
static int plan_axis(KernelObject *self, PyObject *plan, const char *prefix, ok_axis *a) {
    char km[64], kt[64];
    snprintf(km, sizeof km, "%s_km", prefix);
    snprintf(kt, sizeof kt, "%s_kt", prefix);
    Py_ssize_t n1 = 0, n2 = 0;
    a->km = plan_array(self, plan, km, F64, 8, 2, 0, 0, &n1);
    if (!a->km) return -1;
    a->kt = plan_array(self, plan, kt, F64, 8, n1, 0, 0, &n2);
    if (!a->kt) return -1;
    for (Py_ssize_t i = 1; i < n1; i++)
        if (!(a->km[i] > a->km[i - 1])) {
            PyErr_Format(PyExc_ValueError, "kernel plan: %s must increase", km);
            return -1;
        }
    a->k = (int32_t)n1;
    return 0;
}

static int plan_radial(KernelObject *self, PyObject *plan, const char *prefix, ok_radial_map *m) {
    char name[64];
    long long v;
    snprintf(name, sizeof name, "%s_feature", prefix);
    if (plan_int(plan, name, 0, 7, &v) < 0) return -1;
    m->feature = (int32_t)v;
    snprintf(name, sizeof name, "%s_power", prefix);
    if (plan_int(plan, name, 1, 4, &v) < 0) return -1;
    m->power = (int32_t)v;
    snprintf(name, sizeof name, "%s_radial", prefix);
    if (plan_double(plan, name, &m->radial) < 0) return -1;
    snprintf(name, sizeof name, "%s_radius_mm", prefix);
    if (plan_double(plan, name, &m->radius_mm) < 0) return -1;
    return plan_axis(self, plan, prefix, &m->curve);
}

/* The calibration models, each present when its first key is in the plan. */
static int plan_models(KernelObject *self, PyObject *plan, ok_plan *p) {
    ok_models *m = &p->models;
    long long v;
    if (PyDict_GetItemString(plan, "cmap_n")) {
        if (plan_int(plan, "cmap_n", 2, 1 << 15, &v) < 0) return -1;
        m->cmap_n = (int32_t)v;
        if (plan_double(plan, "cmap_x0", &m->cmap_x0) < 0 || plan_double(plan, "cmap_y0", &m->cmap_y0) < 0
            || plan_double(plan, "cmap_step", &m->cmap_step) < 0)
            return -1;
        Py_ssize_t cells = (Py_ssize_t)v * v;
        if (!(m->cmap_ex = plan_array(self, plan, "cmap_ex", F32, 4, cells, 0, 0, NULL))) return -1;
        if (!(m->cmap_ey = plan_array(self, plan, "cmap_ey", F32, 4, cells, 0, 0, NULL))) return -1;
    }
    if (PyDict_GetItemString(plan, "width_major_km")) {
        m->width = 1;
        if (plan_axis(self, plan, "width_major", &m->major) < 0 || plan_axis(self, plan, "width_minor", &m->minor) < 0
            || plan_double(plan, "width_radial_major", &m->radial_major) < 0
            || plan_double(plan, "width_radial_minor", &m->radial_minor) < 0
            || plan_double(plan, "width_radius_mm", &m->width_radius_mm) < 0)
            return -1;
    }
    if (PyDict_GetItemString(plan, "depth_km")) {
        m->depth = 1;
        if (plan_radial(self, plan, "depth", &m->depth_map) < 0) return -1;
        if (PyDict_GetItemString(plan, "force_km")) {
            m->force = 1;
            if (plan_radial(self, plan, "force", &m->force_map) < 0) return -1;
        }
    }
    if (PyDict_GetItemString(plan, "shape_d")) {
        if (plan_int(plan, "shape_d", 1, 63, &v) < 0) return -1;
        m->shape_d = (int32_t)v;
        if (plan_int(plan, "shape_k", 1, 1 << 12, &v) < 0) return -1;
        m->shape_k = (int32_t)v;
        if (plan_int(plan, "shape_c", 1, 63, &v) < 0) return -1;
        m->shape_c = (int32_t)v;
        Py_ssize_t d = m->shape_d, K = m->shape_k, C = m->shape_c, n_sel = 0;
        if (!(m->shape_sel = plan_array(self, plan, "shape_sel", I32, 4, d, 0, 0, &n_sel))) return -1;
        for (Py_ssize_t j = 0; j < d; j++)
            if (m->shape_sel[j] < 0 || m->shape_sel[j] >= 8) {
                PyErr_SetString(PyExc_ValueError, "kernel plan: shape_sel outside the 8 features");
                return -1;
            }
        if (!(m->shape_rule = plan_array(self, plan, "shape_rule", I32, 4, d, 0, 0, NULL))) return -1;
        if (!(m->shape_mean = plan_array(self, plan, "shape_mean", F64, 8, d, 0, 0, NULL))) return -1;
        if (!(m->shape_std = plan_array(self, plan, "shape_std", F64, 8, d, 0, 0, NULL))) return -1;
        if (!(m->shape_proj1 = plan_array(self, plan, "shape_proj1", F64, 8, (d + 1) * K * d, 0, 0, NULL))) return -1;
        if (!(m->shape_const = plan_array(self, plan, "shape_const", F64, 8, K, 0, 0, NULL))) return -1;
        if (!(m->shape_map1 = plan_array(self, plan, "shape_map1", F64, 8, K * (C + 1), 0, 0, NULL))) return -1;
        if (plan_double(plan, "shape_cap", &m->shape_cap) < 0 || plan_double(plan, "shape_q4_floor", &m->shape_q4_floor) < 0
            || plan_double(plan, "shape_q4_max", &m->shape_q4_max) < 0)
            return -1;
    }
    return 0;
}

/* The gradient solve (optitac_edge/core/gradient_solve.py), present when "gs_fibers" is in the plan: every
 * array sized here, the offsets' ends against the envelopes; the rest is checked by ok_kernel_init. */
static int plan_gradient_solve(KernelObject *self, PyObject *plan, ok_plan *p) {
    if (!PyDict_GetItemString(plan, "gs_fibers")) return 0;
    Py_ssize_t nf = p->n_fibers, m = 2 * nf, n_col = 0, n_nbr = 0;
    if (!(p->gs_fibers = plan_array(self, plan, "gs_fibers", I32, 4, nf, 0, 0, NULL))) return -1;
    if (!(p->gs_diag = plan_array(self, plan, "gs_diag", F32, 4, m, 0, 0, NULL))) return -1;
    if (!(p->gs_col_last = plan_array(self, plan, "gs_col_last", I32, 4, m, 0, 0, NULL))) return -1;
    if (!(p->gs_col_ptr = plan_array(self, plan, "gs_col_ptr", I64, 8, m + 1, 0, 0, NULL))) return -1;
    if (!(p->gs_col_env = plan_array(self, plan, "gs_col_env", F32, 4, 0, 0, 0, &n_col))) return -1;
    if (!(p->gs_nbr_ptr = plan_array(self, plan, "gs_nbr_ptr", I32, 4, nf + 1, 0, 0, NULL))) return -1;
    if (!(p->gs_nbr = plan_array(self, plan, "gs_nbr", I32, 4, 0, 0, 0, &n_nbr))) return -1;
    if (!(p->gs_coef = plan_array(self, plan, "gs_coef", F32, 4, 2 * n_nbr, 0, 0, NULL))) return -1;
    if (p->gs_col_ptr[m] != n_col || p->gs_nbr_ptr[nf] != n_nbr) {
        PyErr_SetString(PyExc_ValueError, "kernel plan: the gradient solve's offsets do not end at its arrays' sizes");
        return -1;
    }
    return 0;
}

static int Kernel_init(KernelObject *self, PyObject *args, PyObject *kwds) {
    PyObject *plan;
    static char *kwlist[] = {"plan", NULL};
    if (self->initialised) {
        PyErr_SetString(PyExc_RuntimeError, "Kernel is initialised once");
        return -1;
    }
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "O!", kwlist, &PyDict_Type, &plan)) return -1;
    ok_plan p;
    memset(&p, 0, sizeof p);
    n_plan_read = 0;
    long long v;
    double d;
#define INT(field, name, lo, hi) do { if (plan_int(plan, name, lo, hi, &v) < 0) return -1; p.field = (int32_t)v; } while (0)
#define DBL(field, name) do { if (plan_double(plan, name, &d) < 0) return -1; p.field = d; } while (0)
    INT(n_fibers, "n_fibers", 1, 1 << 20);
    INT(rgb, "rgb", 0, 1);
    INT(n, "n", 2, 4096);
    INT(relative, "relative", 0, 1);
    INT(compensate_gain, "compensate_gain", 0, 1);
    INT(track_baseline, "track_baseline", 0, 1);
    INT(bright_from_common, "bright_from_common", 0, 1);
    INT(max_contacts, "max_contacts", 1, OK_MAX_CANDIDATES);
    if (plan_int(plan, "frame_pixels", 1, (long long)1 << 40, &v) < 0) return -1;
    p.frame_pixels = v;
    if (plan_int(plan, "frame_bytes", 1, (long long)1 << 42, &v) < 0) return -1;
    self->frame_bytes = (Py_ssize_t)v;
    if (v < p.frame_pixels * (p.rgb ? 3 : 1)) { /* the kernel reads every pixel (and channel) of a frame */
        PyErr_Format(PyExc_ValueError, "kernel plan: frame_bytes %lld holds fewer than the %lld bytes of "
                     "frame_pixels %lld", v, (long long)(p.frame_pixels * (p.rgb ? 3 : 1)), (long long)p.frame_pixels);
        return -1;
    }
    DBL(black_level, "black_level");
    DBL(gain_rate_per_ns, "gain_rate_per_ns");
    DBL(tau_ns, "tau_ns");
    DBL(holdoff_ns, "holdoff_ns");
    DBL(bright_hold_ns, "bright_hold_ns");
    DBL(x0_mm, "x0_mm");
    DBL(y0_mm, "y0_mm");
    DBL(step_mm, "step_mm");
    DBL(cell_area_mm2, "cell_area_mm2");
    DBL(min_area_mm2, "min_area_mm2");
    DBL(min_cells, "min_cells");
    DBL(peak_fraction, "peak_fraction");
    DBL(shape_fraction, "shape_fraction");
    DBL(split_fraction, "split_fraction");
    Py_ssize_t nf = p.n_fibers, cells = (Py_ssize_t)p.n * p.n, count;
    p.pixel_start = plan_array(self, plan, "pixel_start", I64, 8, nf + 1, 0, 0, &count);
    if (!p.pixel_start) return -1;
    p.pixel_index = plan_array(self, plan, "pixel_index", I32, 4, p.pixel_start[nf], 0, 0, NULL);
    if (!p.pixel_index) return -1;
    if (p.pixel_start[0] != 0) {
        PyErr_SetString(PyExc_ValueError, "kernel plan: pixel_start[0] must be 0");
        return -1;
    }
#define ARR(field, type, name, kinds, size, min, writable)                                  \
    do {                                                                                  \
        p.field = (type)plan_array(self, plan, name, kinds, size, min, writable, 0, NULL); \
        if (!p.field) return -1;                                                          \
    } while (0)
#define OPT(field, type, name, kinds, size, min, count_out)                                      \
    do {                                                                                       \
        p.field = (type)plan_array(self, plan, name, kinds, size, min, 0, 1, count_out);       \
        if (!p.field && PyErr_Occurred()) return -1;                                           \
    } while (0)
    ARR(inv_count, const float *, "inv_count", F32, 4, nf, 0);
    OPT(rgb_weights, const int32_t *, "rgb_weights", I32, 4, 3, NULL);
    if (p.rgb_weights && (p.rgb_weights[0] < 0 || p.rgb_weights[1] < 0 || p.rgb_weights[2] < 0
                          || p.rgb_weights[0] + p.rgb_weights[1] + p.rgb_weights[2] != 32768)) {
        PyErr_SetString(PyExc_ValueError, "kernel plan: rgb_weights must be 3 weights >= 0 summing to 32768");
        return -1;
    }
    Py_ssize_t n_dead = 0, n_live = 0, n_rows = 0;
    OPT(dead, const int32_t *, "dead", I32, 4, 0, &n_dead);
    OPT(live, const int32_t *, "live", I32, 4, 0, &n_live);
    p.n_dead = p.dead ? (int32_t)n_dead : 0;
    p.n_live = p.live ? (int32_t)n_live : 0;
    if (p.compensate_gain && p.n_live < 1) {
        PyErr_SetString(PyExc_ValueError, "kernel plan: the gain needs live fibers");
        return -1;
    }
    ARR(means, float *, "means", F32, 4, nf, 1);
    ARR(signal, float *, "signal", F32, 4, nf, 1);
    ARR(surface, float *, "surface", F32, 4, cells, 1);
    ARR(baseline, float *, "baseline", F32, 4, nf, 1);
    ARR(level, float *, "level", F32, 4, nf, 1);
    ARR(inv_level, float *, "inv_level", F32, 4, nf, 1);
    OPT(band, const float *, "band", F32, 4, 2 * nf, NULL);
    OPT(support_nbr, const int32_t *, "support_nbr", I32, 4, 6 * nf, NULL);
    for (Py_ssize_t i = 0; p.support_nbr && i < 6 * nf; i++)
        if (p.support_nbr[i] < -1 || p.support_nbr[i] >= nf) {
            PyErr_SetString(PyExc_ValueError, "kernel plan: support_nbr outside the fibers");
            return -1;
        }
    ARR(rest, float *, "rest", F32, 4, nf, 1);
    ARR(contacts, double *, "contacts", F64, 8, (Py_ssize_t)p.max_contacts * OK_FIELDS, 1);
    OPT(dense, const float *, "dense", F32, 4, cells * nf, NULL);
    OPT(tri_cols, const int32_t *, "tri_cols", I32, 4, 0, &count);
    if (p.tri_cols) {
        INT(n_tri, "n_tri", 0, 1 << 26);
        INT(width, "width", 1, 1 << 26);
        INT(n_value_terms, "n_value_terms", 0, 3);
        Py_ssize_t T = p.n_tri, P = p.width;
        if (count < T * OK_CELL_TERMS) {
            PyErr_SetString(PyExc_ValueError, "kernel plan: tri_cols is too short");
            return -1;
        }
        OPT(value_rows, const int32_t *, "value_rows", I32, 4, 0, &n_rows);
        p.n_value_rows = p.value_rows ? (int32_t)n_rows : 0;
        OPT(value_op, const float *, "value_op", F32, 4, n_rows * nf, NULL);
        if (p.n_value_rows && !p.value_op) {
            PyErr_SetString(PyExc_ValueError, "kernel plan: value_rows without value_op");
            return -1;
        }
        ARR(grad_op, const float *, "grad_op", F32, 4, 2 * nf * nf, 0); /* (2N, N) */
        ARR(tri_cells, const int32_t *, "tri_cells", I32, 4, T * P, 0);
        ARR(tri_count, const int32_t *, "tri_count", I32, 4, T, 0);
        ARR(tri_weights, const float *, "tri_weights", F32, 4, T * OK_CELL_TERMS * P, 0);
        ARR(value_w, const float *, "value_w", F32, 4, T, 0);
        ARR(grad_w, const float *, "grad_w", F32, 4, (OK_CELL_TERMS - p.n_value_terms) * T, 0);
        if (plan_gradient_solve(self, plan, &p) < 0) return -1;
    } else if (!p.dense) {
        PyErr_SetString(PyExc_ValueError, "kernel plan: neither surface factors nor a dense matrix");
        return -1;
    }
    if (PyDict_GetItemString(plan, "check_probe")) { /* the frame check (FrameCheck) */
        INT(check_bytes, "check_bytes", 1, 3);
        INT(check_pixels, "check_pixels", 0, 1 << 24);
        DBL(check_dark_level, "check_dark_level");
        DBL(check_dark_fraction, "check_dark_fraction");
        DBL(check_saturated_level, "check_saturated_level");
        DBL(check_saturated_fraction, "check_saturated_fraction");
        ARR(check_probe, const int32_t *, "check_probe", I32, 4, (Py_ssize_t)p.check_pixels * p.check_bytes, 0);
    }
    if (plan_models(self, plan, &p) < 0) return -1;
    if (plan_all_read(plan) < 0) return -1;
    char err[200];
    if (ok_kernel_init(&self->k, &p, err, (int)sizeof err) < 0) {
        PyErr_SetString(PyExc_ValueError, err);
        return -1;
    }
    self->initialised = 1;
    return 0;
}

static void Kernel_dealloc(KernelObject *self) {
    if (self->initialised) ok_kernel_free(&self->k);
    for (int i = 0; i < self->n_bufs; i++) PyBuffer_Release(&self->bufs[i]);
    self->n_bufs = 0;
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* Every method: an initialised kernel that no other thread is running (a frame runs with the GIL released;
 * a second thread's frame, or a change of its levels meanwhile, would race on the kernel's buffers). */
#define KERNEL_BUSY "the compiled kernel is processing a frame in another thread: use one Pipeline per thread"
#define REQUIRE_INIT(self)                                                     \
    do {                                                                       \
        if (!(self)->initialised) {                                            \
            PyErr_SetString(PyExc_RuntimeError, "Kernel is not initialised"); \
            return NULL;                                                       \
        }                                                                      \
        if ((self)->busy) {                                                    \
            PyErr_SetString(PyExc_RuntimeError, KERNEL_BUSY);                  \
            return NULL;                                                       \
        }                                                                      \
    } while (0)

/* The frame's bytes, checked against the plan's frame size (the caller checked shape and format). */
static int frame_buffer(KernelObject *self, PyObject *frame, Py_buffer *b) {
    if (PyObject_GetBuffer(frame, b, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        PyErr_SetString(PyExc_ValueError, "frame must be a C-contiguous uint8 array");
        return -1;
    }
    if (b->itemsize != 1 || b->len != self->frame_bytes) {
        PyErr_Format(PyExc_ValueError, "frame has %zd bytes of %zd, the kernel's frames have %zd of 1",
                     b->len / (b->itemsize ? b->itemsize : 1), b->itemsize, self->frame_bytes);
        PyBuffer_Release(b);
        return -1;
    }
    return 0;
}

/* ---------------------------------------------------------------- per frame */

static PyObject *Kernel_frame(KernelObject *self, PyObject *const *args, Py_ssize_t nargs) {
    REQUIRE_INIT(self);
    if (nargs != 3 && nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "frame(frame, now_ns, dt_ns[, means_ready])");
        return NULL;
    }
    int means_ready = nargs == 4 ? PyObject_IsTrue(args[3]) : 0;
    if (means_ready < 0) return NULL;
    long long now_ns = PyLong_AsLongLong(args[1]);
    if (now_ns == -1 && PyErr_Occurred()) return NULL;
    long long dt_ns = PyLong_AsLongLong(args[2]);
    if (dt_ns == -1 && PyErr_Occurred()) return NULL;
    Py_buffer b;
    if (frame_buffer(self, args[0], &b) < 0) return NULL;
    int32_t n;
    self->busy = 1;
    Py_BEGIN_ALLOW_THREADS
    n = ok_frame(&self->k, (const uint8_t *)b.buf, now_ns, dt_ns, means_ready);
    Py_END_ALLOW_THREADS
    self->busy = 0;
    PyBuffer_Release(&b);
    return PyLong_FromLong(n);
}

static PyObject *Kernel_means(KernelObject *self, PyObject *frame) {
    REQUIRE_INIT(self);
    Py_buffer b;
    if (frame_buffer(self, frame, &b) < 0) return NULL;
    self->busy = 1;
    Py_BEGIN_ALLOW_THREADS
    ok_means(&self->k, (const uint8_t *)b.buf);
    Py_END_ALLOW_THREADS
    self->busy = 0;
    PyBuffer_Release(&b);
    Py_RETURN_NONE;
}

static PyObject *Kernel_check(KernelObject *self, PyObject *frame) {
    REQUIRE_INIT(self);
    if (!self->k.p.check_probe) {
        PyErr_SetString(PyExc_RuntimeError, "check: the plan has no frame check");
        return NULL;
    }
    Py_buffer b;
    if (frame_buffer(self, frame, &b) < 0) return NULL;
    int32_t code;
    self->busy = 1;
    Py_BEGIN_ALLOW_THREADS
    ok_means(&self->k, (const uint8_t *)b.buf);
    code = ok_check(&self->k, (const uint8_t *)b.buf);
    Py_END_ALLOW_THREADS
    self->busy = 0;
    PyBuffer_Release(&b);
    return PyLong_FromLong(code);
}

static PyObject *Kernel_set_levels(KernelObject *self, PyObject *args) {
    REQUIRE_INIT(self);
    float trunc, off, on;
    double delta, tolerance, significant;
    if (!PyArg_ParseTuple(args, "fffddd", &trunc, &off, &on, &delta, &tolerance, &significant)) return NULL;
    ok_set_levels(&self->k, trunc, off, on, delta, tolerance, significant);
    Py_RETURN_NONE;
}

static PyObject *Kernel_reset_gain(KernelObject *self, PyObject *arg) {
    REQUIRE_INIT(self);
    long long now_ns = PyLong_AsLongLong(arg);
    if (now_ns == -1 && PyErr_Occurred()) return NULL;
    ok_reset_gain(&self->k, now_ns);
    Py_RETURN_NONE;
}

static PyObject *Kernel_reset_contact(KernelObject *self, PyObject *Py_UNUSED(ignored)) {
    REQUIRE_INIT(self);
    ok_reset_contact(&self->k);
    Py_RETURN_NONE;
}

static PyObject *Kernel_set_correct(KernelObject *self, PyObject *arg) {
    REQUIRE_INIT(self);
    int on = PyObject_IsTrue(arg);
    if (on < 0) return NULL;
    self->k.correct = on;
    Py_RETURN_NONE;
}

static PyMethodDef Kernel_methods[] = {
    {"set_correct", (PyCFunction)Kernel_set_correct, METH_O,
     "set_correct(on): apply the plan's calibration models to the contacts (default on)."},
    {"frame", (PyCFunction)(void (*)(void))Kernel_frame, METH_FASTCALL,
     "frame(frame, now_ns, dt_ns[, means_ready]) -> contacts: one frame after the baseline is ready."},
    {"means", (PyCFunction)Kernel_means, METH_O, "means(frame): the fiber means into the plan's means."},
    {"check", (PyCFunction)Kernel_check, METH_O,
     "check(frame) -> 0 (process it), 1 (dark), 2 (saturated): the fiber means, then FrameCheck from their "
     "pixels; nothing else changes (frame(..., means_ready=True) goes on from the means)."},
    {"set_levels", (PyCFunction)Kernel_set_levels, METH_VARARGS,
     "set_levels(trunc, off, on, gain_delta, gain_tolerance, gain_significant)"},
    {"reset_gain", (PyCFunction)Kernel_reset_gain, METH_O, "reset_gain(now_ns): gain 1 from now on."},
    {"reset_contact", (PyCFunction)Kernel_reset_contact, METH_NOARGS, "reset_contact(): a tare."},
    {NULL, NULL, 0, NULL}};

#define MEMBER(name, type, field, doc) {name, type, offsetof(KernelObject, k.field), READONLY, doc}
static PyMemberDef Kernel_members[] = {
    MEMBER("gain", T_DOUBLE, gain, "The LED gain the last frame was compensated with."),
    MEMBER("frame_gain", T_DOUBLE, frame_gain, "The last frame's own gain estimate."),
    MEMBER("reference", T_DOUBLE, reference, "The last contact-free frame's gain."),
    MEMBER("reference_ns", T_LONGLONG, reference_ns, "Its time, ns."),
    MEMBER("light_changed", T_INT, light_changed, "The last frame's light changed common-mode."),
    MEMBER("light_changes", T_LONGLONG, light_changes, "Common-mode changes of the light taken."),
    MEMBER("common", T_DOUBLE, common, "The level brightness was measured from (signal units)."),
    MEMBER("raise_pending", T_INT, raise_pending, "The last frame found fibers to raise."),
    MEMBER("in_contact", T_INT, in_contact, "The last frame had a contact."),
    MEMBER("saturated", T_INT, saturated, "The last check found a probed pixel at full scale."),
    MEMBER("cells", T_INT, cells, "Cells above the truncation level in the last frame."),
    MEMBER("evaluated", T_INT, evaluated, "Triangles of the surface the last frame evaluated."),
    MEMBER("correct", T_INT, correct, "The plan's calibration models are applied to the contacts."),
    MEMBER("clear_strength", T_DOUBLE, clear_strength, "Strength above the truncation level without contact."),
    MEMBER("clear_area", T_DOUBLE, clear_area, "Area above the truncation level without contact, mm^2."),
    {NULL, 0, 0, 0, NULL}};

static PyTypeObject KernelType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "optitac_edge.core._frame_kernel.Kernel",
    .tp_doc = "The compiled per-frame kernel of one Pipeline (see optitac_edge/core/compiled.py).",
    .tp_basicsize = sizeof(KernelObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Kernel_init,
    .tp_dealloc = (destructor)Kernel_dealloc,
    .tp_methods = Kernel_methods,
    .tp_members = Kernel_members,
};

/* ---------------------------------------------------------------- helpers for the tests */

static PyObject *mod_sort(PyObject *Py_UNUSED(mod), PyObject *arg) {
    Py_buffer b;
    if (PyObject_GetBuffer(arg, &b, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) return NULL;
    if (b.itemsize != 4 || strcmp(b.format, "f") != 0) {
        PyBuffer_Release(&b);
        PyErr_SetString(PyExc_ValueError, "sort: a float32 array");
        return NULL;
    }
    int32_t n = (int32_t)(b.len / 4);
    uint32_t *scratch = PyMem_Malloc(OK_SORT_SCRATCH(n) * sizeof(uint32_t));
    if (!scratch) {
        PyBuffer_Release(&b);
        return PyErr_NoMemory();
    }
    ok_sort_floats((float *)b.buf, n, scratch);
    PyMem_Free(scratch);
    PyBuffer_Release(&b);
    Py_RETURN_NONE;
}

/* label8(mask uint8 (h, w), labels int32 (h, w)) -> labels including the background: the kernel's
 * labelling of the mask's runs, painted back into cells (for the tests) */
static PyObject *mod_label8(PyObject *Py_UNUSED(mod), PyObject *args) {
    PyObject *mask_obj, *labels_obj;
    if (!PyArg_ParseTuple(args, "OO", &mask_obj, &labels_obj)) return NULL;
    Py_buffer m, l;
    if (PyObject_GetBuffer(mask_obj, &m, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return NULL;
    if (PyObject_GetBuffer(labels_obj, &l, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) {
        PyBuffer_Release(&m);
        return NULL;
    }
    PyObject *result = NULL;
    if (m.ndim != 2 || m.itemsize != 1 || l.itemsize != 4 || l.len != 4 * m.len) {
        PyErr_SetString(PyExc_ValueError, "label8: a (h, w) uint8 mask and (h, w) int32 labels");
    } else {
        int32_t h = (int32_t)m.shape[0], w = (int32_t)m.shape[1];
        Py_ssize_t most = (Py_ssize_t)h * ((w + 1) / 2) + 2; /* at most (w + 1) / 2 runs a row */
        int32_t *a = PyMem_Malloc(6 * most * sizeof(int32_t));
        if (!a) {
            PyErr_NoMemory();
        } else {
            int32_t *ry = a, *rx0 = a + most, *rx1 = a + 2 * most, *lab = a + 3 * most, *parent = a + 4 * most,
                    *map = a + 5 * most, n = 0;
            const uint8_t *mask = (const uint8_t *)m.buf;
            int32_t *labels = (int32_t *)l.buf;
            for (int32_t y = 0; y < h; y++)
                for (int32_t x = 0; x < w; x++) {
                    if (!mask[(Py_ssize_t)y * w + x]) continue;
                    ry[n] = y;
                    rx0[n] = x;
                    while (x + 1 < w && mask[(Py_ssize_t)y * w + x + 1]) x++;
                    rx1[n++] = x;
                }
            int32_t count = ok_label_runs(ry, rx0, rx1, n, lab, parent, map);
            memset(labels, 0, (size_t)l.len);
            for (int32_t i = 0; i < n; i++)
                for (int32_t x = rx0[i]; x <= rx1[i]; x++) labels[(Py_ssize_t)ry[i] * w + x] = lab[i];
            result = PyLong_FromLong(count);
            PyMem_Free(a);
        }
    }
    PyBuffer_Release(&m);
    PyBuffer_Release(&l);
    return result;
}

/* nearest_seed(seed_labels int32 (h, w), nearest int32 (h, w)): the kernel's labelled distance transform */
static PyObject *mod_nearest_seed(PyObject *Py_UNUSED(mod), PyObject *args) {
    PyObject *a, *b;
    if (!PyArg_ParseTuple(args, "OO", &a, &b)) return NULL;
    Py_buffer s, n;
    if (PyObject_GetBuffer(a, &s, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return NULL;
    if (PyObject_GetBuffer(b, &n, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) {
        PyBuffer_Release(&s);
        return NULL;
    }
    PyObject *result = NULL;
    if (s.ndim != 2 || s.itemsize != 4 || n.len != s.len) {
        PyErr_SetString(PyExc_ValueError, "nearest_seed: (h, w) int32 seed labels and (h, w) int32 out");
    } else {
        Py_ssize_t h = s.shape[0], w = s.shape[1];
        int32_t *d = PyMem_Malloc((size_t)(2 * (h + 4) + 2) * (w + 4) * sizeof(int32_t));
        if (!d) {
            PyErr_NoMemory();
        } else {
            ok_nearest_seed((const int32_t *)s.buf, (int32_t)h, (int32_t)w, d, (int32_t *)n.buf);
            PyMem_Free(d);
            result = Py_None;
            Py_INCREF(result);
        }
    }
    PyBuffer_Release(&s);
    PyBuffer_Release(&n);
    return result;
}

static PyMethodDef module_methods[] = {
    {"nearest_seed", mod_nearest_seed, METH_VARARGS,
     "nearest_seed(seed_labels, nearest): every cell to its nearest seed, as cv2.distanceTransformWithLabels."},
    {"sort", mod_sort, METH_O, "sort(a): a float32 array in place, ascending (the kernel's sort)."},
    {"label8", mod_label8, METH_VARARGS, "label8(mask, labels) -> n: 8-connected components, raster order."},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_frame_kernel",
                                    "The compiled per-frame kernel (frame_kernel.c).", -1, module_methods,
                                    NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__frame_kernel(void) {
    if (PyType_Ready(&KernelType) < 0) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (!m) return NULL;
    Py_INCREF(&KernelType);
    if (PyModule_AddObject(m, "Kernel", (PyObject *)&KernelType) < 0) {
        Py_DECREF(&KernelType);
        Py_DECREF(m);
        return NULL;
    }
    if (ok_add_vibration_type(m) < 0 || ok_add_motion_type(m) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    PyModule_AddIntConstant(m, "FIELDS", OK_FIELDS);
    PyModule_AddIntConstant(m, "CELL_TERMS", OK_CELL_TERMS);
    PyObject *names = PyTuple_New(OK_FIELDS);
    if (!names) {
        Py_DECREF(m);
        return NULL;
    }
    for (int i = 0; i < OK_FIELDS; i++) PyTuple_SET_ITEM(names, i, PyUnicode_FromString(field_names[i]));
    if (PyErr_Occurred() || PyModule_AddObject(m, "FIELD_NAMES", names) < 0) {
        Py_DECREF(names);
        Py_DECREF(m);
        return NULL;
    }
    PyModule_AddIntConstant(m, "MAX_CANDIDATES", OK_MAX_CANDIDATES);
    return m;
}
