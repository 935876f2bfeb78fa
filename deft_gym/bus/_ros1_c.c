/* A payload's ROS 1 bytes and back, compiled (deft_gym/bus/ros1.py: `encode` and `_put`, the same
 * bytes; `decoder`'s `decode` and `_reader`, the same values).
 *
 * encode(program, payload) walks `program` - (fields, rest): fields a tuple of (key, kind, sub-program)
 * with kind 0 float64, 1 int64, 2 bool, 3 string, 4 float64[], 5 object, 6 object[] - over the dict
 * `payload` and returns the little-endian ROS 1 serialisation, or None where the payload does not fit
 * the program exactly (a key other than the program's, in another order, a value of another type, an
 * int beyond int64, a string UTF-8 cannot hold, optional keys whose JSON holds null). The optional
 * keys of an object whose program has `rest` are one JSON object (configure's dumps(extra, **kwargs),
 * orjson) after a uint32 length; none: length 0.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

enum { F64, I64, BOOL_, STR, F64S, OBJ, OBJS };

static PyObject *g_dumps = NULL, *g_kwargs = NULL;

typedef struct {
    unsigned char *p;
    Py_ssize_t n, cap;
} Buf;

static int reserve(Buf *b, Py_ssize_t need) {
    if (b->n + need <= b->cap) return 0;
    Py_ssize_t cap = b->cap ? b->cap : 4096;
    while (cap < b->n + need) cap *= 2;
    unsigned char *q = PyMem_Realloc(b->p, cap);
    if (!q) {
        PyErr_NoMemory();
        return -1;
    }
    b->p = q;
    b->cap = cap;
    return 0;
}

/* the low n bytes of v, little-endian (one store on a little-endian machine) */
static inline void le(unsigned char *p, uint64_t v, int n) {
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    memcpy(p, &v, (size_t)n);
#else
    for (int i = 0; i < n; i++) p[i] = (unsigned char)(v >> (8 * i));
#endif
}

/* a double's 8 bytes, little-endian, at q / read back from q */
static inline void store_f64(unsigned char *q, double d) {
    uint64_t u;
    memcpy(&u, &d, 8);
    le(q, u, 8);
}

static inline uint64_t from_le(const unsigned char *q) {
    uint64_t u;
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
    memcpy(&u, q, 8);
#else
    u = 0;
    for (int i = 7; i >= 0; i--) u = u << 8 | q[i];
#endif
    return u;
}

static inline double load_f64(const unsigned char *q) {
    uint64_t u = from_le(q);
    double d;
    memcpy(&d, &u, 8);
    return d;
}

/* a program's (fields, rest) and a field's (key, kind, sub-program), as encode and decode both walk
 * them; `exc` and `who` name the error of a malformed one (0 on success, -1 with it set) */
static int program_parts(PyObject *program, PyObject *exc, const char *who, PyObject **fields, int *rest) {
    if (!PyTuple_Check(program) || PyTuple_GET_SIZE(program) != 2 || !PyTuple_Check(PyTuple_GET_ITEM(program, 0))) {
        PyErr_Format(exc, "%s: a program is (fields, rest)", who);
        return -1;
    }
    *fields = PyTuple_GET_ITEM(program, 0);
    *rest = PyObject_IsTrue(PyTuple_GET_ITEM(program, 1));
    return *rest < 0 ? -1 : 0;
}

static int field_parts(PyObject *f, PyObject *exc, const char *who, PyObject **key, long *kind, PyObject **sub) {
    if (!PyTuple_Check(f) || PyTuple_GET_SIZE(f) != 3) {
        PyErr_Format(exc, "%s: a field is (key, kind, sub-program)", who);
        return -1;
    }
    *key = PyTuple_GET_ITEM(f, 0);
    *sub = PyTuple_GET_ITEM(f, 2);
    *kind = PyLong_AsLong(PyTuple_GET_ITEM(f, 1));
    return *kind == -1 && PyErr_Occurred() ? -1 : 0;
}

static int put_u32(Buf *b, Py_ssize_t v) {
    if (v < 0 || (uint64_t)v > 0xFFFFFFFFu) return 0; /* struct.error in Python: does not fit */
    if (reserve(b, 4)) return -1;
    le(b->p + b->n, (uint64_t)v, 4);
    b->n += 4;
    return 1;
}

static int put_f64(Buf *b, double d) {
    if (reserve(b, 8)) return -1;
    store_f64(b->p + b->n, d);
    b->n += 8;
    return 1;
}

static int put_bytes(Buf *b, const char *s, Py_ssize_t n) {
    int r = put_u32(b, n);
    if (r != 1) return r;
    if (reserve(b, n)) return -1;
    memcpy(b->p + b->n, s, (size_t)n);
    b->n += n;
    return 1;
}

