/* mds_controller.c -- the smallest C controller for MDS-Ach.
 *
 * Reads the newest frame of mds-state, commands two left-arm joints (elbow LEP and shoulder LSP) and
 * puts the reference on mds-ref-filter, the legacy controller input of the pipeline (mux -> filter ->
 * collision gate -> daemon). Every other joint keeps the reference the daemon currently holds, so
 * only the two named joints move, and the filter moves them smoothly.
 *
 * Usage: mds_controller [LEP_rad LSP_rad]      (default -0.3 0.2)
 * Build: make            (needs libach: ach.h and -lach)
 */
#include <errno.h>
#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/types.h>
#include <time.h>

#include <ach.h> /* wants stdint.h, pthread.h, time.h and sys/types.h first */

#include "mds.h"

/* Parse a joint angle in radians; refuse text, NaN and Inf so nothing odd reaches the channel. */
static int parse_angle(const char *text, double *out)
{
    char *end = NULL;
    errno = 0;
    double v = strtod(text, &end);
    if (errno != 0 || end == text || *end != '\0' || !isfinite(v)) {
        fprintf(stderr, "mds_controller: %s is not a finite angle in radians\n", text);
        return -1;
    }
    *out = v;
    return 0;
}

int main(int argc, char **argv)
{
    double lep = -0.3, lsp = 0.2;
    if (argc == 2 && (strcmp(argv[1], "-h") == 0 || strcmp(argv[1], "--help") == 0)) {
        printf("usage: %s [LEP_rad LSP_rad]\n"
               "Sets the left elbow (LEP) and left shoulder pitch (LSP) references on %s.\n",
               argv[0], MDS_CHAN_REF_FILTER_NAME);
        return 0;
    }
    if (argc == 3) {
        if (parse_angle(argv[1], &lep) != 0 || parse_angle(argv[2], &lsp) != 0)
            return 2;
    } else if (argc != 1) {
        fprintf(stderr, "usage: %s [LEP_rad LSP_rad]\n", argv[0]);
        return 2;
    }

    ach_channel_t state_chan, ref_chan;
    enum ach_status r = ach_open(&state_chan, MDS_CHAN_STATE_NAME, NULL);
    if (r != ACH_OK) {
        fprintf(stderr, "ach_open(%s): %s (is the daemon running?)\n", MDS_CHAN_STATE_NAME,
                ach_result_to_string(r));
        return 1;
    }
    r = ach_open(&ref_chan, MDS_CHAN_REF_FILTER_NAME, NULL);
    if (r != ACH_OK) {
        fprintf(stderr, "ach_open(%s): %s\n", MDS_CHAN_REF_FILTER_NAME, ach_result_to_string(r));
        return 1;
    }

    /* Wait up to 1 s for the newest state frame. Channels use CLOCK_MONOTONIC for timeouts. */
    mds_state_t state;
    size_t frame_size = 0;
    struct timespec deadline;
    clock_gettime(CLOCK_MONOTONIC, &deadline);
    deadline.tv_sec += 1;
    r = ach_get(&state_chan, &state, sizeof(state), &frame_size, &deadline, ACH_O_WAIT | ACH_O_LAST);
    if ((r != ACH_OK && r != ACH_MISSED_FRAME) || frame_size != sizeof(state)) {
        fprintf(stderr, "no state frame on %s: %s (frame %zu B, expected %zu B)\n", MDS_CHAN_STATE_NAME,
                ach_result_to_string(r), frame_size, sizeof(state));
        return 1;
    }
    printf("state at t=%.3f s: LEP pos %.4f rad, LSP pos %.4f rad\n", state.time,
           state.joint[MDS_JOINT_LEP].pos, state.joint[MDS_JOINT_LSP].pos);

    /* Start from the references the daemon last received (ref_r), then change only our two joints. */
    mds_ref_t ref;
    memset(&ref, 0, sizeof(ref));
    for (int a = 0; a < MDS_JOINT_COUNT; a++) {
        ref.joint[a].ref = state.joint[a].ref_r;
        ref.joint[a].mode = MDS_REF_MODE_REF_FILTER;
    }
    ref.joint[MDS_JOINT_LEP].ref = lep;
    ref.joint[MDS_JOINT_LSP].ref = lsp;

    r = ach_put(&ref_chan, &ref, sizeof(ref));
    if (r != ACH_OK) {
        fprintf(stderr, "ach_put(%s): %s\n", MDS_CHAN_REF_FILTER_NAME, ach_result_to_string(r));
        return 1;
    }
    printf("put LEP=%.4f LSP=%.4f on %s\n", lep, lsp, MDS_CHAN_REF_FILTER_NAME);

    if (ach_close(&ref_chan) != ACH_OK)
        fprintf(stderr, "ach_close failed\n");
    if (ach_close(&state_chan) != ACH_OK)
        fprintf(stderr, "ach_close failed\n");
    return 0;
}
