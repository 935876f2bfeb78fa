/* The recorder's bus tap, compiled (deft_gym/record/recorder.py: `RecordTap`'s `tap`, the common
 * path). Called with a message whose topic has a channel in `fast`, it encodes the payload - where
 * the entry is (channel id, program) with `bencode(program, payload)` (ROS 1 bytes, None when it
 * does not fit: then `general`), else as JSON with `dumps(payload, **kwargs)` (orjson) - and appends the MCAP Message record's head (opcode 5,
 * record length, channel id, sequence, log time, publish time: struct "<BQHIQQ") and the JSON to
 * `pieces`, the log time (`start_ns` + publish time) to `times` and the channel id to `cids`;
 * once `cids` holds `limit` messages it calls `flush()`. Everything else - a topic without a
 * channel there, a payload orjson cannot encode or whose JSON holds `null` (a non-finite float),
 * a sequence number or time outside the record's fields - goes to `general(msg)`, the Python
 * code that handles it (and raises what the Python version raises). The same bytes as the
 * Python version, with no Python frame per message.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>
#include <stdint.h>

#define HEAD 31 /* 1 + 8 + 2 + 4 + 8 + 8 */

typedef struct {
    PyObject_HEAD
    PyObject *fast, *dumps, *kwargs, *bencode, *general, *flush, *pieces, *times, *cids;
    long long start_ns;
    Py_ssize_t limit;
} Tap;

static PyObject *s_topic, *s_payload, *s_seq, *s_publish_ns;

static void put_le(unsigned char *p, uint64_t v, int n) {
    for (int i = 0; i < n; i++) p[i] = (unsigned char)(v >> (8 * i));
}

static PyObject *general(Tap *self, PyObject *msg) {
    return PyObject_CallOneArg(self->general, msg);
}

