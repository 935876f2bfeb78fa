/* Payload snapshots for the recorder process (deft_gym/record/worker.py): a message payload
 * as bytes at its publish time, read back in the recorder process. About three times faster
 * than pickle for the bus's payloads, which are dicts of lists of floats.
 *
 * `Batch(limit, flush)` is the recorder's bus tap: called with a message, it appends the
 * message's entry (topic, publish time, sequence number, `dumps(payload)`) to its buffer, with
 * no Python frame and no object per message, and calls `flush()` when it holds `limit`
 * messages; `take()` returns the entries as bytes. `read_batch(data)` reads them back.
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
#include <structmember.h>
#include <string.h>

#define MAGIC 'S' /* pickle protocol 2+ starts with 0x80 */
#define MAX_DEPTH 64

static PyObject *pickle_dumps, *pickle_loads, *pickle_protocol;

/* --- writing ------------------------------------------------------------------------------ */

typedef struct {
    char *data;
    Py_ssize_t len, cap;
} Buffer;

static Buffer scratch; /* dumps' buffer, reused across calls: only Python objects of exact
                          built-in types are read while it is filled, so no Python code runs
                          and no other call interleaves */

/* room for n more bytes; 0 on memory error (no Python error set) */
static int reserve(Buffer *b, Py_ssize_t n)
{
    if (b->len + n <= b->cap) return 1;
    Py_ssize_t cap = b->cap ? b->cap : 4096;
    while (cap < b->len + n) cap *= 2;
    char *d = PyMem_Realloc(b->data, cap);
    if (!d) return 0;
    b->data = d;
    b->cap = cap;
    return 1;
}

static int put_bytes(Buffer *b, const void *p, Py_ssize_t n)
{
    if (!reserve(b, n)) return 0;
    memcpy(b->data + b->len, p, n);
    b->len += n;
    return 1;
}

static int put_i64(Buffer *b, int64_t v) { return put_bytes(b, &v, 8); }

static int put_tag_len(Buffer *b, char tag, int64_t v)
{
    return put_bytes(b, &tag, 1) && put_i64(b, v);
}

/* 1: written; 0: not this format (unsupported value, memory) - the caller falls back to pickle */
static int put(Buffer *b, PyObject *o, int depth)
{
    if (depth > MAX_DEPTH) return 0;
    if (PyFloat_CheckExact(o)) {
        double d = PyFloat_AS_DOUBLE(o);
        return put_bytes(b, "f", 1) && put_bytes(b, &d, 8);
    }
    if (PyList_CheckExact(o)) {
        Py_ssize_t n = PyList_GET_SIZE(o), i;
        for (i = 0; i < n; i++)
            if (!PyFloat_CheckExact(PyList_GET_ITEM(o, i))) break;
        if (n > 0 && i == n) { /* all floats: their doubles in a row */
            if (!put_tag_len(b, 'F', n) || !reserve(b, 8 * n)) return 0;
            char *out = b->data + b->len; /* memcpy per element: no alignment needed */
            for (i = 0; i < n; i++) {
                double d = PyFloat_AS_DOUBLE(PyList_GET_ITEM(o, i));
                memcpy(out + 8 * i, &d, 8);
            }
            b->len += 8 * n;
            return 1;
        }
        if (!put_tag_len(b, 'l', n)) return 0;
        for (i = 0; i < n; i++) /* the list cannot change: no Python code runs here */
            if (!put(b, PyList_GET_ITEM(o, i), depth + 1)) return 0;
        return 1;
    }
    if (PyDict_CheckExact(o)) {
        Py_ssize_t pos = 0;
        PyObject *k, *v;
        if (!put_tag_len(b, 'd', PyDict_GET_SIZE(o))) return 0;
        while (PyDict_Next(o, &pos, &k, &v))
            if (!put(b, k, depth + 1) || !put(b, v, depth + 1)) return 0;
        return 1;
    }
    if (PyUnicode_CheckExact(o)) {
        Py_ssize_t n;
        const char *s = PyUnicode_AsUTF8AndSize(o, &n);
        if (!s) { /* a lone surrogate: pickle's business */
            PyErr_Clear();
            return 0;
        }
        return put_tag_len(b, 's', n) && put_bytes(b, s, n);
    }
    if (PyLong_CheckExact(o)) {
        int overflow;
        long long v = PyLong_AsLongLongAndOverflow(o, &overflow);
        if (overflow) return 0;
        if (v == -1 && PyErr_Occurred()) {
            PyErr_Clear();
            return 0;
        }
        return put_tag_len(b, 'i', (int64_t)v);
    }
    if (o == Py_True || o == Py_False || o == Py_None)
        return put_bytes(b, o == Py_True ? "T" : o == Py_False ? "X" : "N", 1);
    if (PyTuple_CheckExact(o)) {
        Py_ssize_t n = PyTuple_GET_SIZE(o);
        if (!put_tag_len(b, 't', n)) return 0;
        for (Py_ssize_t i = 0; i < n; i++)
            if (!put(b, PyTuple_GET_ITEM(o, i), depth + 1)) return 0;
        return 1;
    }
    return 0;
}

