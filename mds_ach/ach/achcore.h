/*
 * achcore.h -- the one C implementation of an Ach channel's put, get, flush, locking and wake-ups, shared by the
 * CPython fast path (mds_ach/ach/_achfast.c) and the project's libach for C clients (libach/libach.c).
 *
 * Why one header: the ring algorithms (libach 2.0's, ach-format.md sections 4-6), the robust PI mutex handling
 * and the futex wake-up must be the same bytes in both, or a C client and a Python node could disagree about a
 * channel. Everything is `static` and compiled into each user; a user that must release a lock around blocking
 * calls (the GIL) defines ACHCORE_BLOCKING_BEGIN / ACHCORE_BLOCKING_END before including this file.
 *
 * Wake-ups. Every put wakes FUTEX_WAKE on the low word of last_seq (the project's readers sleep there: a reader
 * killed inside that wait leaves nothing behind) and then broadcasts the condvar (golems' libach readers sleep
 * there). Readers never wait in the condvar: glibc's process-shared condvar keeps a group reference of a waiter
 * killed inside pthread_cond_wait, and the next broadcast of any writer then hangs forever. A writer that only
 * broadcasts (golems' libach) therefore does not wake a futex sleeper; achcore_wait reports a frame that turned up
 * without a wake-up (WAIT_UNWOKEN) and the caller then looks at last_seq every few hundred microseconds for a
 * while (achcore_poll_ns), which bounds the delay of such frames without touching the condvar.
 *
 * Nothing read from the file is trusted: another process can scribble over it. The geometry (len, index_cnt,
 * data_size) is validated at open; every put and get compares it with the header again and bounds-checks the ring
 * counters and each index entry before using them, so a damaged header reads as ACH_CORRUPT and never leads to an
 * access outside the mapping. `lost` points to a flag set when the file was truncated under the mapping (the
 * Python SIGBUS guard); users without such a guard point it at a zero.
 */
#ifndef MDS_ACHCORE_H
#define MDS_ACHCORE_H

#include <errno.h>
#include <limits.h>
#include <linux/futex.h>
#include <pthread.h>
#include <stdint.h>
#include <string.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#ifndef ACHCORE_BLOCKING_BEGIN
#define ACHCORE_BLOCKING_BEGIN
#define ACHCORE_BLOCKING_END
#endif

#ifndef ACH_H /* libach.c includes the public ach.h first, which defines the same names and values */
enum {
    ACH_OK = 0, ACH_OVERFLOW = 1, ACH_FAILED_SYSCALL = 4, ACH_STALE_FRAMES = 5, ACH_MISSED_FRAME = 6,
    ACH_TIMEOUT = 7, ACH_CLOSED = 10, ACH_BUG = 11, ACH_EINVAL = 12, ACH_CORRUPT = 13
};
enum { ACH_O_WAIT = 1, ACH_O_LAST = 2, ACH_O_COPY = 4 };
#endif

/* not libach's: the mutex was not acquired within lock_ns (mds_ach.ach reports ACH_LOCKED) */
#define ACHCORE_LOCK_TIMED_OUT (-1)

/* how a wait for a new frame ended: no wait needed, woken by a futex wake (or the word changed before the sleep),
 * with a frame that came without a wake-up (the sleep timed out and the frame was there; see achcore_wait), or
 * woken with two or more new frames (one of them may have come without a wake-up: a short look, see there). */
enum { WAIT_NONE = 0, WAIT_WOKEN = 1, WAIT_UNWOKEN = 2, WAIT_SEVERAL = 3 };

