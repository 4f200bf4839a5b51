/*
 * mds_ach.ach._achfast -- optional C fast path for the hot calls of mds_ach.ach (put, get, busy-poll, flush).
 *
 * Why it exists: on a robot's 1 kHz loop a process wakes up with cold caches, and every Python bytecode and
 * ctypes call then costs microseconds. One C call per put/get keeps the Ach hop in the few-microsecond range
 * that C libach reaches. The algorithms are the same as the pure-Python ones in ach.py (libach's put/get
 * steps, literally) and are tested against it and against the golden files; ach.py stays the reference and
 * is used whenever this module is missing or MDS_ACH_PURE_PYTHON=1.
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

#include <errno.h>
#include <limits.h>
#include <linux/futex.h>
#include <pthread.h>
#include <stdint.h>
#include <string.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

/* status codes (enum ach_status) and options, as in ach.py */
enum {
    ACH_OK = 0, ACH_OVERFLOW = 1, ACH_FAILED_SYSCALL = 4, ACH_STALE_FRAMES = 5, ACH_MISSED_FRAME = 6,
    ACH_TIMEOUT = 7, ACH_CLOSED = 10, ACH_BUG = 11, ACH_EINVAL = 12, ACH_CORRUPT = 13,
    LOCK_TIMED_OUT = -1 /* not libach's: the mutex was not acquired within lock_ns (ach.py reports ACH_LOCKED) */
};
enum { ACH_O_WAIT = 1, ACH_O_LAST = 2, ACH_O_COPY = 4 };
/* how a get's futex wait ended: not at all (a frame was there), woken (FUTEX_WAKE, or the word had changed),
 * or at the end of the slice. A frame found after a timed-out wait came from a writer that does not wake the
 * futex (C libach): the caller then uses short slices. */
enum { WAIT_NONE = 0, WAIT_WOKEN = 1, WAIT_TIMED_OUT = 2 };

#define MAGIC 0xB07511F3u
#define GUARD_HEADER 0x1A2A3A4A5A6A7A8AULL
#define GUARD_INDEX 0x1B2B3B4B5B6B7B8BULL
#define GUARD_DATA 0x1C2C3C4C5C6C7C8CULL
#define LOCK_SLICE_NS 50000000LL /* a busy channel lock is waited for in slices this long (see chan_lock) */

/* header words, in u64 units from the start of the file */
#define Q_LEN 1
#define Q_INDEX_CNT 11
#define Q_DATA_SIZE 12
#define Q_DATA_HEAD 13
#define Q_DATA_FREE 14
#define Q_INDEX_HEAD 15
#define Q_INDEX_FREE 16

typedef struct {
    PyObject_HEAD
    char *base;               /* NULL once detached */
    volatile uint64_t *q;     /* the file as u64 words */
    pthread_mutex_t *mutex;
    pthread_cond_t *cond;
    volatile int32_t *dirty;
    volatile uint64_t *last_seq;
    volatile uint64_t *index; /* index[0].size */
    char *data;               /* data ring */
    uint64_t cnt, dsize, len; /* geometry validated at open */
    size_t off_guard_h, off_guard_i, off_guard_d;
    volatile int *lost;       /* set by the SIGBUS guard when the file vanished under the mapping */
    int no_guard;             /* what lost points to without a guard: always 0 */
    uint64_t seq, next;       /* reader state */
    int woken;                /* how the last get's futex wait ended: WAIT_NONE / WAIT_WOKEN / WAIT_TIMED_OUT */
} Handle;

/* libach check_guards, plus the geometry this handle was opened with: magic, len, index_cnt, data_size. */
static inline int header_ok(const Handle *h) {
    volatile uint64_t *q = h->q;
    uint64_t g_h, g_i, g_d;
    memcpy(&g_h, h->base + h->off_guard_h, 8);
    memcpy(&g_i, h->base + h->off_guard_i, 8);
    memcpy(&g_d, h->base + h->off_guard_d, 8); /* may be unaligned */
    return g_h == GUARD_HEADER && g_i == GUARD_INDEX && g_d == GUARD_DATA && (uint32_t)q[0] == MAGIC &&
           q[Q_LEN] == h->len && q[Q_INDEX_CNT] == h->cnt && q[Q_DATA_SIZE] == h->dsize;
}

/* The ring counters (read once by the caller, under the lock) are in range: every put, libach's creation and
 * `mds-ach repair` keep them so. */
static inline int counters_ok(const Handle *h, uint64_t index_head, uint64_t index_free, uint64_t data_head,
                              uint64_t data_free) {
    return index_head < h->cnt && index_free <= h->cnt && data_head < h->dsize && data_free <= h->dsize;
}