static PyObject *Tap_call(Tap *self, PyObject *args, PyObject *kw) {
    PyObject *msg;
    if (!PyArg_UnpackTuple(args, "Tap", 1, 1, &msg)) return NULL;
    PyObject *topic = PyObject_GetAttr(msg, s_topic);
    if (!topic) return NULL;
    PyObject *cid = PyDict_GetItemWithError(self->fast, topic); /* borrowed */
    Py_DECREF(topic);
    if (!cid) {
        if (PyErr_Occurred()) return NULL;
        return general(self, msg);
    }
    PyObject *program = NULL; /* borrowed from the entry */
    if (PyTuple_Check(cid) && PyTuple_GET_SIZE(cid) == 2) {
        program = PyTuple_GET_ITEM(cid, 1);
        cid = PyTuple_GET_ITEM(cid, 0);
    }
    Py_INCREF(cid);
    long c = PyLong_Check(cid) ? PyLong_AsLong(cid) : -1;
    if (c < 0 || c > 0xFFFF) {
        PyErr_Clear();
        Py_DECREF(cid);
        return general(self, msg);
    }
    PyObject *seq_o = PyObject_GetAttr(msg, s_seq);
    PyObject *ns_o = seq_o ? PyObject_GetAttr(msg, s_publish_ns) : NULL;
    if (!ns_o) {
        Py_XDECREF(seq_o);
        Py_DECREF(cid);
        return NULL;
    }
    int overflow = 0;
    long long seq = PyLong_Check(seq_o) ? PyLong_AsLongLongAndOverflow(seq_o, &overflow) : -1;
    long long ns = PyLong_Check(ns_o) ? PyLong_AsLongLongAndOverflow(ns_o, &overflow) : -1;
    Py_DECREF(seq_o);
    Py_DECREF(ns_o);
    if (PyErr_Occurred()) PyErr_Clear();
    /* the record's fields: sequence u32, time u64 (within int64 here; anything else is general's) */
    if (overflow || seq < 0 || seq > 0xFFFFFFFFLL || ns < 0 || ns > INT64_MAX - self->start_ns || self->start_ns < 0) {
        Py_DECREF(cid);
        return general(self, msg);
    }
    long long t = self->start_ns + ns;
    PyObject *payload = PyObject_GetAttr(msg, s_payload);
    if (!payload) {
        Py_DECREF(cid);
        return NULL;
    }
    PyObject *data;
    if (program) { /* ROS 1 bytes, or None: the payload does not fit its layout */
        PyObject *bargs[2] = {program, payload};
        data = PyObject_Vectorcall(self->bencode, bargs, 2, NULL);
        Py_DECREF(payload);
        if (!data) {
            Py_DECREF(cid);
            return NULL;
        }
        if (data == Py_None || !PyBytes_Check(data)) {
            Py_DECREF(data);
            Py_DECREF(cid);
            return general(self, msg);
        }
        goto framed;
    }
    PyObject *pargs = PyTuple_Pack(1, payload);
    Py_DECREF(payload);
    if (!pargs) {
        Py_DECREF(cid);
        return NULL;
    }
    data = PyObject_Call(self->dumps, pargs, self->kwargs);
    Py_DECREF(pargs);
    if (!data) {
        if (!PyErr_ExceptionMatches(PyExc_TypeError)) {
            Py_DECREF(cid);
            return NULL;
        }
        PyErr_Clear(); /* bytes (JSON already), or no JSON form: general decides */
        Py_DECREF(cid);
        return general(self, msg);
    }
    if (!PyBytes_Check(data)) {
        Py_DECREF(data);
        Py_DECREF(cid);
        return general(self, msg);
    }
    Py_ssize_t n = PyBytes_GET_SIZE(data);
    const char *d = PyBytes_AS_STRING(data);
    for (Py_ssize_t i = 0; i + 4 <= n; i++) {
        if (d[i] == 'n' && memcmp(d + i, "null", 4) == 0) { /* a non-finite float (or a None) */
            Py_DECREF(data);
            Py_DECREF(cid);
            return general(self, msg);
        }
    }
framed:;
    Py_ssize_t size = PyBytes_GET_SIZE(data);
    PyObject *head = PyBytes_FromStringAndSize(NULL, HEAD);
    PyObject *t_o = head ? PyLong_FromLongLong(t) : NULL;
    if (!t_o) {
        Py_XDECREF(head);
        Py_DECREF(data);
        Py_DECREF(cid);
        return NULL;
    }
    unsigned char *h = (unsigned char *)PyBytes_AS_STRING(head);
    h[0] = 5;
    put_le(h + 1, (uint64_t)(HEAD - 9 + size), 8);
    put_le(h + 9, (uint64_t)c, 2);
    put_le(h + 11, (uint64_t)seq, 4);
    put_le(h + 15, (uint64_t)t, 8);
    put_le(h + 23, (uint64_t)t, 8);
    int err = PyList_Append(self->pieces, head) || PyList_Append(self->pieces, data) ||
              PyList_Append(self->times, t_o) || PyList_Append(self->cids, cid);
    Py_DECREF(head);
    Py_DECREF(data);
    Py_DECREF(t_o);
    Py_DECREF(cid);
    if (err) return NULL;
    if (PyList_GET_SIZE(self->cids) >= self->limit) return PyObject_CallNoArgs(self->flush);
    Py_RETURN_NONE;
}

