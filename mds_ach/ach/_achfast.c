/*
 * mds_ach.ach._achfast -- optional C fast path for the hot calls of mds_ach.ach (put, get, busy-poll, flush).
 *
 * Why it exists: on a robot's 1 kHz loop a process wakes up with cold caches, and every Python bytecode and
 * ctypes call then costs microseconds. One C call per put/get keeps the Ach hop in the few-microsecond range
 * that C libach reaches. The algorithms live in achcore.h, shared with the project's libach for C clients
 * (libach/libach.c); they are the same as the pure-Python ones in channel.py (libach's put/get steps, literally)
 * and are tested against it and against the golden files; channel.py stays the reference and is used whenever
 * this module is missing or MDS_ACH_PURE_PYTHON=1.
 *
 * A Handle points into a mapping owned by the Python Channel. The Channel guarantees the mapping outlives
 * every call (its in-progress counter) and calls detach() before unmapping, after which every call fails
 * with ACH_CLOSED instead of touching freed memory. The Handle also holds the reader state (seq_num,
 * next_index), updated under the channel mutex as libach does, so threads sharing a handle stay consistent.
 * Waits release the GIL and last at most one slice given by the caller, which checks cancel/close/signals.
 *
 * Nothing read from the file is trusted: another process can scribble over it. The geometry (len, index_cnt,
 * data_size) is validated by Python at open and handed in; every put and get compares it with the header again and
 * bounds-checks the ring counters and each index entry it uses before using them, so a damaged header reads as
 * ACH_CORRUPT and never leads to an access outside the mapping. A file truncated under the mapping is handled by
 * mds_ach.ach._shmguard (SIGBUS); its per-mapping "lost" flag, whose address is handed in, turns the call that met
 * the truncation into ACH_CORRUPT. Locking is bounded when the caller asks for it (lock_ns >= 0).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

/* achcore.h's blocking calls (a busy lock, a wait) run with the GIL released, so the process's other threads keep
 * running. */
#define ACHCORE_BLOCKING_BEGIN Py_BEGIN_ALLOW_THREADS
#define ACHCORE_BLOCKING_END Py_END_ALLOW_THREADS
#include "achcore.h"

typedef struct {
    PyObject_HEAD
    achcore_t c; /* c.base is NULL once detached */
} Handle;

/* ------------------------------------------------------------------------------------------------ */

static int check_open(Handle *h) {
    if (h->c.base == NULL) {
        PyErr_SetString(PyExc_ValueError, "Ach handle is detached (channel closed)");
        return -1;
    }
    return 0;
}

static int Handle_init(Handle *h, PyObject *args, PyObject *kwds) {
    unsigned long long base, cnt, dsize, length, lost = 0;
    Py_ssize_t mutex_off, cond_off, dirty_off, last_off, header_size;
    static char *kwlist[] = {"base", "mutex", "cond", "dirty", "last_seq", "header_size", "index_cnt", "data_size",
                             "length", "lost_flag", NULL};
    h->c.base = NULL;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "KnnnnnKKK|K", kwlist, &base, &mutex_off, &cond_off, &dirty_off,
                                     &last_off, &header_size, &cnt, &dsize, &length, &lost))
        return -1;
    if (cond_off - mutex_off != (Py_ssize_t)sizeof(pthread_mutex_t)) {
        PyErr_Format(PyExc_ValueError, "layout has a %zd-byte mutex, this libc's is %zu", cond_off - mutex_off,
                     sizeof(pthread_mutex_t));
        return -1;
    }
    if (mutex_off < 0 || dirty_off < 0 || last_off < 0 || header_size < 0 ||
        achcore_attach(&h->c, (char *)(uintptr_t)base, (size_t)mutex_off, (size_t)cond_off, (size_t)dirty_off,
                       (size_t)last_off, (size_t)header_size, cnt, dsize, length,
                       lost ? (volatile int *)(uintptr_t)lost : NULL) != 0) {
        h->c.base = NULL;
        PyErr_Format(PyExc_ValueError, "inconsistent geometry: index_cnt=%llu data_size=%llu length=%llu", cnt, dsize,
                     length);
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(put_doc, "put(src, lock_ns=-1) -> status: a complete libach put (header, lock, write, unlock, wake).\n\n"
                      "lock_ns < 0 waits for the channel mutex as long as it takes; otherwise at most lock_ns.");

static PyObject *Handle_put(Handle *h, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 1 && nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "put(src, lock_ns=-1)");
        return NULL;
    }
    if (check_open(h))
        return NULL;
    long long lock_ns = nargs == 2 ? PyLong_AsLongLong(args[1]) : -1;
    if (lock_ns == -1 && PyErr_Occurred())
        return NULL;
    Py_buffer src;
    if (PyObject_GetBuffer(args[0], &src, PyBUF_SIMPLE) < 0)
        return NULL;
    int r = achcore_put(&h->c, (const char *)src.buf, (uint64_t)src.len, lock_ns);
    PyBuffer_Release(&src);
    return PyLong_FromLong(r);
}