/* A live index entry: a non-empty frame inside the data ring, with a sequence number that has been issued. */
static inline int entry_ok(uint64_t size, uint64_t offset, uint64_t seq, uint64_t dsize, uint64_t last_seq) {
    return size != 0 && offset < dsize && size <= dsize - offset && seq != 0 && seq <= last_seq;
}

static long long mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* libach chan_lock: lock, make a dead owner's mutex consistent, refuse a dirty channel. Called with the GIL
 * held; a busy lock (another process mid-put, or stopped while holding it) is waited for with the GIL released
 * so the process's other threads keep running: as long as it takes when lock_ns < 0, else at most lock_ns (then
 * LOCK_TIMED_OUT, the channel untouched). The wait is cut into LOCK_SLICE_NS timed locks, and between them the
 * header is looked at again: a waiter parked in the kernel would otherwise never notice that the file was
 * truncated under it (the lock's owner can then never release it; see _shmguard.c). pthread_mutex_timedlock takes
 * a CLOCK_REALTIME deadline (POSIX); a clock step only lengthens or shortens one slice. */
static int chan_lock(Handle *h, long long lock_ns) {
    int r = pthread_mutex_trylock(h->mutex);
    if (r == EBUSY) {
        long long end = lock_ns < 0 ? -1 : mono_ns() + lock_ns;
        for (;;) {
            long long slice = LOCK_SLICE_NS;
            if (end >= 0 && end - mono_ns() < slice)
                slice = end - mono_ns();
            if (slice < 0)
                slice = 0;
            struct timespec ts;
            clock_gettime(CLOCK_REALTIME, &ts);
            long long ns = ts.tv_nsec + slice;
            ts.tv_sec += (time_t)(ns / 1000000000LL);
            ts.tv_nsec = (long)(ns % 1000000000LL);
            Py_BEGIN_ALLOW_THREADS
            r = pthread_mutex_timedlock(h->mutex, &ts);
            Py_END_ALLOW_THREADS
            if (r != ETIMEDOUT)
                break;
            if (*h->lost || !header_ok(h))
                return ACH_CORRUPT;
            if (end >= 0 && mono_ns() >= end)
                return LOCK_TIMED_OUT;
        }
    }
    if (r == EOWNERDEAD) {
        pthread_mutex_consistent(h->mutex);
    } else if (r == ENOTRECOVERABLE) {
        return ACH_CORRUPT;
    } else if (r) {
        return ACH_FAILED_SYSCALL;
    }
    if (*h->dirty) {
        pthread_mutex_unlock(h->mutex);
        return ACH_CORRUPT;
    }
    return ACH_OK;
}

static void wake_all(Handle *h) {
    /* futex waiters (ach.py readers) on the low word of last_seq, then libach's condvar waiters */
    syscall(SYS_futex, (void *)h->last_seq, FUTEX_WAKE, INT_MAX, NULL, NULL, 0);
    pthread_cond_broadcast(h->cond);
}

/* libach's free(i) of a live entry, which is read once and checked first: 0 (nothing changed) if it is damaged. */
static inline int evict(volatile uint64_t *e, uint64_t dsize, uint64_t last, uint64_t *data_free,
                        uint64_t *index_free) {
    uint64_t size = e[0], offset = e[1], seq = e[2];
    if (!entry_ok(size, offset, seq, dsize, last))
        return 0;
    *data_free += size;
    *index_free += 1;
    e[0] = e[1] = e[2] = 0;
    return 1;
}

/* libach ach_put steps 1-7 (ach-format.md section 4); caller holds the lock. Every value read from the file is
 * read once and checked before it is used, so nothing another process writes meanwhile can move an access out
 * of the ring. Returns with dirty = 0, except when an index entry turns out damaged half-way: ACH_CORRUPT with
 * dirty = 1, so every client sees the channel corrupt until `mds-ach repair` (as after a writer died mid-put).
 * Damaged counters are refused before anything is written. */
static int write_locked(Handle *h, const char *src, uint64_t n) {
    volatile uint64_t *q = h->q, *ix = h->index;
    uint64_t cnt = h->cnt, dsize = h->dsize, last = *h->last_seq;
    uint64_t index_head = q[Q_INDEX_HEAD], index_free = q[Q_INDEX_FREE];
    uint64_t data_head = q[Q_DATA_HEAD], data_free = q[Q_DATA_FREE];
    if (!counters_ok(h, index_head, index_free, data_head, data_free) || last == UINT64_MAX)
        return ACH_CORRUPT; /* (a last_seq that cannot be incremented is as damaged as a wild counter) */
    *h->dirty = 1;
    uint64_t slot = index_head, i;
    if (index_free == 0 && !evict(ix + 3 * index_head, dsize, last, &data_free, &index_free))
        return ACH_CORRUPT; /* index full: drop the oldest frame, which sits in our slot */
    if (dsize - data_head < n) { /* tail wrap: drop frames after data_head, restart at 0 */
        i = (index_head + index_free) % cnt;
        while (ix[3 * i + 1] > data_head) {
            if (!evict(ix + 3 * i, dsize, last, &data_free, &index_free))
                return ACH_CORRUPT;
            i = (i + 1) % cnt;
        }
        if (i == index_head) {
            data_free = dsize;
        } else {
            volatile uint64_t *oldest = ix + 3 * ((index_head + index_free) % cnt);
            uint64_t size = oldest[0], offset = oldest[1], seq = oldest[2];
            if (!entry_ok(size, offset, seq, dsize, last))
                return ACH_CORRUPT;
            data_free = offset;
        }
        data_head = 0;
    }
    i = (index_head + index_free) % cnt;
    while (data_free < n) { /* clear overlap with the oldest frames */
        if (i == index_head)
            data_free = dsize;
        else if (!evict(ix + 3 * i, dsize, last, &data_free, &index_free))
            return ACH_CORRUPT;
        i = (i + 1) % cnt;
    }
    if (dsize - data_head < n) { /* libach's sanity check; cannot happen */
        q[Q_DATA_HEAD] = data_head;
        q[Q_DATA_FREE] = data_free;
        q[Q_INDEX_FREE] = index_free;
        *h->dirty = 0;
        return ACH_BUG;
    }
    memcpy(h->data + data_head, src, n);
    uint64_t seq = last + 1;
    *h->last_seq = seq;
    volatile uint64_t *e = ix + 3 * slot;
    e[0] = n;
    e[1] = data_head;
    e[2] = seq;
    q[Q_DATA_HEAD] = (data_head + n) % dsize;
    q[Q_DATA_FREE] = data_free - n;
    q[Q_INDEX_HEAD] = (index_head + 1) % cnt;
    q[Q_INDEX_FREE] = index_free - 1;
    *h->dirty = 0;
    return ACH_OK;
}

/* libach ach_get steps 3-7; caller holds the lock. Sets *size (needed size on OVERFLOW). Values from the file
 * are read once and checked before use, as in write_locked. */
static int read_locked(Handle *h, char *dst, uint64_t cap, int options, uint64_t *size) {
    volatile uint64_t *q = h->q, *ix = h->index;
    uint64_t last = *h->last_seq, seq = h->seq, cnt = h->cnt, ri;
    uint64_t index_head = q[Q_INDEX_HEAD], index_free = q[Q_INDEX_FREE];
    *size = 0;
    if (!counters_ok(h, index_head, index_free, q[Q_DATA_HEAD], q[Q_DATA_FREE]))
        return ACH_CORRUPT;
    if (last == 0 || (seq == last && !(options & ACH_O_COPY)))
        return ACH_STALE_FRAMES;
    if (options & ACH_O_LAST)
        ri = (index_head + cnt - 1) % cnt;
    else if (ix[3 * h->next + 2] == seq + 1)
        ri = h->next;
    else if (seq == last)
        ri = (index_head + cnt - 1) % cnt;
    else
        ri = (index_head + index_free) % cnt;
    volatile uint64_t *e = ix + 3 * ri;
    uint64_t fsize = e[0], offset = e[1], eseq = e[2];
    if (!entry_ok(fsize, offset, eseq, h->dsize, last)) {
        if (fsize == 0 && offset == 0 && eseq == 0) { /* an empty ring (a repair kept no frame): nothing to miss */
            h->seq = last;
            return ACH_STALE_FRAMES;
        }
        return ACH_CORRUPT;
    }
    if (seq > eseq) /* libach: the channel was re-created under this handle */
        return ACH_BUG;
    if (cap < fsize) {
        *size = fsize;
        return ACH_OVERFLOW;
    }
    memcpy(dst, h->data + offset, fsize);
    h->seq = eseq;
    h->next = (ri + 1) % cnt;
    *size = fsize;
    return eseq > seq + 1 ? ACH_MISSED_FRAME : ACH_OK;
}

/* header, lock, read, unlock: a complete non-blocking libach get. */
static int get_once(Handle *h, char *dst, uint64_t cap, int options, uint64_t *size, long long lock_ns) {
    *size = 0;
    if (!header_ok(h))
        return ACH_CORRUPT;
    int r = chan_lock(h, lock_ns);
    if (r)
        return r;
    r = read_locked(h, dst, cap, options, size);
    pthread_mutex_unlock(h->mutex);
    return *h->lost ? ACH_CORRUPT : r;
}

static void ns_to_timespec(long long ns, struct timespec *ts) {
    if (ns < 0)
        ns = 0;
    ts->tv_sec = (time_t)(ns / 1000000000LL);
    ts->tv_nsec = (long)(ns % 1000000000LL);
}

/* ------------------------------------------------------------------------------------------------ */

static int check_open(Handle *h) {
    if (h->base == NULL) {
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
    h->base = NULL;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "KnnnnnKKK|K", kwlist, &base, &mutex_off, &cond_off, &dirty_off,
                                     &last_off, &header_size, &cnt, &dsize, &length, &lost))
        return -1;
    if (cond_off - mutex_off != (Py_ssize_t)sizeof(pthread_mutex_t)) {
        PyErr_Format(PyExc_ValueError, "layout has a %zd-byte mutex, this libc's is %zu", cond_off - mutex_off,
                     sizeof(pthread_mutex_t));
        return -1;
    }
    /* the geometry Python validated against the mapped file: len = header + 24 * cnt + dsize + 24 bytes */
    if (cnt == 0 || dsize == 0 || header_size < 0 || cnt > (1ULL << 40) || dsize > (1ULL << 50) ||
        length != (unsigned long long)header_size + 24 * cnt + dsize + 24) {
        PyErr_Format(PyExc_ValueError, "inconsistent geometry: index_cnt=%llu data_size=%llu length=%llu", cnt, dsize,
                     length);
        return -1;
    }
    h->base = (char *)(uintptr_t)base;
    h->q = (volatile uint64_t *)h->base;
    h->mutex = (pthread_mutex_t *)(h->base + mutex_off);
    h->cond = (pthread_cond_t *)(h->base + cond_off);
    h->dirty = (volatile int32_t *)(h->base + dirty_off);
    h->last_seq = (volatile uint64_t *)(h->base + last_off);
    h->cnt = cnt;
    h->dsize = dsize;
    h->len = length;
    h->no_guard = 0;
    h->lost = lost ? (volatile int *)(uintptr_t)lost : &h->no_guard;
    h->index = (volatile uint64_t *)(h->base + header_size + 8);
    h->data = h->base + header_size + 16 + 24 * h->cnt;
    h->off_guard_h = (size_t)header_size;
    h->off_guard_i = (size_t)header_size + 8 + 24 * h->cnt;
    h->off_guard_d = (size_t)header_size + 16 + 24 * h->cnt + h->dsize;
    h->seq = 0; /* libach ach_open: seq_num = 0, next_index = 1 */
    h->next = 1;
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
    int r;
    uint64_t n = (uint64_t)src.len;
    if (n == 0) {
        r = ACH_EINVAL;
    } else if (!header_ok(h)) {
        r = ACH_CORRUPT;
    } else if (n > h->dsize) {
        r = ACH_OVERFLOW;
    } else if ((r = chan_lock(h, lock_ns)) == ACH_OK) {
        r = write_locked(h, (const char *)src.buf, n);
        pthread_mutex_unlock(h->mutex);
        wake_all(h);
    }
    PyBuffer_Release(&src);
    return PyLong_FromLong(*h->lost ? ACH_CORRUPT : r);
}