/* dumps(obj) -> bytes; see the comment at the top */
static PyObject *dumps(PyObject *self, PyObject *obj)
{
    scratch.len = 0;
    if (put_bytes(&scratch, &(char){MAGIC}, 1) && put(&scratch, obj, 0))
        return PyBytes_FromStringAndSize(scratch.data, scratch.len);
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

/* the next 8 bytes (a double or an int64) into *out; 0 when there are fewer */
static int get8(Reader *r, void *out)
{
    if (r->end - r->p < 8) return 0;
    memcpy(out, r->p, 8);
    r->p += 8;
    return 1;
}

static int get_len(Reader *r, Py_ssize_t *n)
{
    int64_t v;
    if (!get8(r, &v) || v < 0) return 0;
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
        return get8(r, &d) ? PyFloat_FromDouble(d) : truncated();
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
        return get8(r, &v) ? PyLong_FromLongLong(v) : truncated();
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

/* the object of the n bytes at p: a snapshot, or else a pickle */
static PyObject *load(const char *p, Py_ssize_t n)
{
    if (n > 0 && p[0] == MAGIC) {
        Reader r = {p + 1, p + n};
        PyObject *out = get(&r, 0);
        if (out && r.p != r.end) {
            Py_DECREF(out);
            return truncated();
        }
        return out;
    }
    PyObject *view = PyMemoryView_FromMemory((char *)p, n, PyBUF_READ), *out = NULL;
    if (view) {
        out = PyObject_CallOneArg(pickle_loads, view);
        Py_DECREF(view);
    }
    return out;
}

/* loads(data) -> object; see the comment at the top */
static PyObject *loads(PyObject *self, PyObject *arg)
{
    Py_buffer view;
    if (PyObject_GetBuffer(arg, &view, PyBUF_SIMPLE) < 0) return NULL;
    PyObject *out = load(view.buf, view.len);
    PyBuffer_Release(&view);
    return out;
}

/* --- batches of messages -------------------------------------------------------------------
 * A batch is the entries of messages in publish order. An entry: the topic (length, UTF-8), the
 * publish time [ns], the sequence number, the payload (length, then its dumps() bytes). */

static PyObject *str_topic, *str_publish_ns, *str_seq, *str_payload;

typedef struct {
    PyObject_HEAD
    vectorcallfunc vectorcall;
    Buffer buf;
    Py_ssize_t count, limit, total;
    PyObject *flush;
} Batch;

/* the int attribute `name` of msg as an int64, into *v; 0 with an error set if it is not one */
static int int_attr(PyObject *msg, PyObject *name, int64_t *v)
{
    PyObject *o = PyObject_GetAttr(msg, name);
    if (!o) return 0;
    long long x = PyLong_AsLongLong(o);
    Py_DECREF(o);
    if (x == -1 && PyErr_Occurred()) return 0;
    *v = x;
    return 1;
}

/* append msg's entry; 0 with an error set on failure (the batch is then as before) */
static int append(Batch *self, PyObject *msg)
{
    Buffer *b = &self->buf;
    Py_ssize_t start = b->len, n;
    int64_t ns, seq;
    PyObject *topic = PyObject_GetAttr(msg, str_topic), *payload = NULL, *pickled = NULL;
    if (!topic) return 0;
    const char *t = PyUnicode_Check(topic) ? PyUnicode_AsUTF8AndSize(topic, &n) : NULL;
    if (!t) {
        if (!PyErr_Occurred()) PyErr_SetString(PyExc_TypeError, "a message topic must be a str");
        goto fail;
    }
    if (!int_attr(msg, str_publish_ns, &ns) || !int_attr(msg, str_seq, &seq)) goto fail;
    if (!(payload = PyObject_GetAttr(msg, str_payload))) goto fail;
    if (!put_i64(b, n) || !put_bytes(b, t, n) || !put_i64(b, ns) || !put_i64(b, seq) || !put_i64(b, 0)) {
        PyErr_NoMemory();
        goto fail;
    }
    Py_ssize_t at = b->len; /* the payload's bytes start here; its length goes just before */
    if (!put_bytes(b, &(char){MAGIC}, 1) || !put(b, payload, 0)) {
        b->len = at;
        Py_ssize_t m;
        char *data;
        if (!(pickled = PyObject_CallFunctionObjArgs(pickle_dumps, payload, pickle_protocol, NULL)) ||
            PyBytes_AsStringAndSize(pickled, &data, &m) < 0)
            goto fail;
        if (!put_bytes(b, data, m)) {
            PyErr_NoMemory();
            goto fail;
        }
    }
    int64_t size = b->len - at;
    memcpy(b->data + at - 8, &size, 8);
    Py_DECREF(topic);
    Py_DECREF(payload);
    Py_XDECREF(pickled);
    return 1;
fail:
    b->len = start;
    Py_DECREF(topic);
    Py_XDECREF(payload);
    Py_XDECREF(pickled);
    return 0;
}

/* batch(msg): append its entry; calls flush() when the batch holds `limit` messages */
static PyObject *Batch_vectorcall(PyObject *op, PyObject *const *args, size_t nargsf, PyObject *kwnames)
{
    Batch *self = (Batch *)op;
    if (PyVectorcall_NARGS(nargsf) != 1 || kwnames) {
        PyErr_SetString(PyExc_TypeError, "Batch takes one message");
        return NULL;
    }
    if (!append(self, args[0])) return NULL;
    self->total++;
    if (++self->count >= self->limit) return PyObject_CallNoArgs(self->flush);
    Py_RETURN_NONE;
}

static PyObject *Batch_new(PyTypeObject *type, PyObject *args, PyObject *kw)
{
    static char *names[] = {"limit", "flush", NULL};
    Py_ssize_t limit;
    PyObject *flush;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "nO:Batch", names, &limit, &flush)) return NULL;
    if (limit < 1 || !PyCallable_Check(flush)) {
        PyErr_SetString(PyExc_ValueError, "Batch(limit, flush): limit >= 1 and a callable flush");
        return NULL;
    }
    Batch *self = (Batch *)type->tp_alloc(type, 0);
    if (!self) return NULL;
    self->vectorcall = Batch_vectorcall;
    self->limit = limit;
    Py_INCREF(flush);
    self->flush = flush;
    return (PyObject *)self;
}

