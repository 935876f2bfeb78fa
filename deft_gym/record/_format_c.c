/* `(template % args).encode()` for the viewer topics' JSON (deft_gym/record/textformat.py,
 * `format_bytes`), where the template holds only %d (an exact int), %s (an exact ASCII str),
 * %.Nf (a float; N a single digit, |x| * 10**N below 2**52) and %%: the same bytes as Python's
 * `%`. %.Nf is exact fixed-point rounding: r = nearbyint(|x| * 10**N), then the
 * sign of |x| * 10**N - (r +- 0.5), computed exactly by fma (one rounding of a value whose sign
 * it keeps), moves r by one where the product's rounding crossed a half and settles a tie to
 * even - Python's rounding of the exact binary value. Anything else (another conversion, type or
 * range, too few or too many args) returns NotImplemented and Python's `%` formats it.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

static const double POW10[10] = {1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9};
#define NUMBER_CHARS 32 /* the longest number written here: '-', 16 digits, '.', 9 digits */

/* "%.<nd>f" of x into out (room for NUMBER_CHARS), its length; -1 when out of range */
static int fixed(char *out, double x, int nd) {
    if (!isfinite(x)) return -1;
    double scale = POW10[nd], a = fabs(x);
    if (!(a * scale < 4503599627370496.0)) return -1; /* 2**52: r and r +- 0.5 are exact */
    double r = nearbyint(a * scale);
    double above = fma(a, scale, -(r + 0.5)), below = fma(a, scale, -(r - 0.5));
    int odd = fmod(r, 2.0) != 0.0;
    if (above > 0.0 || (above == 0.0 && odd)) r += 1.0;
    else if (below < 0.0 || (below == 0.0 && odd)) r -= 1.0;
    uint64_t digits = (uint64_t)r, unit = (uint64_t)POW10[nd];
    uint64_t whole = digits / unit, frac = digits % unit;
    char rev[20];
    int n = 0, k = 0;
    if (signbit(x)) out[n++] = '-'; /* as Python: -0.0 and -0.0001 are "-0.000" */
    do {
        rev[k++] = (char)('0' + whole % 10);
        whole /= 10;
    } while (whole);
    while (k) out[n++] = rev[--k];
    if (nd) {
        out[n++] = '.';
        for (int i = nd - 1; i >= 0; i--) {
            out[n + i] = (char)('0' + frac % 10);
            frac /= 10;
        }
        n += nd;
    }
    return n;
}

static PyObject *format_bytes(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2 || !PyUnicode_CheckExact(args[0]) || !PyTuple_CheckExact(args[1]) ||
        !PyUnicode_IS_ASCII(args[0]))
        Py_RETURN_NOTIMPLEMENTED;
    const char *p = (const char *)PyUnicode_DATA(args[0]);
    const char *end = p + PyUnicode_GET_LENGTH(args[0]);
    Py_ssize_t nvals = PyTuple_GET_SIZE(args[1]), used = 0;
    PyObject *const *vals = &PyTuple_GET_ITEM(args[1], 0);
    /* room for the template's text and a number per value; a %s grows it */
    Py_ssize_t cap = (end - p) + NUMBER_CHARS * nvals + 1, n = 0;
    PyObject *bytes = PyBytes_FromStringAndSize(NULL, cap);
    if (!bytes) return NULL;
    char *out = PyBytes_AS_STRING(bytes);
    while (p < end) {
        const char *pct = memchr(p, '%', end - p);
        Py_ssize_t text = (pct ? pct : end) - p;
        memcpy(out + n, p, text);
        n += text;
        if (!pct) break;
        p = pct + 1;
        if (p >= end) goto python;
        char c = *p++;
        if (c == '%') {
            out[n++] = '%';
            continue;
        }
        if (used >= nvals) goto python;
        PyObject *v = vals[used++];
        if (c == 'd') {
            if (!PyLong_CheckExact(v)) goto python;
            int overflow;
            long long iv = PyLong_AsLongLongAndOverflow(v, &overflow);
            if (overflow) goto python;
            n += sprintf(out + n, "%lld", iv);
        } else if (c == 's') {
            if (!PyUnicode_CheckExact(v) || !PyUnicode_IS_ASCII(v)) goto python;
            Py_ssize_t m = PyUnicode_GET_LENGTH(v);
            cap += m;
            if (_PyBytes_Resize(&bytes, cap) < 0) return NULL;
            out = PyBytes_AS_STRING(bytes);
            memcpy(out + n, PyUnicode_DATA(v), m);
            n += m;
        } else if (c == '.' && end - p >= 2 && p[0] >= '0' && p[0] <= '9' && p[1] == 'f') {
            if (!PyFloat_CheckExact(v)) goto python;
            int m = fixed(out + n, PyFloat_AS_DOUBLE(v), p[0] - '0');
            if (m < 0) goto python;
            n += m;
            p += 2;
        } else {
            goto python;
        }
    }
    if (used != nvals) goto python;
    if (_PyBytes_Resize(&bytes, n) < 0) return NULL;
    return bytes;
python:
    Py_DECREF(bytes);
    Py_RETURN_NOTIMPLEMENTED;
}

/* the SHA-256 digests of the sources this build was made from (setup.py defines BUILT_FROM as
 * "<digest of this file> <digest of textformat.py>"; deft_gym.files.stale_kernel compares them) */
#ifndef BUILT_FROM
#define BUILT_FROM ""
#endif

static PyMethodDef methods[] = {
    {"format_bytes", (PyCFunction)(void (*)(void))format_bytes, METH_FASTCALL,
     "format_bytes(template, args): (template % args).encode(), or NotImplemented where Python's % must "
     "format it"},
    {NULL, NULL, 0, NULL}};
static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_format_c", NULL, -1, methods};

PyMODINIT_FUNC PyInit__format_c(void) {
    PyObject *m = PyModule_Create(&module);
    if (m && PyModule_AddStringConstant(m, "BUILT_FROM", BUILT_FROM) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