/* 1: written, 0: does not fit, -1: an error (exception set) */
static int put(Buf *b, PyObject *program, PyObject *obj);

static int put_rest(Buf *b, PyObject *obj, Py_ssize_t pos) {
    PyObject *extra = PyDict_New();
    if (!extra) return -1;
    PyObject *k, *v;
    while (PyDict_Next(obj, &pos, &k, &v)) {
        if (PyDict_SetItem(extra, k, v) < 0) {
            Py_DECREF(extra);
            return -1;
        }
    }
    if (PyDict_GET_SIZE(extra) == 0) {
        Py_DECREF(extra);
        return put_u32(b, 0);
    }
    PyObject *args = PyTuple_Pack(1, extra);
    Py_DECREF(extra);
    if (!args) return -1;
    PyObject *data = PyObject_Call(g_dumps, args, g_kwargs);
    Py_DECREF(args);
    if (!data) return -1; /* a TypeError (no JSON form) is "does not fit": encode decides */
    if (!PyBytes_Check(data)) {
        Py_DECREF(data);
        return 0;
    }
    Py_ssize_t n = PyBytes_GET_SIZE(data);
    const char *d = PyBytes_AS_STRING(data);
    for (Py_ssize_t i = 0; i + 4 <= n; i++) {
        if (d[i] == 'n' && memcmp(d + i, "null", 4) == 0) { /* a non-finite float (or a None) */
            Py_DECREF(data);
            return 0;
        }
    }
    int r = put_bytes(b, d, n);
    Py_DECREF(data);
    return r;
}

static int put(Buf *b, PyObject *program, PyObject *obj) {
    PyObject *fields;
    int rest;
    if (program_parts(program, PyExc_ValueError, "encode", &fields, &rest)) return -1;
    if (!PyDict_CheckExact(obj)) return 0;
    Py_ssize_t nf = PyTuple_GET_SIZE(fields), nd = PyDict_GET_SIZE(obj);
    if (nd < nf || (!rest && nd != nf)) return 0;
    Py_ssize_t pos = 0;
    PyObject *k, *v;
    for (Py_ssize_t i = 0; i < nf; i++) {
        PyObject *key, *sub;
        long kind;
        if (field_parts(PyTuple_GET_ITEM(fields, i), PyExc_ValueError, "encode", &key, &kind, &sub)) return -1;
        if (!PyDict_Next(obj, &pos, &k, &v)) return 0;
        if (k != key) {
            int ne = PyObject_RichCompareBool(k, key, Py_NE);
            if (ne < 0) return -1;
            if (ne) return 0;
        }
        int r;
        switch (kind) {
        case F64:
            if (!PyFloat_CheckExact(v)) return 0;
            r = put_f64(b, PyFloat_AS_DOUBLE(v));
            break;
        case I64: {
            if (!PyLong_CheckExact(v)) return 0;
            int overflow = 0;
            long long x = PyLong_AsLongLongAndOverflow(v, &overflow);
            if (overflow) return 0;
            if (x == -1 && PyErr_Occurred()) return -1;
            if (reserve(b, 8)) return -1;
            le(b->p + b->n, (uint64_t)x, 8);
            b->n += 8;
            r = 1;
            break;
        }
        case BOOL_:
            if (!PyBool_Check(v)) return 0;
            if (reserve(b, 1)) return -1;
            b->p[b->n++] = (unsigned char)(v == Py_True);
            r = 1;
            break;
        case STR: {
            if (!PyUnicode_CheckExact(v)) return 0;
            Py_ssize_t n;
            const char *s = PyUnicode_AsUTF8AndSize(v, &n);
            if (!s) return -1; /* UnicodeEncodeError: encode decides */
            r = put_bytes(b, s, n);
            break;
        }
        case F64S: {
            if (!PyList_CheckExact(v)) return 0;
            Py_ssize_t n = PyList_GET_SIZE(v);
            r = put_u32(b, n);
            if (r != 1) return r;
            if (reserve(b, 8 * n)) return -1;
            unsigned char *q = b->p + b->n; /* one pass: a value that is not a float ends it (None) */
            for (Py_ssize_t j = 0; j < n; j++, q += 8) {
                PyObject *x = PyList_GET_ITEM(v, j);
                if (!PyFloat_CheckExact(x)) return 0;
                store_f64(q, PyFloat_AS_DOUBLE(x));
            }
            b->n += 8 * n;
            break;
        }
        case OBJ:
            r = put(b, sub, v);
            break;
        case OBJS: {
            if (!PyList_CheckExact(v)) return 0;
            Py_ssize_t n = PyList_GET_SIZE(v);
            r = put_u32(b, n);
            for (Py_ssize_t j = 0; r == 1 && j < n; j++) {
                PyObject *item = PyList_GET_ITEM(v, j);
                Py_INCREF(item);
                r = put(b, sub, item);
                Py_DECREF(item);
            }
            break;
        }
        default:
            PyErr_Format(PyExc_ValueError, "encode: unknown field kind %ld", kind);
            return -1;
        }
        if (r != 1) return r;
    }
    if (!rest) return 1;
    return nd == nf ? put_u32(b, 0) : put_rest(b, obj, pos); /* no optional keys: length 0 */
}

