/* Payload snapshots for the recorder process (deft_gym/recorder.py): a message payload as bytes
 * at its publish time, read back in the recorder process. Three to five times faster than
 * pickle for the bus's payloads, which are dicts of lists of floats.
 *
 * `dumps(obj)` serialises a tree of plain values: dict, list, tuple, str, int (64-bit), float,
 * True, False, None - exact types only, no subclasses. Anything else anywhere in the tree (a
 * numpy value, an int beyond 64 bits, a string with a lone surrogate, a tree deeper than
 * MAX_DEPTH) makes it return `pickle.dumps(obj, HIGHEST_PROTOCOL)` instead, so every payload
 * pickle can take is still taken, and fails as pickle fails otherwise.
 * `loads(data)` reads either: data starting with MAGIC is this format, anything else pickle.
 *
 * The format: MAGIC, then one value. A value is a tag byte and its body; lengths, ints and
 * doubles are 8 bytes in the machine's byte order (the bytes never leave the machine: the
 * simulation writes them to its recorder process's pipe).
 *   'd' n, then n (key, value) pairs, in the dict's order   'l' n, then n values (a list)
 *   'F' n, then n doubles (a list of n >= 1 floats only)       't' n, then n values (a tuple)
 *   'f' double   'i' int64   's' n, then n bytes of UTF-8   'T' True   'X' False   'N' None
 * Floats are their 8 bytes, so every double (-0.0, NaN payloads, infinities) comes back bit for
 * bit. A dict is rebuilt in its order with the same keys; lists, tuples, strings, ints and
 * floats come back as the same types with equal values.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

#define MAGIC 'S' /* pickle protocol 2+ starts with 0x80 */
#define MAX_DEPTH 64

static PyObject *pickle_dumps, *pickle_loads, *pickle_protocol;

/* --- writing ------------------------------------------------------------------------------ */

typedef struct {
    char *data;
    Py_ssize_t len, cap;
} Buffer;

static Buffer buf; /* reused across calls: only Python objects of exact built-in types are read
                      while it is filled, so no Python code runs and no other call interleaves */

/* room for n more bytes; 0 on memory error (no Python error set) */
static int reserve(Py_ssize_t n)
{
    if (buf.len + n <= buf.cap) return 1;
    Py_ssize_t cap = buf.cap ? buf.cap : 4096;
    while (cap < buf.len + n) cap *= 2;
    char *d = PyMem_Realloc(buf.data, cap);
    if (!d) return 0;
    buf.data = d;
    buf.cap = cap;
    return 1;
}

static int put_tag_len(char tag, int64_t v)
{
    if (!reserve(1 + 8)) return 0;
    buf.data[buf.len] = tag;
    memcpy(buf.data + buf.len + 1, &v, 8);
    buf.len += 9;
    return 1;
}

/* 1: written; 0: not this format (unsupported value, memory) - the caller falls back to pickle */
static int put(PyObject *o, int depth)
{
    if (depth > MAX_DEPTH) return 0;
    if (PyFloat_CheckExact(o)) {
        double d = PyFloat_AS_DOUBLE(o);
        if (!reserve(9)) return 0;
        buf.data[buf.len] = 'f';
        memcpy(buf.data + buf.len + 1, &d, 8);
        buf.len += 9;
        return 1;
    }
    if (PyList_CheckExact(o)) {
        Py_ssize_t n = PyList_GET_SIZE(o), i;
        for (i = 0; i < n; i++)
            if (!PyFloat_CheckExact(PyList_GET_ITEM(o, i))) break;
        if (n > 0 && i == n) { /* all floats: their doubles in a row */
            if (!put_tag_len('F', n) || !reserve(8 * n)) return 0;
            double *out = (double *)(buf.data + buf.len); /* memcpy per element: no alignment needed */
            for (i = 0; i < n; i++) {
                double d = PyFloat_AS_DOUBLE(PyList_GET_ITEM(o, i));
                memcpy((char *)out + 8 * i, &d, 8);
            }
            buf.len += 8 * n;
            return 1;
        }
        if (!put_tag_len('l', n)) return 0;
        for (i = 0; i < n; i++) /* the list cannot change: no Python code runs here */
            if (!put(PyList_GET_ITEM(o, i), depth + 1)) return 0;
        return 1;
    }
    if (PyDict_CheckExact(o)) {
        Py_ssize_t pos = 0;
        PyObject *k, *v;
        if (!put_tag_len('d', PyDict_GET_SIZE(o))) return 0;
        while (PyDict_Next(o, &pos, &k, &v))
            if (!put(k, depth + 1) || !put(v, depth + 1)) return 0;
        return 1;
    }
    if (PyUnicode_CheckExact(o)) {
        Py_ssize_t n;
        const char *s = PyUnicode_AsUTF8AndSize(o, &n);
        if (!s) { /* a lone surrogate: pickle's business */
            PyErr_Clear();
            return 0;
        }
        if (!put_tag_len('s', n) || !reserve(n)) return 0;
        memcpy(buf.data + buf.len, s, n);
        buf.len += n;
        return 1;
    }
    if (PyLong_CheckExact(o)) {
        int overflow;
        long long v = PyLong_AsLongLongAndOverflow(o, &overflow);
        if (overflow) return 0;
        if (v == -1 && PyErr_Occurred()) {
            PyErr_Clear();
            return 0;
        }
        return put_tag_len('i', (int64_t)v);
    }
    if (o == Py_True || o == Py_False || o == Py_None) {
        if (!reserve(1)) return 0;
        buf.data[buf.len++] = o == Py_True ? 'T' : o == Py_False ? 'X' : 'N';
        return 1;
    }
    if (PyTuple_CheckExact(o)) {
        Py_ssize_t n = PyTuple_GET_SIZE(o);
        if (!put_tag_len('t', n)) return 0;
        for (Py_ssize_t i = 0; i < n; i++)
            if (!put(PyTuple_GET_ITEM(o, i), depth + 1)) return 0;
        return 1;
    }
    return 0;
}

