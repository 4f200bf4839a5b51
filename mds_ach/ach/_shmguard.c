/*
 * mds_ach.ach._shmguard -- a channel file that shrinks (or cannot get memory) under a mapping must not kill the process.
 *
 * Why it exists: an Ach channel is a file in /dev/shm mapped by every client. If anyone truncates that file, every
 * access to a mapped page past the new end raises SIGBUS, in any process that has it mapped: the daemon, the mux,
 * the filter... The same happens when a page of a sparse file is first touched and tmpfs is full. No check made
 * before an access can prevent it (the file can shrink between the check and the access, and glibc's mutex code
 * touches the mapping too), and mlock/MAP_POPULATE do not keep truncated pages either. So the guard handles the
 * fault itself. Every channel mapping is registered here (watch()); a SIGBUS inside a registered mapping:
 *
 *   - file truncated: the file is grown back to the length this process mapped (fallocate, which never shrinks
 *     it, so it cannot undo a re-creation that made it longer). The vanished pages come back as zeros, in every
 *     process: the faulting instruction is retried and completes, and every later access, by any process and by
 *     the kernel's futex code (which glibc turns into an abort when it faults), finds memory. The zeroed header
 *     makes every client see ACH_CORRUPT; `mds-ach repair` re-creates the channel;
 *   - no memory for a page (a full tmpfs), or the file cannot be grown: the rest of the mapping from the faulting
 *     page on is replaced by private zero-filled memory (mmap MAP_FIXED | MAP_ANONYMOUS), and the instruction
 *     completes on that;
 *   - either way the mapping is marked lost with the reason, and the Ach code reports ACH_CORRUPT for it from then
 *     on (re-open the channel after `mds-ach repair`). A SIGBUS anywhere else goes to the handler that was there
 *     before (Python's faulthandler, or the default action), exactly as without the guard.
 *
 * A lost mapping is never unmapped (close() leaves it; it is a few pages): if the page holding the mutex vanished
 * while this thread held it, glibc's robust-mutex list still points into that page.
 * Everything the handler does is async-signal-safe in practice (fstat, fallocate, mmap: plain system calls).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdint.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#define MAX_WATCHED 1024

enum { FINE = 0, LOST_TRUNCATED = 1, LOST_NO_MEMORY = 2 };

typedef struct {
    volatile uintptr_t base; /* 0: free slot; published last by watch(), cleared first by forget() */
    size_t length;           /* bytes mapped */
    int fd;                  /* the channel file, to see its size when a fault happens */
    dev_t dev;               /* and which file it is: every mapping of a truncated file is marked */
    ino_t ino;
    volatile int lost;       /* FINE / LOST_TRUNCATED / LOST_NO_MEMORY; read by _achfast through its address */
    volatile long long size; /* file size the handler saw first */
} Watched;

static Watched watched[MAX_WATCHED];
static volatile int used; /* slots [0, used) may be in use */
static struct sigaction previous; /* the SIGBUS disposition before ours */
static long page_size;

static void pass_on(int sig, siginfo_t *info, void *context) {
    /* Not a channel page: behave as if we were not there. Put the previous disposition back; a fault then
     * happens again on return and reaches it, a sent signal is raised again. */
    sigaction(SIGBUS, &previous, NULL);
    if (info->si_code <= 0)
        raise(sig);
    (void)context;
}