/* The (dst, options, slice_ns, lock_ns) arguments of get and poll; on success dst is a held writable buffer. */
static int read_args(Handle *h, const char *name, PyObject *const *args, Py_ssize_t nargs, Py_buffer *dst,
                     int *options, long long *slice_ns, long long *lock_ns) {
    if (nargs != 3 && nargs != 4) {
        PyErr_Format(PyExc_TypeError, "%s(dst, options, slice_ns, lock_ns=-1)", name);
        return -1;
    }
    if (check_open(h))
        return -1;
    *options = (int)PyLong_AsLong(args[1]);
    *slice_ns = PyLong_AsLongLong(args[2]);
    *lock_ns = nargs == 4 ? PyLong_AsLongLong(args[3]) : -1;
    if (PyErr_Occurred())
        return -1;
    return PyObject_GetBuffer(args[0], dst, PyBUF_WRITABLE);
}

PyDoc_STRVAR(get_doc,
             "get(dst, options, slice_ns, lock_ns=-1) -> (status, size)\n\n"
             "Non-blocking libach get into the writable buffer dst. With ACH_O_WAIT and nothing new, sleep on the\n"
             "last_seq futex (GIL released) for at most slice_ns and return ACH_TIMEOUT if still nothing: the\n"
             "caller loops, checking cancel, close, signals and its own deadline between slices. lock_ns bounds\n"
             "the wait for the channel mutex (< 0: no bound).");

