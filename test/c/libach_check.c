/* libach_check.c -- the C side of test/test_libach.py: exercises the project's libach through ach.h exactly as a C
 * client does (built with `cc libach_check.c $(pkg-config --cflags --libs ach)`).
 *
 *   libach_check trace TRACE.txt    replay golems' libach trace (shared/ach-golden/ARCH/trace.txt): every put, get
 *                                   and flush must give the recorded status, frame size, data, reader state and
 *                                   header/index words; the channels are left for the caller to compare the images
 *   libach_check api NAME           the rest of the API: names, create/open/unlink errors, options, timeouts,
 *                                   cancel, chmod, attributes, status names, struct sizes
 *   libach_check put NAME COUNT HZ  put COUNT frames "c-frame-<i>" (HZ > 0: paced), print "put done"
 *   libach_check get NAME COUNT     ACH_O_WAIT-get COUNT frames (5 s each), print each as "frame <text>"
 *   libach_check wait NAME          print "waiting", then wait forever in ach_get(ACH_O_WAIT)
 * Exit status 0 on success; a failed check prints what differed and exits 1.
 */
#define _GNU_SOURCE
#include <ach.h>
#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

static int failures;

#define CHECK(cond, ...)                                                                                          \
    do {                                                                                                          \
        if (!(cond)) {                                                                                            \
            fprintf(stderr, "%s:%d: check failed: %s: ", __FILE__, __LINE__, #cond);                              \
            fprintf(stderr, __VA_ARGS__);                                                                         \
            fputc('\n', stderr);                                                                                  \
            failures++;                                                                                           \
        }                                                                                                         \
    } while (0)

#define STATUS(expr, want)                                                                                        \
    do {                                                                                                          \
        enum ach_status got_ = (expr);                                                                            \
        CHECK(got_ == (want), "%s returned %s, expected %s (%s)", #expr, ach_result_to_string(got_),             \
              ach_result_to_string(want), ach_errstr());                                                          \
    } while (0)

static long long mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static size_t unhex(const char *hex, unsigned char *out) {
    size_t n = 0;
    while (hex[0] && hex[1] && hex[0] != ' ' && hex[0] != '\n') {
        unsigned v;
        sscanf(hex, "%2x", &v);
        out[n++] = (unsigned char)v;
        hex += 2;
    }
    return n;
}

static enum ach_status status_named(const char *text) {
    for (int s = 0; s < 20; s++) {
        const char *name = ach_result_to_string((ach_status_t)s);
        size_t n = strlen(name);
        if (strncmp(text, name, n) == 0 && text[n] == '(')
            return (enum ach_status)s;
    }
    return (enum ach_status)-1;
}

/* ---- trace replay ----------------------------------------------------------------------------------------- */

/* The header words of a channel file, read from the file itself (fixed offsets; dirty/last_seq after glibc's
 * mutex and condvar). */
static void file_words(const char *name, unsigned long long w[8], unsigned long long ix[][3], size_t cnt) {
    char path[128];
    snprintf(path, sizeof path, "/dev/shm/achshm-%s", name);
    int fd = open(path, O_RDONLY);
    struct stat st;
    fstat(fd, &st);
    unsigned char *m = mmap(NULL, (size_t)st.st_size, PROT_READ, MAP_SHARED, fd, 0);
    size_t sync = 216, dirty = sync + sizeof(pthread_mutex_t) + sizeof(pthread_cond_t), last = dirty + 8;
    size_t hdr = last + 8;
    for (int i = 0; i < 6; i++)
        memcpy(&w[i], m + 88 + 8 * i, 8); /* index_cnt data_size data_head data_free index_head index_free */
    int d;
    memcpy(&d, m + dirty, 4);
    w[6] = (unsigned long long)d;
    memcpy(&w[7], m + last, 8);
    for (size_t i = 0; i < cnt; i++)
        memcpy(ix[i], m + hdr + 8 + 24 * i, 24);
    munmap(m, (size_t)st.st_size);
    close(fd);
}

static int replay(const char *trace) {
    FILE *f = fopen(trace, "r");
    if (!f) {
        perror(trace);
        return 1;
    }
    char line[4096], name[80] = "";
    ach_channel_t writer, reader;
    int open_chan = 0, have_reader = 0, ops = 0;
    size_t cnt = 0;
    unsigned long long idx[64][3];
    while (fgets(line, sizeof line, f)) {
        if (strncmp(line, "== ", 3) == 0) {
            if (have_reader)
                STATUS(ach_close(&reader), ACH_OK);
            if (open_chan)
                STATUS(ach_close(&writer), ACH_OK);
            have_reader = 0;
            sscanf(line + 3, "%79s", name);
            int small = strstr(line, "-m 4 -n 16") != NULL;
            cnt = small ? 4 : 16;
            if (ach_unlink(name) != ACH_OK) { /* a leftover from an earlier run, if any */
            }
            STATUS(ach_create(name, small ? 4 : 0, small ? 16 : 0, NULL), ACH_OK);
            STATUS(ach_open(&writer, name, NULL), ACH_OK);
            open_chan = 1;
        } else if (strncmp(line, "PUT ", 4) == 0) {
            static unsigned char data[4096];
            size_t len = unhex(strstr(line, "bytes=") + 6, data);
            enum ach_status want = status_named(strstr(line, "-> ") + 3);
            STATUS(ach_put(&writer, data, len), want);
            ops++;
        } else if (strncmp(line, "  [after put]", 13) == 0 || strncmp(line, "  [initial]", 11) == 0) {
            unsigned long long want[8], got[8];
            sscanf(strchr(line, ']') + 1,
                   " index_cnt=%llu data_size=%llu data_head=%llu data_free=%llu index_head=%llu index_free=%llu "
                   "last_seq=%llu dirty=%llu",
                   &want[0], &want[1], &want[2], &want[3], &want[4], &want[5], &want[7], &want[6]);
            file_words(name, got, idx, cnt);
            for (int i = 0; i < 8; i++)
                CHECK(got[i] == want[i], "%s header word %d is %llu, libach had %llu", name, i, got[i], want[i]);
        } else if (strncmp(line, "    index[", 10) == 0) {
            unsigned i;
            unsigned long long s, o, q;
            sscanf(line, "    index[%u] size=%llu offset=%llu seq_num=%llu", &i, &s, &o, &q);
            CHECK(i < cnt && idx[i][0] == s && idx[i][1] == o && idx[i][2] == q,
                  "%s index[%u] is {%llu,%llu,%llu}, libach had {%llu,%llu,%llu}", name, i, idx[i][0], idx[i][1],
                  idx[i][2], s, o, q);
        } else if (strncmp(line, "GET[", 4) == 0 || strncmp(line, "FLUSH", 5) == 0) {
            if (strstr(line, "fresh reader") || !have_reader) {
                if (have_reader)
                    STATUS(ach_close(&reader), ACH_OK);
                STATUS(ach_open(&reader, name, NULL), ACH_OK);
                have_reader = 1;
            }
            unsigned long long seq, next;
            sscanf(strstr(line, "reader.seq_num="), "reader.seq_num=%llu reader.next_index=%llu", &seq, &next);
            if (line[0] == 'F') {
                STATUS(ach_flush(&reader), ACH_OK);
            } else {
                unsigned bufsize, opts;
                long long want_size;
                sscanf(strchr(line, ']') + 2, "bufsize=%u opts=0x%x", &bufsize, &opts);
                enum ach_status want = status_named(strstr(line, "-> ") + 3);
                sscanf(strstr(line, "frame_size="), "frame_size=%lld", &want_size);
                unsigned char buf[4096], expect[4096];
                size_t frame_size = (size_t)-1;
                struct timespec rel = {0, 10000000};
                int o = (int)opts | ((opts & ACH_O_WAIT) ? ACH_O_RELTIME : 0);
                STATUS(ach_get(&reader, buf, bufsize, &frame_size, (opts & ACH_O_WAIT) ? &rel : NULL, o), want);
                CHECK((long long)frame_size == want_size, "%s frame_size %lld, libach had %lld", line,
                      (long long)frame_size, want_size);
                const char *d = strstr(line, "data=");
                if (d) {
                    size_t n = unhex(d + 5, expect);
                    CHECK(n == frame_size && memcmp(buf, expect, n) == 0, "%s: data differs", line);
                }
            }
            CHECK(reader.seq_num == seq && reader.next_index == next, "%s reader state %llu/%zu, libach had %llu/%llu",
                  line, (unsigned long long)reader.seq_num, reader.next_index, seq, next);
            ops++;
        }
    }
    if (have_reader)
        STATUS(ach_close(&reader), ACH_OK);
    if (open_chan)
        STATUS(ach_close(&writer), ACH_OK);
    fclose(f);
    printf("trace: %d operations replayed, %d failures\n", ops, failures);
    return failures != 0;
}

/* ---- the rest of the API ---------------------------------------------------------------------------------- */

struct waiter {
    ach_channel_t *chan;
    enum ach_status result;
    size_t size;
    char buf[64];
};

static void *wait_forever(void *arg) {
    struct waiter *w = arg;
    w->result = ach_get(w->chan, w->buf, sizeof w->buf, &w->size, NULL, ACH_O_WAIT);
    return NULL;
}

static int api(const char *name) {
    char path[128];
    snprintf(path, sizeof path, "/dev/shm/achshm-%s", name);
    CHECK(sizeof(ach_channel_t) == 128 && sizeof(ach_attr_t) == 64 && sizeof(ach_create_attr_t) == 128 &&
              sizeof(ach_cancel_attr_t) == 64,
          "struct sizes differ from libach's");
    CHECK(strcmp(ach_result_to_string(ACH_OK), "ACH_OK") == 0, "name of 0");
    CHECK(strcmp(ach_result_to_string(ACH_STALE_FRAMES), "ACH_EAGAIN") == 0, "name of 5");
    CHECK(strcmp(ach_result_to_string(ACH_ENOTSUP), "ACH_ENOTSUP") == 0, "name of 19");
    {
        char mine[] = "set by the client";
        ach_set_errstr(mine); /* golems' libach exports it; clients and tools call it */
        mine[0] = 'X';        /* a copy is kept */
        CHECK(strcmp(ach_errstr(), "set by the client") == 0, "ach_set_errstr: ach_errstr() is '%s'", ach_errstr());
        ach_set_errstr(NULL);
        CHECK(strcmp(ach_errstr(), "") == 0, "ach_set_errstr(NULL): '%s'", ach_errstr());
    }
    CHECK(ACH_O_WAIT == 1 && ACH_O_LAST == 2 && ACH_O_COPY == 4 && ACH_O_RELTIME == 8 && ACH_O_NONBLOCK == 0 &&
              ACH_O_FIRST == 0,
          "option values");
    CHECK(ACH_MISSED_FRAME == 6 && ACH_CANCELED == 16 && ACH_LOCKED == 5, "status values");
    CHECK(ach_status_match(ACH_TIMEOUT, ACH_MASK_TIMEOUT | ACH_MASK_OK), "masks");

    ach_channel_t c, r;
    char long_name[80];
    memset(long_name, 'a', 64);
    long_name[64] = '\0';
    const char *bad[] = {"", ".hidden", "a/b", "sp ace", long_name};
    for (size_t i = 0; i < sizeof bad / sizeof bad[0]; i++) {
        STATUS(ach_create(bad[i], 4, 16, NULL), ACH_INVALID_NAME);
        STATUS(ach_open(&c, bad[i], NULL), ACH_INVALID_NAME);
        STATUS(ach_unlink(bad[i]), ACH_INVALID_NAME);
    }
    if (ach_unlink(name) != ACH_OK) { /* a leftover from an earlier run, if any */
    }
    STATUS(ach_open(&c, name, NULL), ACH_ENOENT);
    STATUS(ach_unlink(name), ACH_ENOENT);

    ach_create_attr_t cattr;
    ach_create_attr_init(&cattr);
    STATUS(ach_create(name, 4, 32, &cattr), ACH_OK);
    STATUS(ach_create(name, 4, 32, NULL), ACH_EEXIST);
    STATUS(ach_create_attr_set_truncate(&cattr, 1), ACH_OK);
    STATUS(ach_create(name, 8, 32, &cattr), ACH_OK);
    STATUS(ach_create_attr_set_map(&cattr, ACH_MAP_KERNEL), ACH_ENOTSUP);

    ach_attr_t attr;
    ach_attr_init(&attr);
    STATUS(ach_open(&c, name, &attr), ACH_OK);
    STATUS(ach_open(&r, name, NULL), ACH_OK);
    clockid_t clock;
    STATUS(ach_channel_clock(&c, &clock), ACH_OK);
    CHECK(clock == CLOCK_MONOTONIC, "clock %d", (int)clock);

    STATUS(ach_put(&c, "x", 0), ACH_EINVAL);
    static char big[8 * 32 + 1];
    STATUS(ach_put(&c, big, sizeof big), ACH_OVERFLOW);
    char buf[64];
    size_t fs = 12345;
    STATUS(ach_get(&r, buf, sizeof buf, &fs, NULL, 0), ACH_STALE_FRAMES);
    CHECK(fs == 12345, "frame_size written on a stale get");

    struct timespec rel = {0, 20000000};
    long long t0 = mono_ns();
    STATUS(ach_get(&r, buf, sizeof buf, &fs, &rel, ACH_O_WAIT | ACH_O_RELTIME), ACH_TIMEOUT);
    long long took = mono_ns() - t0;
    CHECK(took >= 15000000 && took < 1000000000, "relative 20 ms timeout took %lld ns", took);
    struct timespec abs;
    clock_gettime(CLOCK_MONOTONIC, &abs);
    abs.tv_nsec += 20000000;
    if (abs.tv_nsec >= 1000000000) {
        abs.tv_sec++;
        abs.tv_nsec -= 1000000000;
    }
    t0 = mono_ns();
    STATUS(ach_get(&r, buf, sizeof buf, &fs, &abs, ACH_O_WAIT), ACH_TIMEOUT);
    took = mono_ns() - t0;
    CHECK(took >= 15000000 && took < 1000000000, "absolute 20 ms timeout took %lld ns", took);

    STATUS(ach_put(&c, "one", 4), ACH_OK);
    STATUS(ach_put(&c, "two", 4), ACH_OK);
    STATUS(ach_put(&c, "three", 6), ACH_OK);
    STATUS(ach_get(&r, buf, sizeof buf, &fs, NULL, ACH_O_LAST | ACH_O_WAIT), ACH_MISSED_FRAME);
    CHECK(fs == 6 && strcmp(buf, "three") == 0, "O_LAST got %zu bytes '%s'", fs, buf);
    STATUS(ach_get(&r, buf, sizeof buf, &fs, NULL, ACH_O_COPY), ACH_OK);
    CHECK(strcmp(buf, "three") == 0, "O_COPY got '%s'", buf);
    STATUS(ach_put(&c, "four", 5), ACH_OK);
    STATUS(ach_flush(&r), ACH_OK);
    STATUS(ach_get(&r, buf, sizeof buf, &fs, NULL, 0), ACH_STALE_FRAMES);
    STATUS(ach_get(&r, buf, 2, &fs, NULL, ACH_O_COPY), ACH_OVERFLOW);
    CHECK(fs == 5, "overflow frame_size %zu", fs);

    /* a waiting reader thread is woken by a put, then cancelled */
    struct waiter w = {.chan = &r};
    pthread_t th;
    pthread_create(&th, NULL, wait_forever, &w);
    usleep(50000);
    t0 = mono_ns();
    STATUS(ach_put(&c, "five", 5), ACH_OK);
    pthread_join(th, NULL);
    took = mono_ns() - t0;
    CHECK(w.result == ACH_OK && strcmp(w.buf, "five") == 0, "woken get: %s '%s'", ach_result_to_string(w.result),
          w.buf);
    CHECK(took < 20000000, "the woken reader took %lld ns", took);
    pthread_create(&th, NULL, wait_forever, &w);
    usleep(50000);
    ach_cancel_attr_t cancel_attr;
    ach_cancel_attr_init(&cancel_attr);
    STATUS(ach_cancel(&r, &cancel_attr), ACH_OK);
    pthread_join(th, NULL);
    CHECK(w.result == ACH_CANCELED, "cancelled get: %s", ach_result_to_string(w.result));
    STATUS(ach_get(&r, buf, sizeof buf, &fs, NULL, 0), ACH_CANCELED);
    STATUS(ach_flush(&r), ACH_CANCELED);

    STATUS(ach_chmod(&c, 0600), ACH_OK);
    struct stat st;
    stat(path, &st);
    CHECK((st.st_mode & 0777) == 0600, "mode %o", st.st_mode & 0777);
    STATUS(ach_close(&r), ACH_OK);
    STATUS(ach_close(&c), ACH_OK);
    STATUS(ach_unlink(name), ACH_OK);
    STATUS(ach_open(&c, name, NULL), ACH_ENOENT);

    int fd = open(path, O_RDWR | O_CREAT | O_TRUNC, 0600); /* not a channel */
    CHECK(write(fd, "not an ach channel file, just text....", 38) == 38, "write");
    close(fd);
    STATUS(ach_open(&c, name, NULL), ACH_BAD_SHM_FILE);
    unlink(path);
    printf("api: %d failures\n", failures);
    return failures != 0;
}

/* ---- helpers for the Python side -------------------------------------------------------------------------- */

static int put(const char *name, long count, double hz) {
    ach_channel_t c;
    STATUS(ach_open(&c, name, NULL), ACH_OK);
    if (failures)
        return 1;
    long long period = hz > 0 ? (long long)(1e9 / hz) : 0, next = mono_ns();
    for (long i = 0; i < count; i++) {
        if (period) {
            next += period;
            struct timespec ts = {(time_t)(next / 1000000000LL), (long)(next % 1000000000LL)};
            clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
        }
        char frame[32];
        int n = snprintf(frame, sizeof frame, "c-frame-%ld", i);
        STATUS(ach_put(&c, frame, (size_t)n), ACH_OK);
    }
    STATUS(ach_close(&c), ACH_OK);
    printf("put done\n");
    return failures != 0;
}

static int get(const char *name, long count) {
    ach_channel_t c;
    STATUS(ach_open(&c, name, NULL), ACH_OK);
    if (failures)
        return 1;
    for (long i = 0; i < count; i++) {
        char buf[256];
        size_t fs = 0;
        struct timespec rel = {5, 0};
        enum ach_status r = ach_get(&c, buf, sizeof buf - 1, &fs, &rel, ACH_O_WAIT | ACH_O_RELTIME);
        if (r != ACH_OK && r != ACH_MISSED_FRAME) {
            fprintf(stderr, "get %ld: %s\n", i, ach_result_to_string(r));
            return 1;
        }
        buf[fs] = '\0';
        printf("frame %s\n", buf);
        fflush(stdout);
    }
    STATUS(ach_close(&c), ACH_OK);
    return failures != 0;
}

static int wait_only(const char *name) {
    ach_channel_t c;
    STATUS(ach_open(&c, name, NULL), ACH_OK);
    if (failures)
        return 1;
    STATUS(ach_flush(&c), ACH_OK);
    printf("waiting\n");
    fflush(stdout);
    char buf[256];
    size_t fs;
    enum ach_status r = ach_get(&c, buf, sizeof buf, &fs, NULL, ACH_O_WAIT);
    printf("woken %s\n", ach_result_to_string(r));
    return 0;
}

int main(int argc, char **argv) {
    if (argc == 3 && strcmp(argv[1], "trace") == 0)
        return replay(argv[2]);
    if (argc == 3 && strcmp(argv[1], "api") == 0)
        return api(argv[2]);
    if (argc == 5 && strcmp(argv[1], "put") == 0)
        return put(argv[2], atol(argv[3]), atof(argv[4]));
    if (argc == 4 && strcmp(argv[1], "get") == 0)
        return get(argv[2], atol(argv[3]));
    if (argc == 3 && strcmp(argv[1], "wait") == 0)
        return wait_only(argv[2]);
    fprintf(stderr, "usage: %s trace FILE | api NAME | put NAME COUNT HZ | get NAME COUNT | wait NAME\n", argv[0]);
    return 2;
}