static void on_sigbus(int sig, siginfo_t *info, void *context) {
    int saved_errno = errno;
    uintptr_t addr = (uintptr_t)info->si_addr;
    if (info->si_code > 0) { /* raised by the kernel for a real fault: si_addr is meaningful */
        for (int i = 0; i < used; i++) {
            Watched *w = &watched[i];
            uintptr_t base = w->base;
            if (base == 0 || addr < base || addr >= base + w->length)
                continue;
            uintptr_t offset = addr - base, page = offset & ~(uintptr_t)(page_size - 1);
            struct stat st;
            int reason = LOST_NO_MEMORY, known = fstat(w->fd, &st) == 0;
            if (known && (uintptr_t)st.st_size <= offset) {
                reason = LOST_TRUNCATED;
                /* every mapping of this file in this process has lost it, not only the one that touched it first;
                 * mark them before the pages come back as zeros, so no handle sees those without knowing why */
                for (int k = 0; k < used; k++) {
                    Watched *o = &watched[k];
                    if (o->base != 0 && o->dev == st.st_dev && o->ino == st.st_ino && o->lost == FINE) {
                        o->size = (long long)st.st_size;
                        o->lost = LOST_TRUNCATED;
                    }
                }
                if (fallocate(w->fd, 0, 0, (off_t)w->length) == 0) {
                    errno = saved_errno;
                    return; /* the page exists again: the instruction is retried on it */
                }
            }
            void *p = mmap((void *)(base + page), w->length - page, PROT_READ | PROT_WRITE,
                           MAP_FIXED | MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
            if (p == MAP_FAILED)
                break; /* cannot repair the mapping: let the signal take its normal course */
            if (w->lost == FINE) {
                w->size = known ? (long long)st.st_size : -1;
                w->lost = reason;
            }
            errno = saved_errno;
            return;
        }
    }
    errno = saved_errno;
    if (previous.sa_flags & SA_SIGINFO) {
        previous.sa_sigaction(sig, info, context);
    } else if (previous.sa_handler != SIG_DFL && previous.sa_handler != SIG_IGN) {
        previous.sa_handler(sig);
    } else {
        pass_on(sig, info, context);
    }
}

/* Make sure on_sigbus is the process's SIGBUS handler (something may have replaced it since). */
static int install_handler(void) {
    struct sigaction current;
    if (sigaction(SIGBUS, NULL, &current) != 0)
        return -1;
    if ((current.sa_flags & SA_SIGINFO) && current.sa_sigaction == on_sigbus)
        return 0;
    struct sigaction action;
    memset(&action, 0, sizeof action);
    action.sa_sigaction = on_sigbus;
    action.sa_flags = SA_SIGINFO | SA_ONSTACK;
    sigemptyset(&action.sa_mask);
    return sigaction(SIGBUS, &action, &previous);
}

PyDoc_STRVAR(watch_doc,
             "watch(address, length, fd) -> slot\n\n"
             "Guard the mapping [address, address + length) of the open file fd: a SIGBUS inside it marks the\n"
             "slot lost instead of killing the process. Also (re)installs the SIGBUS handler.");

static PyObject *watch(PyObject *module, PyObject *args) {
    unsigned long long address;
    Py_ssize_t length;
    int fd;
    if (!PyArg_ParseTuple(args, "Kni", &address, &length, &fd))
        return NULL;
    if (address == 0 || length <= 0) {
        PyErr_SetString(PyExc_ValueError, "watch: empty mapping");
        return NULL;
    }
    struct stat st;
    if (fstat(fd, &st) != 0 || install_handler() != 0)
        return PyErr_SetFromErrno(PyExc_OSError);
    for (int i = 0; i < MAX_WATCHED; i++) {
        Watched *w = &watched[i];
        if (w->base != 0)
            continue;
        w->length = (size_t)length;
        w->fd = fd;
        w->dev = st.st_dev;
        w->ino = st.st_ino;
        w->lost = FINE;
        w->size = -1;
        if (i >= used)
            used = i + 1;
        __atomic_store_n(&w->base, (uintptr_t)address, __ATOMIC_RELEASE);
        return PyLong_FromLong(i);
    }
    PyErr_Format(PyExc_RuntimeError, "more than %d channel mappings in one process", MAX_WATCHED);
    return NULL;
}

static Watched *slot_arg(PyObject *arg) {
    long i = PyLong_AsLong(arg);
    if (i == -1 && PyErr_Occurred())
        return NULL;
    if (i < 0 || i >= MAX_WATCHED || watched[i].base == 0) {
        PyErr_Format(PyExc_ValueError, "no watched mapping in slot %ld", i);
        return NULL;
    }
    return &watched[i];
}

PyDoc_STRVAR(forget_doc, "forget(slot): stop guarding a mapping (before it is unmapped). Lost mappings stay.");

static PyObject *forget(PyObject *module, PyObject *arg) {
    Watched *w = slot_arg(arg);
    if (w == NULL)
        return NULL;
    __atomic_store_n(&w->base, 0, __ATOMIC_RELEASE);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(state_doc, "state(slot) -> (lost, size): 0 fine, 1 truncated, 2 no memory; file size seen (-1: none).");

static PyObject *state(PyObject *module, PyObject *arg) {
    Watched *w = slot_arg(arg);
    if (w == NULL)
        return NULL;
    return Py_BuildValue("iL", w->lost, w->size);
}

PyDoc_STRVAR(flag_address_doc, "flag_address(slot) -> int: address of the slot's lost flag (a C int).");

static PyObject *flag_address(PyObject *module, PyObject *arg) {
    Watched *w = slot_arg(arg);
    if (w == NULL)
        return NULL;
    return PyLong_FromUnsignedLongLong((unsigned long long)(uintptr_t)&w->lost);
}

static PyMethodDef methods[] = {
    {"watch", watch, METH_VARARGS, watch_doc},
    {"forget", forget, METH_O, forget_doc},
    {"state", state, METH_O, state_doc},
    {"flag_address", flag_address, METH_O, flag_address_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_shmguard", "SIGBUS guard for mapped Ach channel files (see the source's header comment).",
    -1, methods,
};

PyMODINIT_FUNC PyInit__shmguard(void) {
    page_size = sysconf(_SC_PAGESIZE);
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    if (PyModule_AddIntConstant(m, "FINE", FINE) < 0 || PyModule_AddIntConstant(m, "LOST_TRUNCATED", LOST_TRUNCATED) < 0 ||
        PyModule_AddIntConstant(m, "LOST_NO_MEMORY", LOST_NO_MEMORY) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