static PyObject *encode(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "encode(program, payload)");
        return NULL;
    }
    if (!g_dumps) {
        PyErr_SetString(PyExc_RuntimeError, "encode: configure(dumps, kwargs, loads) first");
        return NULL;
    }
    Buf b = {NULL, 0, 0};
    int r = put(&b, args[0], args[1]);
    PyObject *out = NULL;
    if (r == 1) {
        out = PyBytes_FromStringAndSize((const char *)b.p, b.n);
    } else if (r == 0) {
        out = Py_NewRef(Py_None);
    } else if (PyErr_ExceptionMatches(PyExc_TypeError) || PyErr_ExceptionMatches(PyExc_UnicodeEncodeError) ||
               PyErr_ExceptionMatches(PyExc_OverflowError)) {
        PyErr_Clear(); /* as the Python version's except: the payload has no ROS 1 form here */
        out = Py_NewRef(Py_None);
    }
    PyMem_Free(b.p);
    return out;
}

/* ---- reading: decode(program, data) -> dict (ros1.py's _reader and decoder's decode, the same values) ---- */

static PyObject *g_loads = NULL;

static PyObject *bad(const char *what) {
    PyErr_Format(PyExc_ValueError, "not a message of its ros1 schema: %s", what);
    return NULL;
}

static int take_u32(const unsigned char *p, Py_ssize_t n, Py_ssize_t *off, Py_ssize_t *out) {
    if (*off > n - 4) {
        bad("a count runs past the end of the message");
        return -1;
    }
    uint32_t v;
    memcpy(&v, p + *off, 4);
#if !(defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__)
    v = (uint32_t)p[*off] | (uint32_t)p[*off + 1] << 8 | (uint32_t)p[*off + 2] << 16 | (uint32_t)p[*off + 3] << 24;
#endif
    *off += 4;
    *out = (Py_ssize_t)v;
    return 0;
}

static PyObject *get(const unsigned char *p, Py_ssize_t n, Py_ssize_t *off, PyObject *program) {
    PyObject *fields;
    int rest;
    if (program_parts(program, PyExc_TypeError, "decode", &fields, &rest)) return NULL;
    PyObject *out = PyDict_New();
    if (!out) return NULL;
    Py_ssize_t nf = PyTuple_GET_SIZE(fields);
    for (Py_ssize_t i = 0; i < nf; i++) {
        PyObject *key, *sub, *v = NULL;
        long kind;
        if (field_parts(PyTuple_GET_ITEM(fields, i), PyExc_TypeError, "decode", &key, &kind, &sub)) goto fail;
        switch (kind) {
        case F64:
        case I64:
            if (*off > n - 8) {
                bad("a number runs past the end of the message");
                goto fail;
            }
            if (kind == F64) {
                v = PyFloat_FromDouble(load_f64(p + *off));
            } else {
                v = PyLong_FromLongLong((long long)from_le(p + *off));
            }
            *off += 8;
            break;
        case BOOL_:
            if (*off > n - 1) {
                bad("a bool runs past the end of the message");
                goto fail;
            }
            v = PyBool_FromLong(p[(*off)++] != 0);
            break;
        case STR: {
            Py_ssize_t len;
            if (take_u32(p, n, off, &len)) goto fail;
            if (len > n - *off) {
                bad("a string runs past the end of the message");
                goto fail;
            }
            v = PyUnicode_DecodeUTF8((const char *)p + *off, len, "strict");
            if (!v) { /* UnicodeDecodeError: a ValueError, as the Python version's */
                PyObject *type, *value, *tb;
                PyErr_Fetch(&type, &value, &tb);
                Py_XDECREF(type);
                Py_XDECREF(tb);
                PyObject *text = value ? PyObject_Str(value) : NULL;
                Py_XDECREF(value);
                PyErr_Format(PyExc_ValueError, "not a message of its ros1 schema: %S", text ? text : Py_None);
                Py_XDECREF(text);
                goto fail;
            }
            *off += len;
            break;
        }
        case F64S: {
            Py_ssize_t len;
            if (take_u32(p, n, off, &len)) goto fail;
            if (len > (n - *off) / 8) {
                bad("a float64[] runs past the end of the message");
                goto fail;
            }
            v = PyList_New(len);
            if (!v) goto fail;
            for (Py_ssize_t j = 0; j < len; j++) {
                PyObject *x = PyFloat_FromDouble(load_f64(p + *off + 8 * j));
                if (!x) {
                    Py_DECREF(v);
                    goto fail;
                }
                PyList_SET_ITEM(v, j, x);
            }
            *off += 8 * len;
            break;
        }
        case OBJ:
            v = get(p, n, off, sub);
            break;
        case OBJS: {
            Py_ssize_t len;
            if (take_u32(p, n, off, &len)) goto fail;
            v = PyList_New(0); /* (a count past the data fails at its first object, as in Python) */
            for (Py_ssize_t j = 0; v && j < len; j++) {
                PyObject *item = get(p, n, off, sub);
                if (!item || PyList_Append(v, item) < 0) {
                    Py_XDECREF(item);
                    Py_CLEAR(v);
                    break;
                }
                Py_DECREF(item);
            }
            break;
        }
        default:
            PyErr_Format(PyExc_TypeError, "decode: unknown field kind %ld", kind);
            goto fail;
        }
        if (!v) goto fail;
        int err = PyDict_SetItem(out, key, v);
        Py_DECREF(v);
        if (err < 0) goto fail;
    }
    if (rest) {
        Py_ssize_t len;
        if (take_u32(p, n, off, &len)) goto fail;
        if (len) {
            if (len > n - *off) {
                bad("the JSON part runs past the end of the message");
                goto fail;
            }
            PyObject *text = PyBytes_FromStringAndSize((const char *)p + *off, len);
            PyObject *extra = text ? PyObject_CallOneArg(g_loads, text) : NULL;
            Py_XDECREF(text);
            if (!extra) goto fail;
            if (!PyDict_Check(extra)) {
                Py_DECREF(extra);
                PyErr_SetString(PyExc_ValueError, "json_rest is not a JSON object");
                goto fail;
            }
            int err = PyDict_Update(out, extra);
            Py_DECREF(extra);
            if (err < 0) goto fail;
            *off += len;
        }
    }
    return out;
fail:
    Py_DECREF(out);
    return NULL;
}

