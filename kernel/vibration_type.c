/* optitac_edge.core._frame_kernel.Vibration: the CPython face of vibration.c.
 *
 * Vibration(signal, live, constants) keeps the pipeline's signal buffer and its own filter state;
 * update(trunc, dt_ns) runs one frame with the GIL released (optitac_edge/core/vibration.py uses it when
 * the kernel is built and is the reference for what it computes). */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>
#include <string.h>

#include "vibration.h"

typedef struct {
    PyObject_HEAD
    ok_vibration v;
    Py_buffer signal;
    int has_signal;
    int32_t *live;
    float *state;
    int busy; /* a step runs without the GIL: set and read with it held, so one thread at a time */
} VibrationObject;

static void Vibration_dealloc(VibrationObject *self) {
    if (self->has_signal) PyBuffer_Release(&self->signal);
    PyMem_Free(self->live);
    PyMem_Free(self->state);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int Vibration_init(VibrationObject *self, PyObject *args, PyObject *kwds) {
    static char *kwlist[] = {"signal", "live", "cutoff_hz", "rate_fraction", "window", "learn_frames",
                             "min_fibers", "on_sigmas", "quiet_tau_s", "vibrating_tau_s", NULL};
    PyObject *signal_obj, *live_obj;
    ok_vibration p;
    memset(&p, 0, sizeof p);
    if (self->has_signal) {
        PyErr_SetString(PyExc_RuntimeError, "Vibration is initialised once");
        return -1;
    }
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "OOddiiiddd", kwlist, &signal_obj, &live_obj, &p.cutoff_hz,
                                     &p.rate_fraction, &p.window, &p.learn_frames, &p.min_fibers, &p.on_sigmas,
                                     &p.quiet_tau_s, &p.vibrating_tau_s))
        return -1;
    if (p.window < 1 || p.window > OK_VIB_MAX_WINDOW || p.learn_frames < 1 || p.min_fibers < 1 ||
        !(p.cutoff_hz > 0) || !(p.rate_fraction > 0 && p.rate_fraction < 0.5) || !(p.quiet_tau_s > 0) ||
        !(p.vibrating_tau_s > 0) || !(p.on_sigmas > 0)) {
        PyErr_SetString(PyExc_ValueError, "Vibration: constants out of range");
        return -1;
    }
    Py_buffer live;
    if (PyObject_GetBuffer(signal_obj, &self->signal, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return -1;
    self->has_signal = 1;
    if (self->signal.itemsize != 4 || strcmp(self->signal.format, "f") != 0) {
        PyErr_SetString(PyExc_ValueError, "Vibration: the signal is a float32 array");
        return -1;
    }
    if (PyObject_GetBuffer(live_obj, &live, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return -1;
    Py_ssize_t n = live.len / 4, n_fibers = self->signal.len / 4;
    int ok = live.itemsize == 4 && strcmp(live.format, "i") == 0 && n >= 1;
    const int32_t *idx = (const int32_t *)live.buf;
    for (Py_ssize_t i = 0; ok && i < n; i++) ok = idx[i] >= 0 && idx[i] < n_fibers;
    if (!ok) {
        PyBuffer_Release(&live);
        PyErr_SetString(PyExc_ValueError, "Vibration: live is a non-empty int32 array of fiber indices");
        return -1;
    }
    self->live = PyMem_Malloc((size_t)n * sizeof(int32_t));
    self->state = PyMem_Malloc((size_t)n * 4 * sizeof(float));
    if (!self->live || !self->state) {
        PyBuffer_Release(&live);
        PyErr_NoMemory();
        return -1;
    }
    memcpy(self->live, idx, (size_t)n * sizeof(int32_t));
    PyBuffer_Release(&live);
    p.n = (int32_t)n;
    p.live = self->live;
    p.signal = (const float *)self->signal.buf;
    p.x = self->state;
    p.z1 = self->state + n;
    p.z2 = self->state + 2 * n;
    p.mask = self->state + 3 * n;
    self->v = p;
    ok_vibration_reset(&self->v);
    return 0;
}

static PyObject *Vibration_step(VibrationObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (!self->has_signal || !self->live) {
        PyErr_SetString(PyExc_RuntimeError, "Vibration is not initialised");
        return NULL;
    }
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "update(trunc, dt_ns)");
        return NULL;
    }
    double trunc = PyFloat_AsDouble(args[0]);
    if (trunc == -1.0 && PyErr_Occurred()) return NULL;
    long long dt_ns = PyLong_AsLongLong(args[1]);
    if (dt_ns == -1 && PyErr_Occurred()) return NULL;
    if (self->busy) {
        PyErr_SetString(PyExc_RuntimeError, "Vibration is stepping in another thread: use one Pipeline per thread");
        return NULL;
    }
    double level;
    self->busy = 1;
    Py_BEGIN_ALLOW_THREADS
    level = ok_vibration_step(&self->v, (float)trunc, dt_ns);
    Py_END_ALLOW_THREADS
    self->busy = 0;
    return PyFloat_FromDouble(level);
}

static PyObject *Vibration_reset(VibrationObject *self, PyObject *Py_UNUSED(ignored)) {
    if (self->busy) {
        PyErr_SetString(PyExc_RuntimeError, "Vibration is stepping in another thread: use one Pipeline per thread");
        return NULL;
    }
    if (self->live) ok_vibration_reset(&self->v);
    Py_RETURN_NONE;
}

static PyMethodDef Vibration_methods[] = {
    {"update", (PyCFunction)(void (*)(void))Vibration_step, METH_FASTCALL,
     "update(trunc, dt_ns) -> level: the frame in the signal buffer."},
    {"reset", (PyCFunction)Vibration_reset, METH_NOARGS, "reset(): the filter and the noise from the start."},
    {NULL, NULL, 0, NULL}};

static PyMemberDef Vibration_members[] = {
    {"level", T_DOUBLE, offsetof(VibrationObject, v.level), READONLY, "the last frame's level"},
    {"quiet", T_DOUBLE, offsetof(VibrationObject, v.quiet), READONLY, "the level's quiet value"},
    {"unit", T_DOUBLE, offsetof(VibrationObject, v.unit), READONLY, "the noise's mean square"},
    {"vibrating", T_BOOL, offsetof(VibrationObject, v.vibrating), READONLY, "above the quiet level"},
    {"began", T_BOOL, offsetof(VibrationObject, v.began), READONLY, "vibrating turned on in the last frame"},
    {NULL, 0, 0, 0, NULL}};

int ok_set_period(double *field, PyObject *value, const char *who); /* motion_type.c */

static PyObject *Vibration_get_period(VibrationObject *self, void *Py_UNUSED(closure)) {
    return PyFloat_FromDouble(self->v.period_s);
}

static int Vibration_set_period(VibrationObject *self, PyObject *value, void *Py_UNUSED(closure)) {
    return ok_set_period(&self->v.period_s, value, "Vibration");
}

static PyGetSetDef Vibration_getset[] = {
    {"period_s", (getter)Vibration_get_period, (setter)Vibration_set_period,
     "the camera's nominal frame period the filter is designed for, s (0: the first frame interval)", NULL},
    {NULL, NULL, NULL, NULL, NULL}};

static PyTypeObject VibrationType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "optitac_edge.core._frame_kernel.Vibration",
    .tp_doc = "The fibers' vibration, frame by frame (see optitac_edge/core/vibration.py).",
    .tp_basicsize = sizeof(VibrationObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Vibration_init,
    .tp_dealloc = (destructor)Vibration_dealloc,
    .tp_methods = Vibration_methods,
    .tp_members = Vibration_members,
    .tp_getset = Vibration_getset,
};

int ok_add_vibration_type(PyObject *module) {
    if (PyType_Ready(&VibrationType) < 0) return -1;
    Py_INCREF(&VibrationType);
    if (PyModule_AddObject(module, "Vibration", (PyObject *)&VibrationType) < 0) {
        Py_DECREF(&VibrationType);
        return -1;
    }
    return 0;
}
