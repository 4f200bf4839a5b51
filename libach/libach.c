/*
 * libach.c -- mds_ach's libach for C clients: golems' libach 2.0 C API and ABI (ach.h) over the project's channel
 * code (mds_ach/ach/achcore.h, shared with the Python fast path), so C programs written for the original MDS-Ach
 * build and run unchanged against the project's channels and Python nodes.
 *
 * This file only does what is specific to C clients: opening, creating and removing channel files, the handle
 * (ach_channel_t), timeouts, cancel, attributes and status names. Every put, get, flush, lock and wake-up is
 * achcore's, byte for byte what the Python nodes do (test/test_libach.py checks it against them and against the
 * golden files written by golems' libach).
 */
#define _GNU_SOURCE
#include "ach.h"

#include "../mds_ach/ach/achcore.h"

#include <fcntl.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <sys/stat.h>

#define SHM_DIR "/dev/shm"
#define SHM_PREFIX "achshm-"

/* The shared-memory header (ach-format.md 2.1): the fields at fixed offsets, then the sync objects whose size is
 * glibc's. */
struct ach_header {
    uint32_t magic;
    size_t len;
    char name[ACH_CHAN_NAME_MAX + 1];
    union {
        struct {
            size_t index_cnt, data_size, data_head, data_free, index_head, index_free;
            clockid_t clock;
            int anon;
        };
        uint64_t reserved[16];
    };
    struct {
        pthread_mutex_t mutex;
        pthread_cond_t cond;
        int dirty;
    } sync;
    uint64_t last_seq;
};

_Static_assert(offsetof(struct ach_header, index_cnt) == 88, "header: index_cnt at 88");
_Static_assert(offsetof(struct ach_header, clock) == 136, "header: clock at 136");
_Static_assert(offsetof(struct ach_header, sync) == 216, "header: mutex at 216");
_Static_assert(sizeof(ach_channel_t) == 128, "ach_channel_t is libach's 128 bytes");
_Static_assert(sizeof(ach_attr_t) == 64, "ach_attr_t is libach's 64 bytes");
_Static_assert(sizeof(ach_create_attr_t) == 128, "ach_create_attr_t is libach's 128 bytes");
_Static_assert(sizeof(ach_cancel_attr_t) == 64, "ach_cancel_attr_t is libach's 64 bytes");
#if defined(__x86_64__)
_Static_assert(sizeof(struct ach_header) == 320, "x86_64 header is 320 bytes");
#elif defined(__aarch64__)
_Static_assert(sizeof(struct ach_header) == 328, "aarch64 header is 328 bytes");
#endif

#define HDR_SIZE sizeof(struct ach_header)

static uint64_t file_len(uint64_t cnt, uint64_t dsize) { return HDR_SIZE + 24 * cnt + dsize + 24; }

/* ---- errors ---------------------------------------------------------------------------------------------- */

static __thread char errbuf[512];