static PyObject *decode(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "decode(program, data)");
        return NULL;
    }
    if (!g_loads) {
        PyErr_SetString(PyExc_RuntimeError, "decode: configure(dumps, kwargs, loads) first");
        return NULL;
    }
    Py_buffer view;
    if (PyObject_GetBuffer(args[1], &view, PyBUF_SIMPLE) < 0) return NULL;
    Py_ssize_t off = 0;
    PyObject *out = get((const unsigned char *)view.buf, view.len, &off, args[0]);
    if (out && off != view.len) {
        Py_DECREF(out);
        out = NULL;
        PyErr_Format(PyExc_ValueError, "not a message of its ros1 schema: %zd byte(s) after its end", view.len - off);
    }
    PyBuffer_Release(&view);
    return out;
}

static PyObject *configure(PyObject *mod, PyObject *args) {
    PyObject *dumps, *kwargs, *loads;
    if (!PyArg_ParseTuple(args, "OO!O", &dumps, &PyDict_Type, &kwargs, &loads)) return NULL;
    if (!PyCallable_Check(dumps) || !PyCallable_Check(loads)) {
        PyErr_SetString(PyExc_TypeError, "configure: dumps and loads must be callable");
        return NULL;
    }
    Py_XSETREF(g_dumps, Py_NewRef(dumps));
    Py_XSETREF(g_kwargs, Py_NewRef(kwargs));
    Py_XSETREF(g_loads, Py_NewRef(loads));
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"encode", (PyCFunction)(void (*)(void))encode, METH_FASTCALL,
     "encode(program, payload) -> bytes | None: the payload's ROS 1 bytes (ros1.py's encode)"},
    {"decode", (PyCFunction)(void (*)(void))decode, METH_FASTCALL,
     "decode(program, data) -> dict: the payload of ROS 1 bytes (ros1.py's decoder); ValueError if they are not one"},
    {"configure", configure, METH_VARARGS,
     "configure(dumps, kwargs, loads): how optional keys become JSON and are read back"},
    {NULL, NULL, 0, NULL},
};

/* the SHA-256 digests of the sources this build was made from (setup.py defines BUILT_FROM as
 * "<digest of this file> <digest of ros1.py>"; deft_gym.files.stale_kernel compares them) */
#ifndef BUILT_FROM
#define BUILT_FROM ""
#endif

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_ros1_c", NULL, -1, methods};

PyMODINIT_FUNC PyInit__ros1_c(void) {
    PyObject *m = PyModule_Create(&module);
    if (!m) return NULL;
    if (PyModule_AddStringConstant(m, "BUILT_FROM", BUILT_FROM) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
