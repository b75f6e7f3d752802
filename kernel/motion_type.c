/* optitac_edge.core._frame_kernel.Motion: the CPython face of motion.c.
 *
 * Motion(window, slip_sigmas, min_speed, min_shift, hold_fraction, noise_rate, prior, steady_ratio,
 * min_span_fraction) keeps every tracked contact's window (period_s: the camera's nominal frame period, 0 unknown); update(contacts, n, frame, now_ns) reads each contact's contact_id, touch_frame, x_mm,
 * y_mm and strength and sets its vx_mm_s, vy_mm_s, sliding and slide_frame, as ContactMotion.update does
 * (optitac_edge/core/motion.py, the reference). */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>

#include "motion.h"

#include <math.h>

typedef struct {
    PyObject_HEAD
    ok_motion m;
    int initialised;
} MotionObject;

static PyObject *s_id, *s_touch, *s_x, *s_y, *s_strength, *s_vx, *s_vy, *s_sliding, *s_slide_frame;

static int Motion_init(MotionObject *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"window", "slip_sigmas", "min_speed", "min_shift", "hold_fraction", "noise_rate",
                             "prior", "steady_ratio", "min_span_fraction", NULL};
    ok_motion *m = &self->m;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "idddddddd", kwlist, &m->window, &m->slip_sigmas, &m->min_speed,
                                     &m->min_shift, &m->hold_fraction, &m->noise_rate, &m->prior, &m->steady_ratio,
                                     &m->min_span_fraction))
        return -1;
    m->period_s = 0.0;
    if (m->window < 3 || m->window > OK_MOTION_MAX_WINDOW || !(m->prior >= 0) || !(m->noise_rate > 0) ||
        !(m->steady_ratio >= 1.0) || !(m->min_span_fraction >= 0.0 && m->min_span_fraction <= 1.0)) {
        PyErr_SetString(PyExc_ValueError, "Motion: constants out of range");
        return -1;
    }
    m->prior_strength = NAN;
    ok_motion_reset(m);
    self->initialised = 1;
    return 0;
}

static int get_long(PyObject *obj, PyObject *name, long *out) {
    PyObject *v = PyObject_GetAttr(obj, name);
    if (!v) return -1;
    *out = PyLong_AsLong(v);
    Py_DECREF(v);
    return *out == -1 && PyErr_Occurred() ? -1 : 0;
}

static int get_double(PyObject *obj, PyObject *name, double *out) {
    PyObject *v = PyObject_GetAttr(obj, name);
    if (!v) return -1;
    *out = PyFloat_AsDouble(v);
    Py_DECREF(v);
    return *out == -1.0 && PyErr_Occurred() ? -1 : 0;
}

static int set_steal(PyObject *obj, PyObject *name, PyObject *value) {
    if (!value) return -1;
    int r = PyObject_SetAttr(obj, name, value);
    Py_DECREF(value);
    return r;
}

static PyObject *Motion_update(MotionObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (!self->initialised) {
        PyErr_SetString(PyExc_RuntimeError, "Motion is not initialised");
        return NULL;
    }
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "update(contacts, n, frame, now_ns)");
        return NULL;
    }
    Py_ssize_t n = PyLong_AsSsize_t(args[1]);
    long frame = PyLong_AsLong(args[2]);
    long long now_ns = PyLong_AsLongLong(args[3]);
    if (PyErr_Occurred()) return NULL;
    PyObject *seq = PySequence_Fast(args[0], "update: contacts must be a sequence");
    if (!seq) return NULL;
    if (n < 0 || n > PySequence_Fast_GET_SIZE(seq)) {
        Py_DECREF(seq);
        PyErr_SetString(PyExc_ValueError, "update: n out of range");
        return NULL;
    }
    double t_s = (double)now_ns * 1e-9;
    for (Py_ssize_t i = 0; i < n; i++) {
        PyObject *c = PySequence_Fast_GET_ITEM(seq, i);
        long id, touch;
        double x, y, strength;
        if (get_long(c, s_id, &id) < 0 || get_long(c, s_touch, &touch) < 0 || get_double(c, s_x, &x) < 0 ||
            get_double(c, s_y, &y) < 0 || get_double(c, s_strength, &strength) < 0)
            goto fail;
        ok_track *track = ok_motion_track(&self->m, (int32_t)id, touch == frame, (int32_t)frame);
        if (!track) {
            PyErr_SetString(PyExc_RuntimeError, "update: more contacts than Motion keeps tracks");
            goto fail;
        }
        ok_motion_out out;
        ok_motion_step(&self->m, track, x, y, strength, (int32_t)frame, t_s, &out);
        if (set_steal(c, s_vx, PyFloat_FromDouble(out.vx)) < 0 || set_steal(c, s_vy, PyFloat_FromDouble(out.vy)) < 0 ||
            PyObject_SetAttr(c, s_sliding, out.sliding ? Py_True : Py_False) < 0 ||
            set_steal(c, s_slide_frame, PyLong_FromLong(out.slide_frame)) < 0)
            goto fail;
    }
    Py_DECREF(seq);
    ok_motion_forget(&self->m, (int32_t)frame);
    Py_RETURN_NONE;