#define ACHCORE_MAGIC 0xB07511F3u
#define ACHCORE_GUARD_HEADER 0x1A2A3A4A5A6A7A8AULL
#define ACHCORE_GUARD_INDEX 0x1B2B3B4B5B6B7B8BULL
#define ACHCORE_GUARD_DATA 0x1C2C3C4C5C6C7C8CULL
#define ACHCORE_LOCK_SLICE_NS 50000000LL /* a busy channel lock is waited for in slices this long (achcore_lock) */
#define ACHCORE_IDLE_SLICE_NS 50000000LL /* libach: a waiting reader re-checks cancel this often */
#define ACHCORE_UNWOKEN_POLL_NS 300000LL /* look at last_seq this often after a frame came without a wake-up */
#define ACHCORE_UNWOKEN_HOLD_NS 10000000000LL /* ... for this long after the last such frame */
#define ACHCORE_UNWOKEN_PROBE_NS 300000000LL /* ... and for this long after a wake-up that found several frames */
#define ACHCORE_LATE_LOOK_NS 1000000LL /* a timed-out look that returned this much late proves no unwoken frame */

/* header words, in u64 units from the start of the file (ach-format.md 2.1) */
#define ACHCORE_Q_LEN 1
#define ACHCORE_Q_INDEX_CNT 11
#define ACHCORE_Q_DATA_SIZE 12
#define ACHCORE_Q_DATA_HEAD 13
#define ACHCORE_Q_DATA_FREE 14
#define ACHCORE_Q_INDEX_HEAD 15
#define ACHCORE_Q_INDEX_FREE 16

typedef struct achcore {
    char *base;               /* the mapped file; NULL once detached */
    volatile uint64_t *q;     /* the file as u64 words */
    pthread_mutex_t *mutex;
    pthread_cond_t *cond;
    volatile int32_t *dirty;
    volatile uint64_t *last_seq;
    volatile uint64_t *index; /* index[0].size */
    char *data;               /* data ring */
    uint64_t cnt, dsize, len; /* geometry validated at open */
    size_t off_guard_h, off_guard_i, off_guard_d;
    volatile int *lost;       /* set when the file vanished under the mapping */
    int no_guard;             /* what lost points to without a guard: always 0 */
    uint64_t seq, next;       /* reader state (libach: seq_num, next_index) */
    int woken;                /* how the last wait ended: WAIT_NONE / WAIT_WOKEN / WAIT_UNWOKEN */
    long long unwoken_until;  /* CLOCK_MONOTONIC ns until which waits poll (achcore_poll_ns) */
} achcore_t;

static inline long long achcore_mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* Point c at a mapped channel. Offsets are from the start of the file; the geometry must be the file's
 * (len = header + 24 * cnt + dsize + 24). Returns 0, or -1 for a layout this libc cannot use or a bad geometry. */
static inline int achcore_attach(achcore_t *c, char *base, size_t mutex_off, size_t cond_off, size_t dirty_off,
                          size_t last_off, size_t header_size, uint64_t cnt, uint64_t dsize, uint64_t len,
                          volatile int *lost) {
    memset(c, 0, sizeof *c);
    if (cond_off - mutex_off != sizeof(pthread_mutex_t))
        return -1;
    if (cnt == 0 || dsize == 0 || cnt > (1ULL << 40) || dsize > (1ULL << 50) ||
        len != (uint64_t)header_size + 24 * cnt + dsize + 24)
        return -1;
    c->base = base;
    c->q = (volatile uint64_t *)base;
    c->mutex = (pthread_mutex_t *)(base + mutex_off);
    c->cond = (pthread_cond_t *)(base + cond_off);
    c->dirty = (volatile int32_t *)(base + dirty_off);
    c->last_seq = (volatile uint64_t *)(base + last_off);
    c->cnt = cnt;
    c->dsize = dsize;
    c->len = len;
    c->lost = lost ? lost : &c->no_guard;
    c->index = (volatile uint64_t *)(base + header_size + 8);
    c->data = base + header_size + 16 + 24 * cnt;
    c->off_guard_h = header_size;
    c->off_guard_i = header_size + 8 + 24 * cnt;
    c->off_guard_d = header_size + 16 + 24 * cnt + dsize;
    c->seq = 0; /* libach ach_open: seq_num = 0, next_index = 1 */
    c->next = 1;
    return 0;
}