/* dumps(obj) -> bytes; see the comment at the top */
static PyObject *dumps(PyObject *self, PyObject *obj)
{
    buf.len = 0;
    if (reserve(1)) {
        buf.data[buf.len++] = MAGIC;
        if (put(obj, 0)) return PyBytes_FromStringAndSize(buf.data, buf.len);
    }
    return PyObject_CallFunctionObjArgs(pickle_dumps, obj, pickle_protocol, NULL);
}

/* --- reading ------------------------------------------------------------------------------ */

typedef struct {
    const char *p, *end;
} Reader;

static PyObject *truncated(void)
{
    PyErr_SetString(PyExc_ValueError, "snapshot data is truncated or malformed");
    return NULL;
}

static int get_len(Reader *r, Py_ssize_t *n)
{
    int64_t v;
    if (r->end - r->p < 8) return 0;
    memcpy(&v, r->p, 8);
    r->p += 8;
    if (v < 0) return 0;
    *n = (Py_ssize_t)v;
    return 1;
}

static PyObject *get(Reader *r, int depth)
{
    Py_ssize_t n, i;
    if (depth > MAX_DEPTH || r->p >= r->end) return truncated();
    char tag = *r->p++;
    switch (tag) {
    case 'f': {
        double d;
        if (r->end - r->p < 8) return truncated();
        memcpy(&d, r->p, 8);
        r->p += 8;
        return PyFloat_FromDouble(d);
    }
    case 'F': {
        if (!get_len(r, &n) || (r->end - r->p) / 8 < n) return truncated();
        PyObject *l = PyList_New(n);
        if (!l) return NULL;
        for (i = 0; i < n; i++) {
            double d;
            memcpy(&d, r->p + 8 * i, 8);
            PyObject *f = PyFloat_FromDouble(d);
            if (!f) {
                Py_DECREF(l);
                return NULL;
            }
            PyList_SET_ITEM(l, i, f);
        }
        r->p += 8 * n;
        return l;
    }
    case 'l':
    case 't': {
        if (!get_len(r, &n) || r->end - r->p < n) return truncated(); /* each value >= 1 byte */
        PyObject *c = tag == 'l' ? PyList_New(n) : PyTuple_New(n);
        if (!c) return NULL;
        for (i = 0; i < n; i++) {
            PyObject *v = get(r, depth + 1);
            if (!v) {
                Py_DECREF(c);
                return NULL;
            }
            if (tag == 'l')
                PyList_SET_ITEM(c, i, v);
            else
                PyTuple_SET_ITEM(c, i, v);
        }
        return c;
    }
    case 'd': {
        if (!get_len(r, &n) || (r->end - r->p) / 2 < n) return truncated();
        PyObject *d = PyDict_New();
        if (!d) return NULL;
        for (i = 0; i < n; i++) {
            PyObject *k = get(r, depth + 1), *v = k ? get(r, depth + 1) : NULL;
            if (!v || PyDict_SetItem(d, k, v) < 0) {
                Py_XDECREF(k);
                Py_XDECREF(v);
                Py_DECREF(d);
                return NULL;
            }
            Py_DECREF(k);
            Py_DECREF(v);
        }
        return d;
    }
    case 's': {
        if (!get_len(r, &n) || r->end - r->p < n) return truncated();
        PyObject *s = PyUnicode_DecodeUTF8(r->p, n, "strict");
        r->p += n;
        return s;
    }
    case 'i': {
        int64_t v;
        if (r->end - r->p < 8) return truncated();
        memcpy(&v, r->p, 8);
        r->p += 8;
        return PyLong_FromLongLong(v);
    }
    case 'T':
        Py_RETURN_TRUE;
    case 'X':
        Py_RETURN_FALSE;
    case 'N':
        Py_RETURN_NONE;
    }
    return truncated();
}

/* loads(data) -> object; see the comment at the top */
static PyObject *loads(PyObject *self, PyObject *arg)
{
    Py_buffer view;
    if (PyObject_GetBuffer(arg, &view, PyBUF_SIMPLE) < 0) return NULL;
    PyObject *out;
    if (view.len > 0 && ((const char *)view.buf)[0] == MAGIC) {
        Reader r = {(const char *)view.buf + 1, (const char *)view.buf + view.len};
        out = get(&r, 0);
        if (out && r.p != r.end) {
            Py_DECREF(out);
            out = truncated();
        }
    } else {
        out = PyObject_CallOneArg(pickle_loads, arg);
    }
    PyBuffer_Release(&view);
    return out;
}

static PyMethodDef methods[] = {
    {"dumps", dumps, METH_O, "dumps(obj) -> bytes: a snapshot of a plain payload (else its pickle)"},
    {"loads", loads, METH_O, "loads(data) -> object: a snapshot or a pickle read back"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_snapshot_c", NULL, -1, methods};

PyMODINIT_FUNC PyInit__snapshot_c(void)
{
    PyObject *pickle = PyImport_ImportModule("pickle");
    if (!pickle) return NULL;
    pickle_dumps = PyObject_GetAttrString(pickle, "dumps");
    pickle_loads = PyObject_GetAttrString(pickle, "loads");
    pickle_protocol = PyObject_GetAttrString(pickle, "HIGHEST_PROTOCOL");
    Py_DECREF(pickle);
    if (!pickle_dumps || !pickle_loads || !pickle_protocol) return NULL;
    return PyModule_Create(&module);
}