static void Batch_dealloc(Batch *self)
{
    PyObject_GC_UnTrack(self);
    Py_CLEAR(self->flush);
    PyMem_Free(self->buf.data);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int Batch_traverse(Batch *self, visitproc visit, void *arg)
{
    Py_VISIT(self->flush);
    return 0;
}

static int Batch_clear(Batch *self)
{
    Py_CLEAR(self->flush);
    return 0;
}

/* take() -> bytes: the entries so far; the batch is then empty */
static PyObject *Batch_take(Batch *self, PyObject *unused)
{
    PyObject *out = PyBytes_FromStringAndSize(self->buf.data ? self->buf.data : "", self->buf.len);
    if (out) self->buf.len = self->count = 0;
    return out;
}

static PyMethodDef Batch_methods[] = {
    {"take", (PyCFunction)Batch_take, METH_NOARGS, "take() -> bytes: the entries so far (the batch is then empty)"},
    {NULL, NULL, 0, NULL},
};

static PyMemberDef Batch_members[] = {
    {"count", T_PYSSIZET, offsetof(Batch, count), READONLY, "messages in the batch"},
    {"total", T_PYSSIZET, offsetof(Batch, total), READONLY, "messages appended since the batch was made"},
    {"limit", T_PYSSIZET, offsetof(Batch, limit), READONLY, "the count at which flush() is called"},
    {NULL, 0, 0, 0, NULL},
};

static PyTypeObject BatchType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "deft_gym.record._snapshot_c.Batch",
    .tp_doc = "Batch(limit, flush): a bus tap appending each message's entry (its payload as dumps() "
              "writes it) to a buffer; flush() is called when it holds `limit` messages, and take() "
              "returns the entries.",
    .tp_basicsize = sizeof(Batch),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_HAVE_VECTORCALL,
    .tp_new = Batch_new,
    .tp_dealloc = (destructor)Batch_dealloc,
    .tp_free = PyObject_GC_Del,
    .tp_traverse = (traverseproc)Batch_traverse,
    .tp_clear = (inquiry)Batch_clear,
    .tp_call = PyVectorcall_Call,
    .tp_vectorcall_offset = offsetof(Batch, vectorcall),
    .tp_methods = Batch_methods,
    .tp_members = Batch_members,
};