/* Record what went wrong for ach_errstr and return the status. */
static enum ach_status fail(enum ach_status r, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
static enum ach_status fail(enum ach_status r, const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(errbuf, sizeof errbuf, fmt, ap);
    va_end(ap);
    return r;
}

static enum ach_status errno_status(int err) {
    switch (err) {
    case ENOENT:
        return ACH_ENOENT;
    case EEXIST:
        return ACH_EEXIST;
    case EACCES:
    case EPERM:
        return ACH_EACCES;
    case EINVAL:
        return ACH_EINVAL;
    case EFAULT:
        return ACH_EFAULT;
    case EINTR:
        return ACH_EINTR;
    default:
        return ACH_FAILED_SYSCALL;
    }
}

const char *ach_errstr(void) { return errbuf; }

/* golems' libach exports this too (its callers: achd, the DNS lookups); a copy, so the caller's string may go. */
void ach_set_errstr(const char *str) { snprintf(errbuf, sizeof errbuf, "%s", str ? str : ""); }

const char *ach_result_to_string(ach_status_t result) {
    static const char *const names[] = {
        "ACH_OK",      "ACH_OVERFLOW", "ACH_INVALID_NAME", "ACH_BAD_SHM_FILE", "ACH_FAILED_SYSCALL",
        "ACH_EAGAIN",  "ACH_MISSED_FRAME", "ACH_TIMEOUT", "ACH_EEXIST", "ACH_ENOENT",
        "ACH_CLOSED",  "ACH_BUG",      "ACH_EINVAL",       "ACH_CORRUPT",      "ACH_BAD_HEADER",
        "ACH_EACCES",  "ACH_CANCELED", "ACH_EFAULT",       "ACH_EINTR",        "ACH_ENOTSUP",
    };
    if ((unsigned)result < sizeof names / sizeof names[0])
        return names[result];
    return "UNKNOWN";
}

/* ---- names and files -------------------------------------------------------------------------------------- */

/* libach_name_ok: 1..63 characters of [A-Za-z0-9_.-], not starting with '.'. */
static enum ach_status name_ok(const char *name) {
    if (name == NULL)
        return fail(ACH_INVALID_NAME, "channel name is NULL");
    size_t n = strnlen(name, ACH_CHAN_NAME_MAX);
    if (n == 0 || n >= ACH_CHAN_NAME_MAX)
        return fail(ACH_INVALID_NAME, "channel name must have 1 to 63 characters");
    if (name[0] == '.')
        return fail(ACH_INVALID_NAME, "channel name '%s' starts with '.'", name);
    for (size_t i = 0; i < n; i++) {
        char ch = name[i];
        if (!((ch >= 'a' && ch <= 'z') || (ch >= 'A' && ch <= 'Z') || (ch >= '0' && ch <= '9') || ch == '_' ||
              ch == '.' || ch == '-'))
            return fail(ACH_INVALID_NAME, "channel name '%s' has '%c'; allowed are [A-Za-z0-9_.-]", name, ch);
    }
    return ACH_OK;
}

static void shm_path(char *out, size_t cap, const char *name) { snprintf(out, cap, SHM_DIR "/" SHM_PREFIX "%s", name); }

/* Allocate every page now: a full /dev/shm is an error here, not a SIGBUS in whoever first touches a page. */
static enum ach_status reserve(int fd, uint64_t len, const char *path) {
    int err = posix_fallocate(fd, 0, (off_t)len);
    if (err == 0 || err == EOPNOTSUPP || err == ENODEV)
        return ACH_OK;
    return fail(ACH_FAILED_SYSCALL, "%s: cannot reserve %llu bytes of channel memory: %s (see `df -h " SHM_DIR "`)",
                path, (unsigned long long)len, strerror(err));
}

/* ---- attributes ------------------------------------------------------------------------------------------- */

void ach_attr_init(ach_attr_t *attr) { memset(attr, 0, sizeof *attr); }

enum ach_status ach_attr_set_shm(ach_attr_t *attr, struct ach_header *shm) {
    (void)attr;
    (void)shm;
    return fail(ACH_ENOTSUP, "anonymous channels are not supported");
}

enum ach_status ach_attr_set_lock_source(ach_attr_t *attr, int lock_source) {
    if (lock_source)
        return fail(ACH_ENOTSUP, "the source lock is not supported");
    attr->lock_source = 0;
    return ACH_OK;
}

void ach_create_attr_init(ach_create_attr_t *attr) {
    memset(attr, 0, sizeof *attr);
    attr->clock = ACH_DEFAULT_CLOCK;
}

enum ach_status ach_create_attr_set_clock(ach_create_attr_t *attr, clockid_t clock) {
    attr->clock = clock;
    attr->set_clock = 1;
    return ACH_OK;
}

enum ach_status ach_create_attr_set_map(ach_create_attr_t *attr, enum ach_map map) {
    if (map != ACH_MAP_DEFAULT && map != ACH_MAP_USER)
        return fail(ACH_ENOTSUP, "only shared-memory channels (ACH_MAP_DEFAULT, ACH_MAP_USER) are supported");
    attr->map = map;
    return ACH_OK;
}

enum ach_status ach_create_attr_set_truncate(ach_create_attr_t *attr, int truncate) {
    attr->truncate = truncate ? 1 : 0;
    return ACH_OK;
}

enum ach_status ach_create_attr_get_shm(ach_create_attr_t *attr, struct ach_header **shm) {
    (void)attr;
    (void)shm;
    return fail(ACH_ENOTSUP, "anonymous channels are not supported");
}

void ach_cancel_attr_init(ach_cancel_attr_t *attr) { memset(attr, 0, sizeof *attr); }

enum ach_status ach_cancel_attr_set_async_unsafe(ach_cancel_attr_t *attr, int asyn_unsafe) {
    attr->async_unsafe = asyn_unsafe ? 1 : 0;
    return ACH_OK;
}

/* ---- create / unlink / chmod ------------------------------------------------------------------------------ */

/* Fill a zeroed mapping as libach's ach_create does: sync objects (robust, priority-inheriting, process-shared
 * mutex; process-shared condvar on `clock`), counters, guards, magic, name. */
static enum ach_status init_file(char *base, uint64_t len, const char *name, uint64_t cnt, uint64_t dsize,
                                 clockid_t clock) {
    struct ach_header *h = (struct ach_header *)base;
    pthread_mutexattr_t ma;
    pthread_condattr_t ca;
    int err = pthread_mutexattr_init(&ma);
    if (!err)
        err = pthread_mutexattr_setpshared(&ma, PTHREAD_PROCESS_SHARED);
    if (!err)
        err = pthread_mutexattr_setprotocol(&ma, PTHREAD_PRIO_INHERIT);
    if (!err)
        err = pthread_mutexattr_setrobust(&ma, PTHREAD_MUTEX_ROBUST);
    if (!err)
        err = pthread_mutex_init(&h->sync.mutex, &ma);
    pthread_mutexattr_destroy(&ma);
    if (!err)
        err = pthread_condattr_init(&ca);
    if (!err) {
        err = pthread_condattr_setpshared(&ca, PTHREAD_PROCESS_SHARED);
        if (!err)
            err = pthread_condattr_setclock(&ca, clock);
        if (!err)
            err = pthread_cond_init(&h->sync.cond, &ca);
        pthread_condattr_destroy(&ca);
    }
    if (err)
        return fail(ACH_FAILED_SYSCALL, "initialising the channel's mutex and condvar: %s", strerror(err));
    h->len = len;
    h->index_cnt = cnt;
    h->data_size = dsize;
    h->data_head = 0;
    h->data_free = dsize;
    h->index_head = 0;
    h->index_free = cnt;
    h->clock = clock;
    uint64_t g;
    g = ACHCORE_GUARD_HEADER;
    memcpy(base + HDR_SIZE, &g, 8);
    g = ACHCORE_GUARD_INDEX;
    memcpy(base + HDR_SIZE + 8 + 24 * cnt, &g, 8);
    g = ACHCORE_GUARD_DATA;
    memcpy(base + HDR_SIZE + 16 + 24 * cnt + dsize, &g, 8);
    h->magic = ACHCORE_MAGIC;
    strncpy(h->name, name, ACH_CHAN_NAME_MAX);
    h->name[ACH_CHAN_NAME_MAX] = '\0';
    return ACH_OK;
}

/* Built under a temporary name and linked into place: nobody ever opens a half-initialised channel. Without
 * truncate an existing channel gives ACH_EEXIST; with it the old file is replaced (processes that have it open
 * keep the old memory instead of being clobbered). The mode is 0666 filtered by the umask, as libach's. */
enum ach_status ach_create(const char *name, size_t frame_cnt, size_t frame_size, ach_create_attr_t *attr) {
    enum ach_status r = name_ok(name);
    if (r)
        return r;
    if (attr && attr->map != ACH_MAP_DEFAULT && attr->map != ACH_MAP_USER)
        return fail(ACH_ENOTSUP, "only shared-memory channels are supported");
    uint64_t cnt = frame_cnt ? frame_cnt : ACH_DEFAULT_FRAME_COUNT;
    uint64_t fsize = frame_size ? frame_size : ACH_DEFAULT_FRAME_SIZE;
    if (cnt > (1ULL << 30) || fsize > (1ULL << 40) || cnt * fsize > (1ULL << 40))
        return fail(ACH_EINVAL, "%llu x %llu bytes is unreasonably large", (unsigned long long)cnt,
                    (unsigned long long)fsize);
    clockid_t clock = attr && attr->set_clock ? attr->clock : ACH_DEFAULT_CLOCK;
    uint64_t dsize = cnt * fsize, len = file_len(cnt, dsize);
    char path[128], tmp[192];
    shm_path(path, sizeof path, name);
    snprintf(tmp, sizeof tmp, SHM_DIR "/." SHM_PREFIX "%s.%d.%ld.tmp", name, (int)getpid(), (long)gettid());
    int fd = open(tmp, O_RDWR | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
    if (fd < 0)
        return fail(errno_status(errno), "%s: %s", tmp, strerror(errno));
    char *base = MAP_FAILED;
    if (ftruncate(fd, (off_t)len) != 0) {
        r = fail(errno_status(errno), "%s: ftruncate: %s", tmp, strerror(errno));
    } else if ((r = reserve(fd, len, path)) == ACH_OK) {
        base = mmap(NULL, len, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
        if (base == MAP_FAILED)
            r = fail(ACH_FAILED_SYSCALL, "%s: mmap: %s", tmp, strerror(errno));
        else
            r = init_file(base, len, name, cnt, dsize, clock);
    }
    if (base != MAP_FAILED)
        munmap(base, len);
    if (r == ACH_OK) {
        int done = attr && attr->truncate ? rename(tmp, path) : link(tmp, path);
        if (done != 0)
            r = errno == EEXIST ? fail(ACH_EEXIST, "channel %s exists (%s)", name, path)
                                : fail(errno_status(errno), "%s: %s", path, strerror(errno));
    }
    close(fd);
    unlink(tmp); /* after link(); a no-op after rename() */
    return r;
}

enum ach_status ach_unlink(const char *name) {
    enum ach_status r = name_ok(name);
    if (r)
        return r;
    char path[128];
    shm_path(path, sizeof path, name);
    if (unlink(path) != 0)
        return fail(errno_status(errno), "%s: %s", path, strerror(errno));
    return ACH_OK;
}

enum ach_status ach_chmod(ach_channel_t *chan, mode_t mode) {
    if (fchmod(chan->fd, mode) != 0)
        return fail(errno_status(errno), "chmod: %s", strerror(errno));
    return ACH_OK;
}

/* ---- open / close ----------------------------------------------------------------------------------------- */

enum ach_status ach_open(ach_channel_t *chan, const char *name, ach_attr_t *attr) {
    memset(chan, 0, sizeof *chan);
    chan->fd = -1;
    chan->fd_source_lock = -1;
    enum ach_status r = name_ok(name);
    if (r)
        return r;
    if (attr && attr->map != ACH_MAP_DEFAULT && attr->map != ACH_MAP_USER)
        return fail(ACH_ENOTSUP, "only shared-memory channels are supported");
    if (attr && attr->lock_source)
        return fail(ACH_ENOTSUP, "the source lock is not supported");
    char path[128];
    shm_path(path, sizeof path, name);
    /* Never through a symbolic link (another user may plant one in /dev/shm to a file of theirs), never block
     * on a FIFO: refuse anything but a regular file, as the Python open does (mds_ach.ach.files). */
    int fd = open(path, O_RDWR | O_CLOEXEC | O_NOFOLLOW | O_NONBLOCK);
    if (fd < 0 && errno == ELOOP)
        return fail(ACH_BAD_SHM_FILE, "%s is a symbolic link: a channel is never opened through one", path);
    if (fd < 0)
        return fail(errno_status(errno), "%s: %s", path, strerror(errno));
    struct stat st;
    uint32_t magic = 0;
    char *base = MAP_FAILED;
    achcore_t *core = NULL;
    struct ach_header *h;
    if (fstat(fd, &st) != 0) {
        r = fail(ACH_FAILED_SYSCALL, "%s: fstat: %s", path, strerror(errno));
        goto out;
    }
    if (!S_ISREG(st.st_mode)) {
        r = fail(ACH_BAD_SHM_FILE, "%s is not a regular file, not a channel file", path);
        goto out;
    }
    if (fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) & ~O_NONBLOCK) != 0) {
        r = fail(ACH_FAILED_SYSCALL, "%s: fcntl: %s", path, strerror(errno));
        goto out;
    }
    if (pread(fd, &magic, 4, 0) != 4 || magic != ACHCORE_MAGIC) {
        r = fail(ACH_BAD_SHM_FILE, "%s: bad magic number (%lld bytes)", path, (long long)st.st_size);
        goto out;
    }
    if ((uint64_t)st.st_size < HDR_SIZE + 24) {
        r = fail(ACH_BAD_SHM_FILE, "%s: truncated, %lld bytes", path, (long long)st.st_size);
        goto out;
    }
    if ((r = reserve(fd, (uint64_t)st.st_size, path)) != ACH_OK) /* libach's `ach mk` leaves the file sparse */
        goto out;
    base = mmap(NULL, (size_t)st.st_size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    if (base == MAP_FAILED) {
        r = fail(ACH_FAILED_SYSCALL, "%s: mmap: %s", path, strerror(errno));
        goto out;
    }
    h = (struct ach_header *)base;
    core = malloc(sizeof *core);
    if (core == NULL) {
        r = fail(ACH_FAILED_SYSCALL, "out of memory");
        goto out;
    }
    if (h->len != (uint64_t)st.st_size || h->index_cnt == 0 || h->data_size == 0 ||
        h->index_cnt > (1ULL << 40) || h->data_size > (1ULL << 50) || h->len != file_len(h->index_cnt, h->data_size) ||
        achcore_attach(core, base, offsetof(struct ach_header, sync.mutex), offsetof(struct ach_header, sync.cond),
                       offsetof(struct ach_header, sync.dirty), offsetof(struct ach_header, last_seq), HDR_SIZE,
                       h->index_cnt, h->data_size, h->len, NULL) != 0) {
        r = fail(ACH_CORRUPT, "%s: inconsistent geometry (len %llu, file %lld bytes, index_cnt %llu, data_size %llu)",
                 path, (unsigned long long)h->len, (long long)st.st_size, (unsigned long long)h->index_cnt,
                 (unsigned long long)h->data_size);
        goto out;
    }
    if (!achcore_header_ok(core)) {
        r = fail(ACH_CORRUPT, "%s: damaged guards", path);
        goto out;
    }
    chan->shm = h;
    chan->len = (size_t)st.st_size;
    chan->fd = fd;
    chan->seq_num = core->seq;
    chan->next_index = core->next;
    chan->clock = h->clock;
    chan->cancel = 0;
    chan->core = core;
    return ACH_OK;
out:
    free(core);
    if (base != MAP_FAILED)
        munmap(base, (size_t)st.st_size);
    close(fd);
    return r;
}

enum ach_status ach_close(ach_channel_t *chan) {
    if (chan->core == NULL)
        return fail(ACH_EINVAL, "ach_close: channel is not open");
    enum ach_status r = achcore_header_ok(chan->core) ? ACH_OK : fail(ACH_CORRUPT, "ach_close: damaged guards");
    munmap((void *)chan->shm, chan->len);
    close(chan->fd);
    free(chan->core);
    chan->core = NULL;
    chan->shm = NULL;
    chan->fd = -1;
    return r;
}

enum ach_status ach_channel_fd(const struct ach_channel *channel, int *file_descriptor) {
    *file_descriptor = channel->fd;
    return ACH_OK;
}

enum ach_status ach_channel_map(const struct ach_channel *channel, enum ach_map *map) {
    (void)channel;
    *map = ACH_MAP_USER;
    return ACH_OK;
}

enum ach_status ach_channel_clock(const struct ach_channel *channel, clockid_t *clock) {
    *clock = channel->clock;
    return ACH_OK;
}

/* ---- put / get / flush / cancel --------------------------------------------------------------------------- */

enum ach_status ach_put(ach_channel_t *chan, const void *buf, size_t len) {
    if (chan->core == NULL)
        return fail(ACH_EINVAL, "ach_put: channel is not open");
    if (buf == NULL && len)
        return fail(ACH_EFAULT, "ach_put: NULL buffer");
    return (enum ach_status)achcore_put(chan->core, (const char *)buf, len, -1);
}

static long long clock_ns(clockid_t clock) {
    struct timespec ts;
    clock_gettime(clock, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* libach ach_get. A waiting get sleeps on the channel's futex (achcore_wait) in slices of at most 50 ms, looking
 * at the cancel flag between them (ach_cancel also wakes it at once). */
enum ach_status ach_get(ach_channel_t *chan, void *buf, size_t size, size_t *frame_size,
                        const struct timespec *ACH_RESTRICT abstime, int options) {
    achcore_t *c = chan->core;
    if (c == NULL)
        return fail(ACH_EINVAL, "ach_get: channel is not open");
    if (buf == NULL && size)
        return fail(ACH_EFAULT, "ach_get: NULL buffer");
    int wait = options & ACH_O_WAIT;
    long long deadline = -1; /* on the channel's clock, ns */
    if (wait && abstime) {
        long long t = (long long)abstime->tv_sec * 1000000000LL + abstime->tv_nsec;
        deadline = (options & ACH_O_RELTIME) ? clock_ns(chan->clock) + t : t;
    }
    uint64_t got = 0;
    int r;
    for (;;) {
        if (chan->cancel) {
            r = ACH_CANCELED;
            break;
        }
        r = achcore_get_once(c, (char *)buf, size, options & ~(ACH_O_WAIT | ACH_O_RELTIME), &got, -1);
        if (!wait || r != ACH_STALE_FRAMES)
            break;
        long long slice = ACHCORE_IDLE_SLICE_NS;
        if (deadline >= 0) {
            long long left = deadline - clock_ns(chan->clock);
            if (left <= 0) {
                r = ACH_TIMEOUT;
                break;
            }
            if (left < slice)
                slice = left;
        }
        achcore_wait(c, slice, achcore_poll_ns(c, achcore_mono_ns()));
    }
    if (wait)
        achcore_poll_ns(c, achcore_mono_ns()); /* remember a frame that came without a wake-up */
    if (frame_size && (r == ACH_OK || r == ACH_MISSED_FRAME || r == ACH_OVERFLOW))
        *frame_size = got;
    chan->seq_num = c->seq;
    chan->next_index = c->next;
    return (enum ach_status)r;
}

enum ach_status ach_flush(ach_channel_t *chan) {
    if (chan->core == NULL)
        return fail(ACH_EINVAL, "ach_flush: channel is not open");
    if (chan->cancel)
        return ACH_CANCELED;
    int r = achcore_flush(chan->core, -1);
    chan->seq_num = chan->core->seq;
    chan->next_index = chan->core->next;
    return (enum ach_status)r;
}

/* Set the sticky flag and wake the channel's futex sleepers (one syscall: async-signal-safe); the waiting
 * ach_get of this handle sees the flag and returns ACH_CANCELED, others go back to sleep. */
enum ach_status ach_cancel(ach_channel_t *chan, const ach_cancel_attr_t *attr) {
    (void)attr;
    if (chan->core == NULL)
        return ACH_EINVAL;
    chan->cancel = 1;
    syscall(SYS_futex, (void *)chan->core->last_seq, FUTEX_WAKE, INT_MAX, NULL, NULL, 0);
    return ACH_OK;
}

void ach_dump(struct ach_header *shm) {
    fprintf(stderr, "Magic: %x\nlen: %zu\nname: %s\nindex_cnt: %zu\nindex_head: %zu\nindex_free: %zu\n"
                    "data_size: %zu\ndata_head: %zu\ndata_free: %zu\nlast_seq: %llu\n",
            shm->magic, shm->len, shm->name, shm->index_cnt, shm->index_head, shm->index_free, shm->data_size,
            shm->data_head, shm->data_free, (unsigned long long)shm->last_seq);
}
