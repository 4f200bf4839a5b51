/* ach_latency.c -- the C ends of bench/bench_libach.py, built against the project's libach (pkg-config ach).
 *
 *   ach_latency write NAME HZ COUNT libach     put COUNT stamped frames at HZ with ach_put (futex wake + broadcast)
 *   ach_latency write NAME HZ COUNT broadcast  the same, but each put wakes only the condvar, as golems' libach 2.0
 *                                              does (lock, libach's write, unlock, pthread_cond_broadcast): the
 *                                              put algorithm is achcore's, only the futex wake is left out
 *   ach_latency read NAME COUNT SKIP           ACH_O_WAIT-get COUNT frames from C writers, print the wake-up
 *                                              latencies after the first SKIP as "median_us p99_us max_us"
 *
 * A frame is {u64 CLOCK_MONOTONIC ns at the put, u64 index, char tag}; tag 'C' for these writers (other writers
 * on the same channel use other tags and are not measured).
 */
#define _GNU_SOURCE
#include <ach.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "achcore.h" /* for the broadcast-only writer: achcore_t is the handle's channel state */

struct frame {
    uint64_t stamp_ns;
    uint64_t index;
    char tag;
};

static long long mono_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (long long)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

/* golems' libach put: the same ring update under the same lock, then only the condvar broadcast. */
static int put_broadcast_only(ach_channel_t *chan, const void *buf, size_t len) {
    achcore_t *c = chan->core;
    int r = achcore_lock(c, -1);
    if (r)
        return r;
    r = achcore_write_locked(c, buf, len);
    pthread_mutex_unlock(c->mutex);
    pthread_cond_broadcast(c->cond);
    return r;
}

static int write_frames(const char *name, double hz, long count, int broadcast_only) {
    ach_channel_t chan;
    enum ach_status r = ach_open(&chan, name, NULL);
    if (r != ACH_OK) {
        fprintf(stderr, "ach_open(%s): %s\n", name, ach_result_to_string(r));
        return 1;
    }
    long long period = (long long)(1e9 / hz), next = mono_ns();
    for (long i = 0; i < count; i++) {
        next += period;
        struct timespec ts = {(time_t)(next / 1000000000LL), (long)(next % 1000000000LL)};
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL);
        struct frame f = {(uint64_t)mono_ns(), (uint64_t)i, 'C'};
        r = broadcast_only ? (enum ach_status)put_broadcast_only(&chan, &f, sizeof f) : ach_put(&chan, &f, sizeof f);
        if (r != ACH_OK) {
            fprintf(stderr, "put: %s\n", ach_result_to_string(r));
            return 1;
        }
    }
    return ach_close(&chan) != ACH_OK;
}

static int cmp(const void *a, const void *b) {
    long long x = *(const long long *)a, y = *(const long long *)b;
    return (x > y) - (x < y);
}

static int read_frames(const char *name, long count, long skip) {
    ach_channel_t chan;
    enum ach_status r = ach_open(&chan, name, NULL);
    if (r != ACH_OK || ach_flush(&chan) != ACH_OK) {
        fprintf(stderr, "ach_open(%s): %s\n", name, ach_result_to_string(r));
        return 1;
    }
    long long *lat = calloc((size_t)count, sizeof *lat);
    long n = 0, seen = 0;
    while (seen < count) {
        struct frame f;
        size_t fs;
        struct timespec rel = {5, 0};
        r = ach_get(&chan, &f, sizeof f, &fs, &rel, ACH_O_WAIT | ACH_O_RELTIME);
        long long now = mono_ns();
        if (r == ACH_TIMEOUT)
            break;
        if ((r != ACH_OK && r != ACH_MISSED_FRAME) || fs != sizeof f || f.tag != 'C')
            continue;
        if (seen++ >= skip)
            lat[n++] = now - (long long)f.stamp_ns;
    }
    if (n == 0) {
        fprintf(stderr, "no frames\n");
        return 1;
    }
    qsort(lat, (size_t)n, sizeof *lat, cmp);
    printf("%.3f %.3f %.3f\n", lat[n / 2] / 1e3, lat[(n - 1) * 99 / 100] / 1e3, lat[n - 1] / 1e3);
    free(lat);
    return ach_close(&chan) != ACH_OK;
}

int main(int argc, char **argv) {
    if (argc == 6 && strcmp(argv[1], "write") == 0)
        return write_frames(argv[2], atof(argv[3]), atol(argv[4]), strcmp(argv[5], "broadcast") == 0);
    if (argc == 5 && strcmp(argv[1], "read") == 0)
        return read_frames(argv[2], atol(argv[3]), atol(argv[4]));
    fprintf(stderr, "usage: %s write NAME HZ COUNT libach|broadcast | read NAME COUNT SKIP\n", argv[0]);
    return 2;
}
