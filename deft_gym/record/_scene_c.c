/* The values of a Foxglove scene template (deft_gym/record/scene.py, `scene_args`): the same
 * tuple as the Python version, for the states it takes, without a Python frame per value.
 *
 * scene_args(sec, nsec, rows, xs, ys, stamp, plan) -> (sec, nsec, then per row (sec, nsec, x, -y,
 * sin(-h/2), cos(-h/2), x, -y, v), then with `plan` (sec, nsec, x0, -y0, x1, -y1, ..., the stamp's
 * JSON string)), or None when a value is not finite. It takes rows as a list of 8-tuples whose
 * x, y, h and v are floats, xs and ys as lists of floats, a stamp that is a str, float or int
 * whose text needs no JSON escape, and values below 1e300 in magnitude (so that Python's sum of
 * them cannot overflow: it is finite exactly when each is); for anything else it returns
 * NotImplemented and the Python version decides. The arithmetic is Python's: -0.5 * h, the C
 * library's sin and cos (which math.sin and math.cos call), negation.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

/* |x| below 1e300: finite, and a sum of fewer than 1e8 of them is finite too */
#define SMALL(x) (fabs(x) < 1e300)

static PyObject *scene_args(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError, "scene_args(sec, nsec, rows, xs, ys, stamp, plan)");
        return NULL;
    }
    PyObject *sec = args[0], *nsec = args[1], *rows = args[2], *xs = args[3], *ys = args[4], *stamp = args[5];
    int plan = PyObject_IsTrue(args[6]);
    if (plan < 0) return NULL;
    if (!PyList_CheckExact(rows) || !PyList_CheckExact(xs) || !PyList_CheckExact(ys)) Py_RETURN_NOTIMPLEMENTED;
    Py_ssize_t n_rows = PyList_GET_SIZE(rows), n_pts = PyList_GET_SIZE(xs);
    if (plan && PyList_GET_SIZE(ys) != n_pts) Py_RETURN_NOTIMPLEMENTED; /* Python: a ValueError, None */
    int finite = 1;
    /* the checks first: nothing is made for a state the Python version must decide */
    for (Py_ssize_t r = 0; r < n_rows; r++) {
        PyObject *row = PyList_GET_ITEM(rows, r);
        if (!PyTuple_CheckExact(row) || PyTuple_GET_SIZE(row) != 8) Py_RETURN_NOTIMPLEMENTED;
        for (int k = 2; k < 6; k++) {
            PyObject *v = PyTuple_GET_ITEM(row, k);
            if (!PyFloat_CheckExact(v)) Py_RETURN_NOTIMPLEMENTED;
            double d = PyFloat_AS_DOUBLE(v);
            if (isfinite(d) && !SMALL(d)) Py_RETURN_NOTIMPLEMENTED;
            finite &= isfinite(d) != 0;
        }
    }
    PyObject *stamp_json = NULL;
    if (plan) {
        for (Py_ssize_t i = 0; i < n_pts; i++) {
            for (int side = 0; side < 2; side++) {
                PyObject *v = PyList_GET_ITEM(side ? ys : xs, i);
                if (!PyFloat_CheckExact(v)) Py_RETURN_NOTIMPLEMENTED;
                double d = PyFloat_AS_DOUBLE(v);
                if (isfinite(d) && !SMALL(d)) Py_RETURN_NOTIMPLEMENTED;
                finite &= isfinite(d) != 0;
            }
        }
        if (!(PyUnicode_CheckExact(stamp) || PyFloat_CheckExact(stamp) || PyLong_CheckExact(stamp)))
            Py_RETURN_NOTIMPLEMENTED;
        if (finite) {
            PyObject *text = PyObject_Str(stamp);
            if (!text) return NULL;
            /* json.dumps of a str whose characters are printable ASCII other than " and \ */
            Py_ssize_t m = PyUnicode_GET_LENGTH(text);
            int plain = PyUnicode_IS_ASCII(text);
            const unsigned char *c = plain ? (const unsigned char *)PyUnicode_DATA(text) : NULL;
            for (Py_ssize_t i = 0; plain && i < m; i++)
                plain = c[i] >= 0x20 && c[i] < 0x7f && c[i] != '"' && c[i] != '\\';
            if (!plain) {
                Py_DECREF(text);
                Py_RETURN_NOTIMPLEMENTED;
            }
            stamp_json = PyUnicode_FromFormat("\"%U\"", text);
            Py_DECREF(text);
            if (!stamp_json) return NULL;
        }
    }
    if (!finite) Py_RETURN_NONE; /* a sum with a NaN or an infinity is not finite */
    Py_ssize_t n = 2 + 9 * n_rows + (plan ? 3 + 2 * n_pts : 0);
    PyObject *out = PyTuple_New(n);
    if (!out) {
        Py_XDECREF(stamp_json);
        return NULL;
    }
    Py_ssize_t at = 0;
