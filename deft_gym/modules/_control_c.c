/* Compiled parts of the control module (deft_gym/modules/control.py): the conversion of a
 * planned trajectory, once per new plan, and the nearest trajectory point, once per cycle.
 *
 * `float_lists(tr)` is `_float_lists(tr)` followed by `_well_formed(...)` for the usual case:
 * every column ("t", "x", "y", "v", "a", "heading") a list of the same number n >= 1 of plain
 * Python floats, no heading step of pi or more (so np.unwrap would change nothing but -0.0),
 * finite ascending times and finite arc lengths. It then returns the dict the Python version
 * returns: the same t, x, y, v, a list objects, heading with `+ 0.0` added to every element
 * after the first (-0.0 becomes 0.0), and `s`, the running sum from 0.0 of the step lengths.
 * Anything else (not a dict, a missing key, a column that is not a list or has another length,
 * an element that is an int, a bool, a float subclass or a numpy scalar, a heading step >= pi or
 * NaN, a non-finite time or arc length, a time going backwards) returns None, and the Python and
 * numpy path runs and computes the same result or raises the same error as without this module.
 *
 * Bit-identity: the step lengths are np.hypot(np.diff(x), np.diff(y)), i.e. the C library's
 * hypot of x[i+1] - x[i] and y[i+1] - y[i] (numpy's float64 hypot calls it), and `s` adds them
 * in order like itertools.accumulate; the heading test is `abs(b - a) < math.pi` on doubles;
 * the well-formedness tests are the same comparisons as _well_formed. Build flags keep IEEE
 * semantics (no fast-math, no FMA contraction); see setup.py.
 *
 * `nearest(xs, ys, x, y)` is `_nearest` (np.argmin of the squared distances: the first of
 * equals, the first NaN) with the same operations, dx * dx + dy * dy; None when xs and ys are
 * not lists of the same length of plain floats or x, y not plain floats (then `_nearest` runs).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>

enum { C_T, C_X, C_Y, C_V, C_A, C_HEADING, N_COLS };
static const char *const NAMES[N_COLS] = {"t", "x", "y", "v", "a", "heading"};
static PyObject *KEYS[N_COLS], *KEY_S;

#define PI 3.141592653589793 /* math.pi, the double nearest to pi */
#define AT(l, i) PyFloat_AS_DOUBLE(PyList_GET_ITEM(l, i))

/* whether l is a list of exactly n plain floats (no ints, bools, subclasses, numpy scalars) */
static int all_floats(PyObject *l, Py_ssize_t n)
{
    if (!PyList_CheckExact(l) || PyList_GET_SIZE(l) != n) return 0;
    for (Py_ssize_t i = 0; i < n; i++)
        if (!PyFloat_CheckExact(PyList_GET_ITEM(l, i))) return 0;
    return 1;
}

/* the columns of `tr` if all are lists of n >= 1 plain floats, else 0 (no error set) */
static int float_columns(PyObject *tr, PyObject **cols, Py_ssize_t *n_out)
{
    if (!PyDict_CheckExact(tr)) return 0;
    Py_ssize_t n = -1;
    for (int c = 0; c < N_COLS; c++) {
        PyObject *l = PyDict_GetItemWithError(tr, KEYS[c]);
        if (!l) { /* missing (Python raises KeyError) or a failing key comparison: Python decides */
            PyErr_Clear();
            return 0;
        }
        if (c == C_T) n = PyList_CheckExact(l) ? PyList_GET_SIZE(l) : -1;
        if (n < 1 || !all_floats(l, n)) return 0;
        cols[c] = l;
    }
    *n_out = n;
    return 1;
}