/* The (dst, options, slice_ns, lock_ns, poll_ns) arguments of get and poll; on success dst is a held writable
 * buffer. */
static int read_args(Handle *h, const char *name, PyObject *const *args, Py_ssize_t nargs, Py_buffer *dst,
                     int *options, long long *slice_ns, long long *lock_ns, long long *poll_ns) {
    if (nargs < 3 || nargs > 5) {
        PyErr_Format(PyExc_TypeError, "%s(dst, options, slice_ns, lock_ns=-1, poll_ns=0)", name);
        return -1;
    }
    if (check_open(h))
        return -1;
    *options = (int)PyLong_AsLong(args[1]);
    *slice_ns = PyLong_AsLongLong(args[2]);
    *lock_ns = nargs >= 4 ? PyLong_AsLongLong(args[3]) : -1;
    *poll_ns = nargs >= 5 ? PyLong_AsLongLong(args[4]) : 0;
    if (PyErr_Occurred())
        return -1;
    return PyObject_GetBuffer(args[0], dst, PyBUF_WRITABLE);
}

PyDoc_STRVAR(get_doc,
             "get(dst, options, slice_ns, lock_ns=-1, poll_ns=0) -> (status, size)\n\n"
             "Non-blocking libach get into the writable buffer dst. With ACH_O_WAIT and nothing new, sleep on the\n"
             "last_seq futex (GIL released) for at most slice_ns and return ACH_TIMEOUT if still nothing: the\n"
             "caller loops, checking cancel, close, signals and its own deadline between slices. poll_ns > 0 also\n"
             "looks at last_seq that often during the sleep (for writers that do not wake the futex); `woken` tells\n"
             "how the sleep ended. lock_ns bounds the wait for the channel mutex (< 0: no bound).");

static PyObject *Handle_get(Handle *h, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer dst;
    int options;
    long long slice_ns, lock_ns, poll_ns;
    if (read_args(h, "get", args, nargs, &dst, &options, &slice_ns, &lock_ns, &poll_ns) < 0)
        return NULL;
    uint64_t size = 0;
    int r;
    if (options & ACH_O_WAIT)
        achcore_wait(&h->c, slice_ns, poll_ns);
    r = achcore_get_once(&h->c, dst.buf, (uint64_t)dst.len, options & ~ACH_O_WAIT, &size, lock_ns);
    if ((options & ACH_O_WAIT) && r == ACH_STALE_FRAMES)
        r = ACH_TIMEOUT;
    PyBuffer_Release(&dst);
    return Py_BuildValue("iK", r, (unsigned long long)size);
}

PyDoc_STRVAR(poll_doc,
             "poll(dst, options, slice_ns, lock_ns=-1) -> (status, size)\n\n"
             "Busy-poll: spin on last_seq (GIL released) for at most slice_ns, then get. ACH_TIMEOUT when nothing\n"
             "new arrived within the slice.");

static inline void cpu_relax(void) {
#if defined(__x86_64__)
    __builtin_ia32_pause();
#elif defined(__aarch64__)
    __asm__ __volatile__("yield");
#endif
}