/* read_batch(data) -> [(topic, publish_ns, payload, seq), ...]: a batch's entries read back */
static PyObject *read_batch(PyObject *self, PyObject *arg)
{
    Py_buffer view;
    if (PyObject_GetBuffer(arg, &view, PyBUF_SIMPLE) < 0) return NULL;
    Reader r = {view.buf, (const char *)view.buf + view.len};
    PyObject *out = PyList_New(0);
    while (out && r.p < r.end) {
        Py_ssize_t n, m;
        int64_t ns, seq;
        if (!get_len(&r, &n) || r.end - r.p < 16 || r.end - r.p - 16 < n) goto bad;
        PyObject *topic = PyUnicode_DecodeUTF8(r.p, n, "strict");
        r.p += n;
        memcpy(&ns, r.p, 8);
        memcpy(&seq, r.p + 8, 8);
        r.p += 16;
        PyObject *payload = NULL, *entry = NULL;
        if (topic && get_len(&r, &m) && r.end - r.p >= m) {
            payload = load(r.p, m);
            r.p += m;
        } else if (topic) {
            Py_DECREF(topic);
            goto bad;
        }
        if (payload) entry = Py_BuildValue("(NLNL)", topic, (long long)ns, payload, (long long)seq);
        else Py_XDECREF(topic);
        if (!entry || PyList_Append(out, entry) < 0) Py_CLEAR(out);
        Py_XDECREF(entry);
    }
    PyBuffer_Release(&view);
    return out;
bad:
    Py_DECREF(out);
    PyBuffer_Release(&view);
    return truncated();
}

static PyMethodDef methods[] = {
    {"dumps", dumps, METH_O, "dumps(obj) -> bytes: a snapshot of a plain payload (else its pickle)"},
    {"loads", loads, METH_O, "loads(data) -> object: a snapshot or a pickle read back"},
    {"read_batch", read_batch, METH_O, "read_batch(data) -> [(topic, publish_ns, payload, seq), ...]"},
    {NULL, NULL, 0, NULL},
};

/* the SHA-256 digests of the sources this build was made from (setup.py defines BUILT_FROM as
   "<digest of this file> <digest of the Python file it mirrors>"); the module that loads it
   refuses a build whose digests differ from the files beside it (a stale kernel) */
#ifndef BUILT_FROM
#define BUILT_FROM ""
#endif

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
    if (!(str_topic = PyUnicode_InternFromString("topic")) ||
        !(str_publish_ns = PyUnicode_InternFromString("publish_ns")) ||
        !(str_seq = PyUnicode_InternFromString("seq")) || !(str_payload = PyUnicode_InternFromString("payload")))
        return NULL;
    if (PyType_Ready(&BatchType) < 0) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m && PyModule_AddObjectRef(m, "Batch", (PyObject *)&BatchType) < 0) Py_CLEAR(m);
    if (m && PyModule_AddStringConstant(m, "BUILT_FROM", BUILT_FROM) < 0) Py_CLEAR(m);
    return m;
}