/* float_lists(tr) -> dict | None; see the comment at the top */
static PyObject *float_lists(PyObject *self, PyObject *tr)
{
    PyObject *cols[N_COLS];
    Py_ssize_t n;
    if (!float_columns(tr, cols, &n)) Py_RETURN_NONE;
    PyObject *T = cols[C_T], *X = cols[C_X], *Y = cols[C_Y], *H = cols[C_HEADING];
    for (Py_ssize_t i = 0; i < n; i++) {
        double t = AT(T, i);
        if (!isfinite(t)) Py_RETURN_NONE;
        if (i > 0 && !(t - AT(T, i - 1) >= 0.0)) Py_RETURN_NONE;
        if (i > 0 && !(fabs(AT(H, i) - AT(H, i - 1)) < PI)) Py_RETURN_NONE; /* np.unwrap's case */
    }
    PyObject *heading = NULL, *s = NULL, *out = NULL;
    if (!(heading = PyList_New(n)) || !(s = PyList_New(n))) goto done;
    PyObject *h0 = PyList_GET_ITEM(H, 0);
    Py_INCREF(h0); /* the first heading is kept as it is */
    PyList_SET_ITEM(heading, 0, h0);
    for (Py_ssize_t i = 1; i < n; i++) {
        PyObject *h = PyFloat_FromDouble(AT(H, i) + 0.0);
        if (!h) goto done;
        PyList_SET_ITEM(heading, i, h);
    }
    double acc = 0.0;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (i > 0) {
            double seg = hypot(AT(X, i) - AT(X, i - 1), AT(Y, i) - AT(Y, i - 1));
            acc = i == 1 ? seg : acc + seg; /* accumulate's first value is the step itself */
            if (!isfinite(acc)) {
                out = Py_None; /* not well formed: the Python path decides */
                Py_INCREF(out);
                goto done;
            }
        }
        PyObject *v = PyFloat_FromDouble(acc);
        if (!v) goto done;
        PyList_SET_ITEM(s, i, v);
    }
    if (!(out = PyDict_New())) goto done;
    for (int c = 0; c < N_COLS; c++)
        if (PyDict_SetItem(out, KEYS[c], c == C_HEADING ? heading : cols[c]) < 0) goto fail;
    if (PyDict_SetItem(out, KEY_S, s) < 0) goto fail;
    goto done;
fail:
    Py_CLEAR(out);
done:
    Py_XDECREF(heading);
    Py_XDECREF(s);
    return out;
}

/* nearest(xs, ys, x, y) -> int | None; see the comment at the top */
static PyObject *nearest(PyObject *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 4) {
        PyErr_SetString(PyExc_TypeError, "nearest(xs, ys, x, y)");
        return NULL;
    }
    PyObject *xs = args[0], *ys = args[1];
    if (!PyList_CheckExact(xs)) Py_RETURN_NONE;
    Py_ssize_t n = PyList_GET_SIZE(xs);
    if (!all_floats(xs, n) || !all_floats(ys, n) || !PyFloat_CheckExact(args[2]) ||
        !PyFloat_CheckExact(args[3]))
        Py_RETURN_NONE;
    double x = PyFloat_AS_DOUBLE(args[2]), y = PyFloat_AS_DOUBLE(args[3]), best = INFINITY;
    Py_ssize_t i = 0;
    for (Py_ssize_t k = 0; k < n; k++) {
        double dx = AT(xs, k) - x, dy = AT(ys, k) - y;
        double d2 = dx * dx + dy * dy;
        if (d2 < best) {
            i = k;
            best = d2;
        } else if (d2 != d2) {
            return PyLong_FromSsize_t(k);
        }
    }
    return PyLong_FromSsize_t(i);
}
#undef AT

static PyMethodDef methods[] = {
    {"float_lists", float_lists, METH_O,
     "A well-formed planned trajectory as control's plain-float lists, else None; see the module "
     "source."},
    {"nearest", (PyCFunction)(void (*)(void))nearest, METH_FASTCALL,
     "Index of the trajectory point nearest to (x, y) as _nearest finds it, or None."},
    {NULL, NULL, 0, NULL},
};

/* the SHA-256 digests of the sources this build was made from (setup.py defines BUILT_FROM as
   "<digest of this file> <digest of the Python file it mirrors>"); the module that loads it
   refuses a build whose digests differ from the files beside it (a stale kernel) */
#ifndef BUILT_FROM
#define BUILT_FROM ""
#endif

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_control_c",
                                    "Compiled trajectory conversion and nearest point of the control module.", -1,
                                    methods, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__control_c(void)
{
    for (int c = 0; c < N_COLS; c++)
        if (!(KEYS[c] = PyUnicode_InternFromString(NAMES[c]))) return NULL;
    if (!(KEY_S = PyUnicode_InternFromString("s"))) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m && PyModule_AddStringConstant(m, "BUILT_FROM", BUILT_FROM) < 0) Py_CLEAR(m);
    return m;
}