static PyObject *Handle_poll(Handle *h, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer dst;
    int options;
    long long slice_ns, lock_ns, poll_ns;
    if (read_args(h, "poll", args, nargs, &dst, &options, &slice_ns, &lock_ns, &poll_ns) < 0)
        return NULL;
    achcore_t *c = &h->c;
    int changed = *c->last_seq != c->seq;
    if (!changed) {
        Py_BEGIN_ALLOW_THREADS
        long long end = achcore_mono_ns() + slice_ns;
        unsigned spins = 0;
        while (!(changed = *c->last_seq != c->seq)) {
            cpu_relax();
            if ((++spins & 0x3FF) == 0 && achcore_mono_ns() >= end)
                break;
        }
        if (changed) {
            /* last_seq changes while the writer still holds the mutex; locking now would sleep in the kernel
             * (PI futex). Spin briefly until the lock word is free. */
            volatile int32_t *word = (volatile int32_t *)c->mutex;
            for (spins = 0; *word && spins < 100000; spins++)
                cpu_relax();
        }
        Py_END_ALLOW_THREADS
    }
    uint64_t size = 0;
    int r = changed ? achcore_get_once(c, dst.buf, (uint64_t)dst.len, options & ~ACH_O_WAIT, &size, lock_ns)
                    : ACH_TIMEOUT;
    PyBuffer_Release(&dst);
    return Py_BuildValue("iK", r, (unsigned long long)size);
}

PyDoc_STRVAR(flush_doc, "flush(lock_ns=-1) -> status: mark every frame as seen (libach ach_flush), under the lock.");

static PyObject *Handle_flush(Handle *h, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs > 1) {
        PyErr_SetString(PyExc_TypeError, "flush(lock_ns=-1)");
        return NULL;
    }
    if (check_open(h))
        return NULL;
    long long lock_ns = nargs == 1 ? PyLong_AsLongLong(args[0]) : -1;
    if (lock_ns == -1 && PyErr_Occurred())
        return NULL;
    return PyLong_FromLong(achcore_flush(&h->c, lock_ns));
}

PyDoc_STRVAR(detach_doc, "detach(): forget the mapping; every later call raises instead of touching it.");

static PyObject *Handle_detach(Handle *h, PyObject *unused) {
    h->c.base = NULL;
    Py_RETURN_NONE;
}

static PyMethodDef Handle_methods[] = {
    {"put", (PyCFunction)(void (*)(void))Handle_put, METH_FASTCALL, put_doc},
    {"get", (PyCFunction)(void (*)(void))Handle_get, METH_FASTCALL, get_doc},
    {"poll", (PyCFunction)(void (*)(void))Handle_poll, METH_FASTCALL, poll_doc},
    {"flush", (PyCFunction)(void (*)(void))Handle_flush, METH_FASTCALL, flush_doc},
    {"detach", (PyCFunction)Handle_detach, METH_NOARGS, detach_doc},
    {NULL, NULL, 0, NULL},
};

static PyObject *Handle_get_seq(Handle *h, void *unused) { return PyLong_FromUnsignedLongLong(h->c.seq); }
static PyObject *Handle_get_next(Handle *h, void *unused) { return PyLong_FromUnsignedLongLong(h->c.next); }
static PyObject *Handle_get_woken(Handle *h, void *unused) { return PyLong_FromLong(h->c.woken); }

static PyGetSetDef Handle_getset[] = {
    {"seq", (getter)Handle_get_seq, NULL, "sequence number of the last frame this handle read", NULL},
    {"next", (getter)Handle_get_next, NULL, "index slot this handle reads next in order", NULL},
    {"woken", (getter)Handle_get_woken, NULL, "how the last get's wait ended: 0 no wait, 1 woken, 2 a frame came without a wake-up",
     NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyTypeObject HandleType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "mds_ach.ach._achfast.Handle",
    .tp_basicsize = sizeof(Handle),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = PyDoc_STR("Handle(base, mutex, cond, dirty, last_seq, header_size, index_cnt, data_size, length, "
                        "lost_flag=0): C put/get on a mapped channel"),
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Handle_init,
    .tp_methods = Handle_methods,
    .tp_getset = Handle_getset,
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_achfast", "C fast path for mds_ach.ach (see the source's header comment).", -1, NULL,
};

PyMODINIT_FUNC PyInit__achfast(void) {
    if (PyType_Ready(&HandleType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    Py_INCREF(&HandleType);
    if (PyModule_AddObject(m, "Handle", (PyObject *)&HandleType) < 0 ||
        PyModule_AddIntConstant(m, "MUTEX_SIZE", (long)sizeof(pthread_mutex_t)) < 0 ||
        PyModule_AddIntConstant(m, "LOCK_TIMED_OUT", ACHCORE_LOCK_TIMED_OUT) < 0) {
        Py_DECREF(&HandleType);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