/* libach check_guards, plus the geometry this handle was opened with: magic, len, index_cnt, data_size. */
static inline int achcore_header_ok(const achcore_t *c) {
    volatile uint64_t *q = c->q;
    uint64_t g_h, g_i, g_d;
    memcpy(&g_h, c->base + c->off_guard_h, 8);
    memcpy(&g_i, c->base + c->off_guard_i, 8);
    memcpy(&g_d, c->base + c->off_guard_d, 8); /* may be unaligned */
    return g_h == ACHCORE_GUARD_HEADER && g_i == ACHCORE_GUARD_INDEX && g_d == ACHCORE_GUARD_DATA &&
           (uint32_t)q[0] == ACHCORE_MAGIC && q[ACHCORE_Q_LEN] == c->len && q[ACHCORE_Q_INDEX_CNT] == c->cnt &&
           q[ACHCORE_Q_DATA_SIZE] == c->dsize;
}

/* The ring counters (read once by the caller, under the lock) are in range: every put, libach's creation and
 * `mds-ach repair` keep them so. */
static inline int achcore_counters_ok(const achcore_t *c, uint64_t index_head, uint64_t index_free,
                                      uint64_t data_head, uint64_t data_free) {
    return index_head < c->cnt && index_free <= c->cnt && data_head < c->dsize && data_free <= c->dsize;
}

/* A live index entry: a non-empty frame inside the data ring, with a sequence number that has been issued. */
static inline int achcore_entry_ok(uint64_t size, uint64_t offset, uint64_t seq, uint64_t dsize, uint64_t last) {
    return size != 0 && offset < dsize && size <= dsize - offset && seq != 0 && seq <= last;
}

/* libach chan_lock: lock, make a dead owner's mutex consistent, refuse a dirty channel. A busy lock (another
 * process mid-put, or stopped while holding it) is waited for as long as it takes when lock_ns < 0, else at most
 * lock_ns (then ACHCORE_LOCK_TIMED_OUT, the channel untouched). The wait is cut into ACHCORE_LOCK_SLICE_NS timed
 * locks, and between them the header is looked at again: a waiter parked in the kernel would otherwise never
 * notice that the file was truncated under it. pthread_mutex_timedlock takes a CLOCK_REALTIME deadline (POSIX);
 * a clock step only lengthens or shortens one slice. */
static inline int achcore_lock(achcore_t *c, long long lock_ns) {
    int r = pthread_mutex_trylock(c->mutex);
    if (r == EBUSY) {
        long long end = lock_ns < 0 ? -1 : achcore_mono_ns() + lock_ns;
        for (;;) {
            long long slice = ACHCORE_LOCK_SLICE_NS;
            if (end >= 0 && end - achcore_mono_ns() < slice)
                slice = end - achcore_mono_ns();
            if (slice < 0)
                slice = 0;
            struct timespec ts;
            clock_gettime(CLOCK_REALTIME, &ts);
            long long ns = ts.tv_nsec + slice;
            ts.tv_sec += (time_t)(ns / 1000000000LL);
            ts.tv_nsec = (long)(ns % 1000000000LL);
            ACHCORE_BLOCKING_BEGIN
            r = pthread_mutex_timedlock(c->mutex, &ts);
            ACHCORE_BLOCKING_END
            if (r != ETIMEDOUT)
                break;
            if (*c->lost || !achcore_header_ok(c))
                return ACH_CORRUPT;
            if (end >= 0 && achcore_mono_ns() >= end)
                return ACHCORE_LOCK_TIMED_OUT;
        }
    }
    if (r == EOWNERDEAD) {
        pthread_mutex_consistent(c->mutex);
    } else if (r == ENOTRECOVERABLE) {
        return ACH_CORRUPT;
    } else if (r) {
        return ACH_FAILED_SYSCALL;
    }
    if (*c->dirty) {
        pthread_mutex_unlock(c->mutex);
        return ACH_CORRUPT;
    }
    return ACH_OK;
}

/* After the unlock: futex sleepers (this project's readers, Python and C) on the low word of last_seq, then
 * golems' libach readers in the condvar. */
