/*
 * ach.h -- the C API of mds_ach's libach: the published interface of golems' libach 2.0 (names, values, struct
 * sizes), for the calls C clients use, over the same shared-memory channels as the Python nodes.
 *
 * Programs written for libach 2.0 compile unchanged against this header and link with -lach; binaries built
 * against golems' header run against this library (same soname, same struct sizes). Differences, all on purpose:
 *  - ach_get(ACH_O_WAIT) sleeps on a futex keyed on the channel's last_seq word, not in the channel's condvar, so
 *    a reader killed inside its wait never wedges the channel's writers (glibc's condvar would). Puts wake both
 *    this library's and golems' readers; frames from writers that only broadcast the condvar (golems' libach)
 *    are noticed within ~0.3 ms once the first has been seen (see mds_ach/ach/achcore.h).
 *  - Only POSIX shared memory (/dev/shm/achshm-NAME): ACH_MAP_ANON and ACH_MAP_KERNEL give ACH_ENOTSUP, and
 *    ach_attr_set_lock_source(attr, 1) gives ACH_ENOTSUP.
 *  - ach_create builds the file under a temporary name and links it into place, with every page allocated, so
 *    no client ever opens a half-initialised channel and a full /dev/shm fails at creation, not with SIGBUS.
 * Installed by `make setup` as $VENV/include/ach.h with $VENV/lib/libach.so and $VENV/lib/pkgconfig/ach.pc.
 */
#ifndef ACH_H
#define ACH_H

#include <signal.h>
#include <stddef.h>
#include <stdint.h>
#include <sys/types.h>
#include <time.h>