#define PUT(obj) PyTuple_SET_ITEM(out, at++, (obj))
#define PUT_REF(obj) (Py_INCREF(obj), PUT(obj))
#define PUT_FLOAT(d)                              \
    do {                                          \
        PyObject *f_ = PyFloat_FromDouble(d);     \
        if (!f_) goto fail;                       \
        PUT(f_);                                  \
    } while (0)
    PUT_REF(sec);
    PUT_REF(nsec);
    for (Py_ssize_t r = 0; r < n_rows; r++) {
        PyObject *row = PyList_GET_ITEM(rows, r);
        PyObject *x = PyTuple_GET_ITEM(row, 2), *v = PyTuple_GET_ITEM(row, 5);
        double y = PyFloat_AS_DOUBLE(PyTuple_GET_ITEM(row, 3));
        double half = -0.5 * PyFloat_AS_DOUBLE(PyTuple_GET_ITEM(row, 4));
        PUT_REF(sec);
        PUT_REF(nsec);
        PUT_REF(x);
        PUT_FLOAT(-y);
        PUT_FLOAT(sin(half));
        PUT_FLOAT(cos(half));
        PUT_REF(x);
        PUT_FLOAT(-y);
        PUT_REF(v);
    }
    if (plan) {
        PUT_REF(sec);
        PUT_REF(nsec);
        for (Py_ssize_t i = 0; i < n_pts; i++) {
            PUT_REF(PyList_GET_ITEM(xs, i)); /* float(x) of a float is x */
            PUT_FLOAT(-PyFloat_AS_DOUBLE(PyList_GET_ITEM(ys, i)));
        }
        PUT(stamp_json);
        stamp_json = NULL;
    }
    return out;
fail:
    /* the unfilled items are NULL, which the tuple's deallocation skips */
    Py_XDECREF(stamp_json);
    Py_DECREF(out);
    return NULL;
#undef PUT
#undef PUT_REF
#undef PUT_FLOAT
}

/* the SHA-256 digests of the sources this build was made from (setup.py defines BUILT_FROM as
 * "<digest of this file> <digest of scene.py>"; deft_gym.files.stale_kernel compares them) */
#ifndef BUILT_FROM
#define BUILT_FROM ""
#endif

static PyMethodDef methods[] = {
    {"scene_args", (PyCFunction)(void (*)(void))scene_args, METH_FASTCALL,
     "scene_args(sec, nsec, rows, xs, ys, stamp, plan): deft_gym.record.scene.scene_args's tuple (or None), or "
     "NotImplemented where the Python version must decide"},
    {NULL, NULL, 0, NULL}};
static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_scene_c", NULL, -1, methods};

PyMODINIT_FUNC PyInit__scene_c(void) {
    PyObject *m = PyModule_Create(&module);
    if (m && PyModule_AddStringConstant(m, "BUILT_FROM", BUILT_FROM) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