fail:
    Py_DECREF(seq);
    return NULL;
}

static PyObject *Motion_reset(MotionObject *self, PyObject *Py_UNUSED(ignored)) {
    ok_motion_reset(&self->m);
    Py_RETURN_NONE;
}

static PyMethodDef Motion_methods[] = {
    {"update", (PyCFunction)(void (*)(void))Motion_update, METH_FASTCALL,
     "update(contacts, n, frame, now_ns): the first n contacts' velocity and slip state, in place."},
    {"reset", (PyCFunction)Motion_reset, METH_NOARGS, "reset(): forget every contact (a tare)."},
    {NULL, NULL, 0, NULL}};

/* a frame period: a finite number >= 0 (0: not known) */
int ok_set_period(double *field, PyObject *value, const char *who) {
    if (!value) {
        PyErr_Format(PyExc_AttributeError, "%s.period_s cannot be deleted", who);
        return -1;
    }
    double v = PyFloat_AsDouble(value);
    if (v == -1.0 && PyErr_Occurred()) return -1;
    if (!(v >= 0.0) || !isfinite(v)) {
        PyErr_Format(PyExc_ValueError, "%s.period_s must be a finite number of seconds >= 0", who);
        return -1;
    }
    *field = v;
    return 0;
}

static PyObject *Motion_get_period(MotionObject *self, void *Py_UNUSED(closure)) {
    return PyFloat_FromDouble(self->m.period_s);
}

static int Motion_set_period(MotionObject *self, PyObject *value, void *Py_UNUSED(closure)) {
    return ok_set_period(&self->m.period_s, value, "Motion");
}

static PyGetSetDef Motion_getset[] = {
    {"period_s", (getter)Motion_get_period, (setter)Motion_set_period,
     "the camera's nominal frame period, s (0: not known)", NULL},
    {NULL, NULL, NULL, NULL, NULL}};

static PyTypeObject MotionType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "optitac_edge.core._frame_kernel.Motion",
    .tp_doc = "Every tracked contact's velocity and slip state (see optitac_edge/core/motion.py).",
    .tp_basicsize = sizeof(MotionObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Motion_init,
    .tp_methods = Motion_methods,
    .tp_getset = Motion_getset,
};

int ok_add_motion_type(PyObject *module) {
    if (!(s_id = PyUnicode_InternFromString("contact_id")) || !(s_touch = PyUnicode_InternFromString("touch_frame")) ||
        !(s_x = PyUnicode_InternFromString("x_mm")) || !(s_y = PyUnicode_InternFromString("y_mm")) ||
        !(s_strength = PyUnicode_InternFromString("strength")) ||
        !(s_vx = PyUnicode_InternFromString("vx_mm_s")) || !(s_vy = PyUnicode_InternFromString("vy_mm_s")) ||
        !(s_sliding = PyUnicode_InternFromString("sliding")) ||
        !(s_slide_frame = PyUnicode_InternFromString("slide_frame")))
        return -1;
    if (PyType_Ready(&MotionType) < 0) return -1;
    Py_INCREF(&MotionType);
    if (PyModule_AddObject(module, "Motion", (PyObject *)&MotionType) < 0) {
        Py_DECREF(&MotionType);
        return -1;
    }
    return 0;
}