static int Tap_init(Tap *self, PyObject *args, PyObject *kw) {
    static char *names[] = {"fast", "start_ns", "dumps", "kwargs", "bencode", "general", "flush", "pieces", "times",
                            "cids", "limit", NULL};
    PyObject *fast, *dumps, *kwargs, *bencode, *gen, *flush, *pieces, *times, *cids;
    long long start_ns;
    Py_ssize_t limit;
    if (!PyArg_ParseTupleAndKeywords(args, kw, "O!LOO!OOOO!O!O!n", names, &PyDict_Type, &fast, &start_ns, &dumps,
                                     &PyDict_Type, &kwargs, &bencode, &gen, &flush, &PyList_Type, &pieces,
                                     &PyList_Type, &times, &PyList_Type, &cids, &limit))
        return -1;
    if (limit < 1 || !PyCallable_Check(dumps) || !PyCallable_Check(bencode) || !PyCallable_Check(gen) ||
        !PyCallable_Check(flush)) {
        PyErr_SetString(PyExc_ValueError, "Tap: limit >= 1 and callables dumps, bencode, general, flush");
        return -1;
    }
    PyObject *old[] = {self->fast, self->dumps, self->kwargs, self->bencode, self->general, self->flush,
                       self->pieces, self->times, self->cids};
    Py_INCREF(fast);
    Py_INCREF(dumps);
    Py_INCREF(kwargs);
    Py_INCREF(bencode);
    Py_INCREF(gen);
    Py_INCREF(flush);
    Py_INCREF(pieces);
    Py_INCREF(times);
    Py_INCREF(cids);
    self->fast = fast;
    self->dumps = dumps;
    self->kwargs = kwargs;
    self->bencode = bencode;
    self->general = gen;
    self->flush = flush;
    self->pieces = pieces;
    self->times = times;
    self->cids = cids;
    self->start_ns = start_ns;
    self->limit = limit;
    for (int i = 0; i < 9; i++) Py_XDECREF(old[i]);
    return 0;
}

static int Tap_traverse(Tap *self, visitproc visit, void *arg) {
    Py_VISIT(self->fast);
    Py_VISIT(self->dumps);
    Py_VISIT(self->kwargs);
    Py_VISIT(self->bencode);
    Py_VISIT(self->general);
    Py_VISIT(self->flush);
    Py_VISIT(self->pieces);
    Py_VISIT(self->times);
    Py_VISIT(self->cids);
    return 0;
}

static int Tap_clear(Tap *self) {
    Py_CLEAR(self->fast);
    Py_CLEAR(self->dumps);
    Py_CLEAR(self->kwargs);
    Py_CLEAR(self->bencode);
    Py_CLEAR(self->general);
    Py_CLEAR(self->flush);
    Py_CLEAR(self->pieces);
    Py_CLEAR(self->times);
    Py_CLEAR(self->cids);
    return 0;
}

static void Tap_dealloc(Tap *self) {
    PyObject_GC_UnTrack(self);
    Tap_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyTypeObject TapType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "deft_gym.record._tap_c.Tap",
    .tp_basicsize = sizeof(Tap),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_doc = "Tap(fast, start_ns, dumps, kwargs, bencode, general, flush, pieces, times, cids, limit): the recorder's tap",
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Tap_init,
    .tp_call = (ternaryfunc)Tap_call,
    .tp_traverse = (traverseproc)Tap_traverse,
    .tp_clear = (inquiry)Tap_clear,
    .tp_dealloc = (destructor)Tap_dealloc,
};

/* the SHA-256 digests of the sources this build was made from (setup.py defines BUILT_FROM as
 * "<digest of this file> <digest of recorder.py>"; deft_gym.files.stale_kernel compares them) */
#ifndef BUILT_FROM
#define BUILT_FROM ""
#endif

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_tap_c", NULL, -1, NULL};

PyMODINIT_FUNC PyInit__tap_c(void) {
    if (PyType_Ready(&TapType) < 0) return NULL;
    s_topic = PyUnicode_InternFromString("topic");
    s_payload = PyUnicode_InternFromString("payload");
    s_seq = PyUnicode_InternFromString("seq");
    s_publish_ns = PyUnicode_InternFromString("publish_ns");
    if (!s_topic || !s_payload || !s_seq || !s_publish_ns) return NULL;
    PyObject *m = PyModule_Create(&module);
    if (!m) return NULL;
    Py_INCREF(&TapType);
    if (PyModule_AddObject(m, "Tap", (PyObject *)&TapType) < 0 ||
        PyModule_AddStringConstant(m, "BUILT_FROM", BUILT_FROM) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