static inline void achcore_wake_all(achcore_t *c) {
    syscall(SYS_futex, (void *)c->last_seq, FUTEX_WAKE, INT_MAX, NULL, NULL, 0);
    pthread_cond_broadcast(c->cond);
}

/* libach's free(i) of a live entry, which is read once and checked first: 0 (nothing changed) if it is damaged. */
static inline int achcore_evict(volatile uint64_t *e, uint64_t dsize, uint64_t last, uint64_t *data_free,
                                uint64_t *index_free) {
    uint64_t size = e[0], offset = e[1], seq = e[2];
    if (!achcore_entry_ok(size, offset, seq, dsize, last))
        return 0;
    *data_free += size;
    *index_free += 1;
    e[0] = e[1] = e[2] = 0;
    return 1;
}

/* libach ach_put steps 1-7 (ach-format.md section 4); caller holds the lock. Every value read from the file is
 * read once and checked before it is used. Returns with dirty = 0, except when an index entry turns out damaged
 * half-way: ACH_CORRUPT with dirty = 1, so every client sees the channel corrupt until `mds-ach repair` (as after
 * a writer died mid-put). Damaged counters are refused before anything is written. */
static inline int achcore_write_locked(achcore_t *c, const char *src, uint64_t n) {
    volatile uint64_t *q = c->q, *ix = c->index;
    uint64_t cnt = c->cnt, dsize = c->dsize, last = *c->last_seq;
    uint64_t index_head = q[ACHCORE_Q_INDEX_HEAD], index_free = q[ACHCORE_Q_INDEX_FREE];
    uint64_t data_head = q[ACHCORE_Q_DATA_HEAD], data_free = q[ACHCORE_Q_DATA_FREE];
    if (!achcore_counters_ok(c, index_head, index_free, data_head, data_free) || last == UINT64_MAX)
        return ACH_CORRUPT; /* (a last_seq that cannot be incremented is as damaged as a wild counter) */
    *c->dirty = 1;
    uint64_t slot = index_head, i;
    if (index_free == 0 && !achcore_evict(ix + 3 * index_head, dsize, last, &data_free, &index_free))
        return ACH_CORRUPT; /* index full: drop the oldest frame, which sits in our slot */
    if (dsize - data_head < n) { /* tail wrap: drop frames after data_head, restart at 0 */
        i = (index_head + index_free) % cnt;
        while (ix[3 * i + 1] > data_head) {
            if (!achcore_evict(ix + 3 * i, dsize, last, &data_free, &index_free))
                return ACH_CORRUPT;
            i = (i + 1) % cnt;
        }
        if (i == index_head) {
            data_free = dsize;
        } else {
            volatile uint64_t *oldest = ix + 3 * ((index_head + index_free) % cnt);
            uint64_t size = oldest[0], offset = oldest[1], seq = oldest[2];
            if (!achcore_entry_ok(size, offset, seq, dsize, last))
                return ACH_CORRUPT;
            data_free = offset;
        }
        data_head = 0;
    }
    i = (index_head + index_free) % cnt;
    while (data_free < n) { /* clear overlap with the oldest frames */
        if (i == index_head)
            data_free = dsize;
        else if (!achcore_evict(ix + 3 * i, dsize, last, &data_free, &index_free))
            return ACH_CORRUPT;
        i = (i + 1) % cnt;
    }
    if (dsize - data_head < n) { /* libach's sanity check; cannot happen */
        q[ACHCORE_Q_DATA_HEAD] = data_head;
        q[ACHCORE_Q_DATA_FREE] = data_free;
        q[ACHCORE_Q_INDEX_FREE] = index_free;
        *c->dirty = 0;
        return ACH_BUG;
    }
    memcpy(c->data + data_head, src, n);
    uint64_t seq = last + 1;
    *c->last_seq = seq;
    volatile uint64_t *e = ix + 3 * slot;
    e[0] = n;
    e[1] = data_head;
    e[2] = seq;
    q[ACHCORE_Q_DATA_HEAD] = (data_head + n) % dsize;
    q[ACHCORE_Q_DATA_FREE] = data_free - n;
    q[ACHCORE_Q_INDEX_HEAD] = (index_head + 1) % cnt;
    q[ACHCORE_Q_INDEX_FREE] = index_free - 1;
    *c->dirty = 0;
    return ACH_OK;
}