#ifdef __cplusplus
#define ACH_RESTRICT
extern "C" {
#elif defined(__STDC_VERSION__) && __STDC_VERSION__ >= 199901L
#define ACH_RESTRICT restrict
#else
#define ACH_RESTRICT
#endif

#ifdef __GNUC__
#define ACH_WARN_UNUSED __attribute__((warn_unused_result))
#else
#define ACH_WARN_UNUSED
#endif

#define ACH_DEFAULT_CLOCK CLOCK_MONOTONIC
#define ACH_DEFAULT_FRAME_COUNT 16
#define ACH_DEFAULT_FRAME_SIZE 512
#define ACH_CHAN_NAME_MAX 64ul

/* Result of every call (libach's values; ach_result_to_string gives the name). */
typedef enum ach_status {
    ACH_OK = 0,             /* success */
    ACH_OVERFLOW = 1,       /* get: buffer too small (frame_size = needed); put: frame larger than the ring */
    ACH_INVALID_NAME = 2,   /* name empty, >= 64 characters, starting with '.', or not [A-Za-z0-9_.-] */
    ACH_BAD_SHM_FILE = 3,   /* not an Ach channel file */
    ACH_FAILED_SYSCALL = 4, /* a system call failed (ach_errstr says which) */
    ACH_EAGAIN = 5,         /* no new frame */
    ACH_MISSED_FRAME = 6,   /* frames were skipped; data still returned */
    ACH_TIMEOUT = 7,        /* nothing new before the deadline */
    ACH_EEXIST = 8,         /* channel already exists */
    ACH_ENOENT = 9,         /* no such channel */
    ACH_CLOSED = 10,        /* unused */
    ACH_BUG = 11,           /* internal error (or the channel was re-created under an open handle) */
    ACH_EINVAL = 12,        /* invalid argument (e.g. a put of 0 bytes) */
    ACH_CORRUPT = 13,       /* bad guards, or a writer died mid-put (`mds-ach repair` recovers it) */
    ACH_BAD_HEADER = 14,    /* achd: invalid header */
    ACH_EACCES = 15,        /* permission denied */
    ACH_CANCELED = 16,      /* ach_cancel was called on this handle */
    ACH_EFAULT = 17,        /* bad address */
    ACH_EINTR = 18,         /* interrupted (internal) */
    ACH_ENOTSUP = 19        /* not supported by this library */
} ach_status_t;

#define ACH_STALE_FRAMES ACH_EAGAIN
#define ACH_LOCKED ACH_EAGAIN

#define ACH_STATUS_MASK(r) (1 << (r))

enum ach_mask {
    ACH_MASK_OK = ACH_STATUS_MASK(ACH_OK),
    ACH_MASK_OVERFLOW = ACH_STATUS_MASK(ACH_OVERFLOW),
    ACH_MASK_INVALID_NAME = ACH_STATUS_MASK(ACH_INVALID_NAME),
    ACH_MASK_BAD_SHM_FILE = ACH_STATUS_MASK(ACH_BAD_SHM_FILE),
    ACH_MASK_FAILED_SYSCALL = ACH_STATUS_MASK(ACH_FAILED_SYSCALL),
    ACH_MASK_EAGAIN = ACH_STATUS_MASK(ACH_EAGAIN),
    ACH_MASK_MISSED_FRAME = ACH_STATUS_MASK(ACH_MISSED_FRAME),
    ACH_MASK_TIMEOUT = ACH_STATUS_MASK(ACH_TIMEOUT),
    ACH_MASK_EEXIST = ACH_STATUS_MASK(ACH_EEXIST),
    ACH_MASK_ENOENT = ACH_STATUS_MASK(ACH_ENOENT),
    ACH_MASK_CLOSED = ACH_STATUS_MASK(ACH_CLOSED),
    ACH_MASK_BUG = ACH_STATUS_MASK(ACH_BUG),
    ACH_MASK_EINVAL = ACH_STATUS_MASK(ACH_EINVAL),
    ACH_MASK_CORRUPT = ACH_STATUS_MASK(ACH_CORRUPT),
    ACH_MASK_BAD_HEADER = ACH_STATUS_MASK(ACH_BAD_HEADER),
    ACH_MASK_EACCES = ACH_STATUS_MASK(ACH_EACCES),
    ACH_MASK_CANCELED = ACH_STATUS_MASK(ACH_CANCELED),
    ACH_MASK_EFAULT = ACH_STATUS_MASK(ACH_EFAULT),
    ACH_MASK_EINTR = ACH_STATUS_MASK(ACH_EINTR),
    ACH_MASK_ENOTSUP = ACH_STATUS_MASK(ACH_ENOTSUP),
    ACH_MASK_LOCKED = ACH_STATUS_MASK(ACH_LOCKED),
    ACH_MASK_NONE = 0,
    ACH_MASK_ALL = 0xffffffff
};

#define ACH_MASK_STALE_FRAMES ACH_MASK_EAGAIN

typedef enum ach_mask ach_mask_t;

static inline int ach_status_mask(enum ach_status status) { return ACH_STATUS_MASK(status); }

static inline int ach_status_match(enum ach_status status, int mask) {
    return (ACH_STATUS_MASK(status) & mask) ? 1 : 0;
}

/* Options of ach_get (or-ed). */
typedef enum {
    ACH_O_NONBLOCK = 0x00, /* default: return at once */
    ACH_O_FIRST = 0x00,    /* default: the oldest frame not yet seen */
    ACH_O_ABSTIME = 0x00,  /* default: the timeout is absolute, on the channel's clock (CLOCK_MONOTONIC) */
    ACH_O_WAIT = 0x01,     /* block until there is a frame this handle has not seen */
    ACH_O_LAST = 0x02,     /* the newest frame, skipping older ones */
    ACH_O_COPY = 0x04,     /* return the last frame even if already seen */
    ACH_O_RELTIME = 0x08   /* the timeout is relative */
} ach_get_opts_t;

/* Where a channel's memory lives. Only the POSIX shared-memory mapping is supported here. */
enum ach_map { ACH_MAP_DEFAULT = 0, ACH_MAP_ANON = 1, ACH_MAP_USER = 2, ACH_MAP_KERNEL = 3 };

struct ach_header; /* the shared-memory layout, not for clients */

/* Kernel-device get options (golems' klinux backend); part of the channel struct's layout only. */
typedef struct achk_opt {
    int options;
    struct timespec reltime;
} achk_opt_t;

/* Attributes of ach_open (64 bytes, as libach's). */
typedef struct ach_attr {
    union {
        struct {
            enum ach_map map;
            struct ach_header *shm;
            union {
                uint64_t reserve_bits;
                struct {
                    unsigned int lock_source : 1;
                };
            };
        };
        uint64_t reserved_size[8];
    };
} ach_attr_t;

void ach_attr_init(ach_attr_t *attr);
enum ach_status ACH_WARN_UNUSED ach_attr_set_shm(ach_attr_t *attr, struct ach_header *shm);
enum ach_status ach_attr_set_lock_source(ach_attr_t *attr, int lock_source);

/* Attributes of ach_create (128 bytes, as libach's). */
typedef struct ach_create_attr {
    union {
        struct {
            enum ach_map map;
            struct ach_header *shm;
            clockid_t clock;
            union {
                uint64_t reserve_bits;
                struct {
                    unsigned int truncate : 1;  /* replace an existing channel */
                    unsigned int set_clock : 1; /* use `clock` for the condvar and timeouts */
                };
            };
        };
        uint64_t reserved[16];
    };
} ach_create_attr_t;

void ach_create_attr_init(ach_create_attr_t *attr);
enum ach_status ACH_WARN_UNUSED ach_create_attr_set_clock(ach_create_attr_t *attr, clockid_t clock);
enum ach_status ACH_WARN_UNUSED ach_create_attr_set_map(ach_create_attr_t *attr, enum ach_map map);
enum ach_status ACH_WARN_UNUSED ach_create_attr_set_truncate(ach_create_attr_t *attr, int truncate);
enum ach_status ACH_WARN_UNUSED ach_create_attr_get_shm(ach_create_attr_t *attr, struct ach_header **shm);

struct ach_channel_vtab;
struct achcore;

/* An open channel (128 bytes, as libach's; the first fields keep libach's names and places). Use it through the
 * functions below. One handle per thread, as with libach (ach_cancel from another thread or a signal handler is
 * the exception). */
typedef struct ach_channel {
    union {
        struct {
            struct ach_header *shm; /* the mapped file */
            size_t len;             /* length of the mapping */
            int fd;                 /* file descriptor of the mapped file */
            union {
                uint64_t seq_num;   /* last sequence number read */
                achk_opt_t k_opts;
            };
            size_t next_index;      /* next index entry to try */
            clockid_t clock;        /* the channel's clock */
            volatile sig_atomic_t cancel;
            const struct ach_channel_vtab *vtab;
            int fd_source_lock;
            struct achcore *core;   /* mds_ach: the shared channel code's state (mds_ach/ach/achcore.h) */
        };
        uint64_t reserved[16];
    };
} ach_channel_t;

enum ach_status ACH_WARN_UNUSED ach_channel_fd(const struct ach_channel *channel, int *file_descriptor);
enum ach_status ACH_WARN_UNUSED ach_channel_map(const struct ach_channel *channel, enum ach_map *map);
enum ach_status ACH_WARN_UNUSED ach_channel_clock(const struct ach_channel *channel, clockid_t *clock);

/* Create channel `name` with frame_cnt frames of nominal frame_size bytes (0: 16 x 512). attr may be NULL. */
enum ach_status ACH_WARN_UNUSED ach_create(const char *name, size_t frame_cnt, size_t frame_size,
                                           ach_create_attr_t *attr);

/* Open channel `name` into `channel`. attr may be NULL. */
enum ach_status ACH_WARN_UNUSED ach_open(ach_channel_t *channel, const char *name, ach_attr_t *attr);

/* Read a frame into buf (size bytes); *frame_size gets its length (the needed size on ACH_OVERFLOW). abstime
 * bounds an ACH_O_WAIT (NULL: forever), absolute on the channel's clock unless ACH_O_RELTIME. */
enum ach_status ACH_WARN_UNUSED ach_get(ach_channel_t *chan, void *buf, size_t size, size_t *frame_size,
                                        const struct timespec *ACH_RESTRICT abstime, int options);

/* Put len bytes (len > 0) as one frame; wakes every waiting reader. */
enum ach_status ach_put(ach_channel_t *channel, const void *buf, size_t len);

/* Mark every frame in the channel as seen by this handle. */
enum ach_status ACH_WARN_UNUSED ach_flush(ach_channel_t *chan);

/* Unmap and close. */
enum ach_status ACH_WARN_UNUSED ach_close(ach_channel_t *chan);

/* "ACH_OK", "ACH_OVERFLOW", ... ("UNKNOWN" for other values). */
const char *ach_result_to_string(ach_status_t result);

/* A description of this thread's most recent error. */
const char *ach_errstr(void);

/* Set this thread's error description (what ach_errstr returns next), as golems' libach exports. */
void ach_set_errstr(const char *str);

/* Print the channel's header to stderr (debugging). */
void ach_dump(struct ach_header *shm);

/* Set the permissions of the channel's file. */
enum ach_status ach_chmod(ach_channel_t *chan, mode_t mode);

/* Remove channel `name` (open handles keep working on the old memory). */
enum ach_status ACH_WARN_UNUSED ach_unlink(const char *name);

/* Attributes of ach_cancel (64 bytes, as libach's). */
typedef struct ach_cancel_attr {
    union {
        struct {
            unsigned int async_unsafe : 1;
        };
        int64_t reserved[8];
    };
} ach_cancel_attr_t;

void ach_cancel_attr_init(ach_cancel_attr_t *attr);
enum ach_status ACH_WARN_UNUSED ach_cancel_attr_set_async_unsafe(ach_cancel_attr_t *attr, int asyn_unsafe);

/* Make this handle's waiting and later ach_get / ach_flush return ACH_CANCELED (sticky until ach_open). Safe in a
 * signal handler and from another thread. attr may be NULL. */
enum ach_status ACH_WARN_UNUSED ach_cancel(ach_channel_t *chan, const ach_cancel_attr_t *attr);

#ifdef __cplusplus
}
#endif

#endif /* ACH_H */