static PyObject *Handle_get(Handle *h, PyObject *const *args, Py_ssize_t nargs) {
    Py_buffer dst;
    int options;
    long long slice_ns, lock_ns;
    if (read_args(h, "get", args, nargs, &dst, &options, &slice_ns, &lock_ns) < 0)
        return NULL;
    uint64_t size = 0;
    int r;
    if (!(options & ACH_O_WAIT)) {
        r = get_once(h, dst.buf, (uint64_t)dst.len, options, &size, lock_ns);
    } else {
        /* the lock-free look at last_seq is only a hint; get_once decides under the lock */
        uint64_t last = *h->last_seq;
        h->woken = WAIT_NONE;
        if (last == h->seq) {
            struct timespec ts;
            long fr;
            int err;
            ns_to_timespec(slice_ns, &ts);
            Py_BEGIN_ALLOW_THREADS
            fr = syscall(SYS_futex, (void *)h->last_seq, FUTEX_WAIT, (uint32_t)last, &ts, NULL, 0);
            err = errno;
            Py_END_ALLOW_THREADS
            h->woken = (fr == -1 && err == ETIMEDOUT) ? WAIT_TIMED_OUT : WAIT_WOKEN;
        }
        r = get_once(h, dst.buf, (uint64_t)dst.len, options & ~ACH_O_WAIT, &size, lock_ns);
        if (r == ACH_STALE_FRAMES)
            r = ACH_TIMEOUT;
    }
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
    long long slice_ns, lock_ns;
    if (read_args(h, "poll", args, nargs, &dst, &options, &slice_ns, &lock_ns) < 0)
        return NULL;
    int changed = *h->last_seq != h->seq;
    if (!changed) {
        Py_BEGIN_ALLOW_THREADS
        long long end = mono_ns() + slice_ns;
        unsigned spins = 0;
        while (!(changed = *h->last_seq != h->seq)) {
            cpu_relax();
            if ((++spins & 0x3FF) == 0 && mono_ns() >= end)
                break;
        }
        if (changed) {
            /* last_seq changes while the writer still holds the mutex; locking now would sleep in the kernel
             * (PI futex). Spin briefly until the lock word is free. */
            volatile int32_t *word = (volatile int32_t *)h->mutex;
            for (spins = 0; *word && spins < 100000; spins++)
                cpu_relax();
        }
        Py_END_ALLOW_THREADS
    }
    uint64_t size = 0;
    int r = changed ? get_once(h, dst.buf, (uint64_t)dst.len, options & ~ACH_O_WAIT, &size, lock_ns) : ACH_TIMEOUT;
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
    if (!header_ok(h))
        return PyLong_FromLong(ACH_CORRUPT);
    int r = chan_lock(h, lock_ns);
    if (r == ACH_OK) {
        uint64_t index_head = h->q[Q_INDEX_HEAD];
        if (counters_ok(h, index_head, h->q[Q_INDEX_FREE], h->q[Q_DATA_HEAD], h->q[Q_DATA_FREE])) {
            h->seq = *h->last_seq;
            h->next = index_head;
        } else {
            r = ACH_CORRUPT;
        }
        pthread_mutex_unlock(h->mutex);
    }
    return PyLong_FromLong(*h->lost ? ACH_CORRUPT : r);
}

PyDoc_STRVAR(detach_doc, "detach(): forget the mapping; every later call raises instead of touching it.");

static PyObject *Handle_detach(Handle *h, PyObject *unused) {
    h->base = NULL;
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

static PyObject *Handle_get_seq(Handle *h, void *unused) { return PyLong_FromUnsignedLongLong(h->seq); }
static PyObject *Handle_get_next(Handle *h, void *unused) { return PyLong_FromUnsignedLongLong(h->next); }
static PyObject *Handle_get_woken(Handle *h, void *unused) { return PyLong_FromLong(h->woken); }

static PyGetSetDef Handle_getset[] = {
    {"seq", (getter)Handle_get_seq, NULL, "sequence number of the last frame this handle read", NULL},
    {"next", (getter)Handle_get_next, NULL, "index slot this handle reads next in order", NULL},
    {"woken", (getter)Handle_get_woken, NULL, "how the last get's wait ended: 0 no wait, 1 woken, 2 timed out",
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
        PyModule_AddIntConstant(m, "LOCK_TIMED_OUT", LOCK_TIMED_OUT) < 0) {
        Py_DECREF(&HandleType);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