/* libach ach_get steps 3-7; caller holds the lock. Sets *size (needed size on OVERFLOW). Values from the file
 * are read once and checked before use, as in achcore_write_locked. */
static inline int achcore_read_locked(achcore_t *c, char *dst, uint64_t cap, int options, uint64_t *size) {
    volatile uint64_t *q = c->q, *ix = c->index;
    uint64_t last = *c->last_seq, seq = c->seq, cnt = c->cnt, ri;
    uint64_t index_head = q[ACHCORE_Q_INDEX_HEAD], index_free = q[ACHCORE_Q_INDEX_FREE];
    *size = 0;
    if (!achcore_counters_ok(c, index_head, index_free, q[ACHCORE_Q_DATA_HEAD], q[ACHCORE_Q_DATA_FREE]))
        return ACH_CORRUPT;
    if (last == 0 || (seq == last && !(options & ACH_O_COPY)))
        return ACH_STALE_FRAMES;
    if (options & ACH_O_LAST)
        ri = (index_head + cnt - 1) % cnt;
    else if (c->next < cnt && ix[3 * c->next + 2] == seq + 1)
        ri = c->next;
    else if (seq == last)
        ri = (index_head + cnt - 1) % cnt;
    else
        ri = (index_head + index_free) % cnt;
    volatile uint64_t *e = ix + 3 * ri;
    uint64_t fsize = e[0], offset = e[1], eseq = e[2];
    if (!achcore_entry_ok(fsize, offset, eseq, c->dsize, last)) {
        if (fsize == 0 && offset == 0 && eseq == 0) { /* an empty ring (a repair kept no frame): nothing to miss */
            c->seq = last;
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
    memcpy(dst, c->data + offset, fsize);
    c->seq = eseq;
    c->next = (ri + 1) % cnt;
    *size = fsize;
    return eseq > seq + 1 ? ACH_MISSED_FRAME : ACH_OK;
}

/* header, lock, read, unlock: a complete non-blocking libach get. */
static inline int achcore_get_once(achcore_t *c, char *dst, uint64_t cap, int options, uint64_t *size, long long lock_ns) {
    *size = 0;
    if (!achcore_header_ok(c))
        return ACH_CORRUPT;
    int r = achcore_lock(c, lock_ns);
    if (r)
        return r;
    r = achcore_read_locked(c, dst, cap, options, size);
    pthread_mutex_unlock(c->mutex);
    return *c->lost ? ACH_CORRUPT : r;
}

/* A complete libach put: checks, lock, write, unlock, wake every kind of waiter. */
static inline int achcore_put(achcore_t *c, const char *src, uint64_t n, long long lock_ns) {
    int r;
    if (n == 0)
        return ACH_EINVAL;
    if (!achcore_header_ok(c))
        return ACH_CORRUPT;
    if (n > c->dsize)
        return ACH_OVERFLOW;
    if ((r = achcore_lock(c, lock_ns)) != ACH_OK)
        return r;
    r = achcore_write_locked(c, src, n);
    pthread_mutex_unlock(c->mutex);
    achcore_wake_all(c);
    return *c->lost ? ACH_CORRUPT : r;
}

/* libach ach_flush: mark every frame as seen, under the lock. */
static inline int achcore_flush(achcore_t *c, long long lock_ns) {
    if (!achcore_header_ok(c))
        return ACH_CORRUPT;
    int r = achcore_lock(c, lock_ns);
    if (r == ACH_OK) {
        uint64_t index_head = c->q[ACHCORE_Q_INDEX_HEAD];
        if (achcore_counters_ok(c, index_head, c->q[ACHCORE_Q_INDEX_FREE], c->q[ACHCORE_Q_DATA_HEAD],
                                c->q[ACHCORE_Q_DATA_FREE])) {
            c->seq = *c->last_seq;
            c->next = index_head;
        } else {
            r = ACH_CORRUPT;
        }
        pthread_mutex_unlock(c->mutex);
    }
    return *c->lost ? ACH_CORRUPT : r;
}

/* How often the next wait should look at last_seq by itself (0: only when woken), and record how the last wait
 * ended: a frame without a wake-up keeps the handle polling for ACHCORE_UNWOKEN_HOLD_NS (a caller with its own
 * tunables does this bookkeeping itself). */
static inline long long achcore_poll_ns(achcore_t *c, long long now) {
    if (c->woken == WAIT_UNWOKEN)
        c->unwoken_until = now + ACHCORE_UNWOKEN_HOLD_NS;
    else if (c->woken == WAIT_SEVERAL && c->unwoken_until < now + ACHCORE_UNWOKEN_PROBE_NS)
        c->unwoken_until = now + ACHCORE_UNWOKEN_PROBE_NS;
    c->woken = WAIT_NONE;
    return now < c->unwoken_until ? ACHCORE_UNWOKEN_POLL_NS : 0;
}

/* Sleep (lock-free, on the last_seq futex) until last_seq differs from this handle's seq, for at most slice_ns;
 * with poll_ns > 0 look at last_seq at least that often. Sets c->woken. Returns 1 when last_seq moved, 0 when
 * the slice ended (or a signal interrupted the sleep: the caller handles it and comes back). The look at last_seq
 * is only a hint; the get that follows decides under the lock. A process killed in here leaves nothing behind. */
static inline int achcore_wait(achcore_t *c, long long slice_ns, long long poll_ns) {
    uint64_t seen = c->seq;
    uint64_t last = *c->last_seq;
    c->woken = WAIT_NONE;
    if (last != seen)
        return 1;
    long long end = achcore_mono_ns() + slice_ns;
    for (;;) {
        long long left = end - achcore_mono_ns();
        if (left <= 0)
            return 0;
        long long span = poll_ns > 0 && poll_ns < left ? poll_ns : left;
        long long span_end = achcore_mono_ns() + span;
        struct timespec ts = {(time_t)(span / 1000000000LL), (long)(span % 1000000000LL)};
        long fr;
        int err;
        ACHCORE_BLOCKING_BEGIN
        fr = syscall(SYS_futex, (void *)c->last_seq, FUTEX_WAIT, (uint32_t)last, &ts, NULL, 0);
        err = errno;
        ACHCORE_BLOCKING_END
        uint64_t now_last = *c->last_seq;
        if (now_last != seen) {
            /* timed out with a frame there: nobody woke us. Woken with two or more new frames proves nothing: a
             * reader that waited for a CPU (a busy machine) finds a waking writer's next frames too; taken for a
             * broadcast-only writer, each such reader polled every ACHCORE_UNWOKEN_POLL_NS for 10 s (1-3 % of a
             * core per reader). But on a channel a waking writer also streams to, a broadcast-only writer's frames
             * are only ever seen with the waking writer's next one (never at the end of a slice): so the caller
             * looks briefly (ACHCORE_UNWOKEN_PROBE_NS), long enough for such a frame to time a look out. */
            int timed_out = fr == -1 && err == ETIMEDOUT;
            /* A timed-out look that got its CPU late (a busy machine) may find a waking writer's frame put after
             * the timeout, its wake-up lost on nobody: proof of nothing, so only a short look too. */
            int late = achcore_mono_ns() - span_end > ACHCORE_LATE_LOOK_NS;
            c->woken = timed_out && !late ? WAIT_UNWOKEN
                       : timed_out || now_last - seen >= 2 ? WAIT_SEVERAL : WAIT_WOKEN;
            return 1;
        }
        if (!(fr == -1 && err == ETIMEDOUT))
            return 0; /* woken without a frame (cancel, close) or a signal: the caller looks and comes back */
        last = now_last;
    }
}

#endif /* MDS_ACHCORE_H */
