/* mds_ik_request.c -- ask the IK node for a Cartesian hand position.
 *
 * Puts one mds_ik_t on mds-ik. The target is in the robot frame (metres, origin between the
 * shoulders, x forward, y left, z up); ik_method is the number of task DOF (3 = position only, in
 * the order p-x p-y p-z t-x t-y t-z). The IK node solves it and sends the joint solution through the
 * mux, filter and collision gate like any other reference.
 *
 * Usage: mds_ik_request [left|right] [x y z]     (default: left 0.3 0.2 0.0)
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

static int parse_metres(const char *text, double *out)
{
    char *end = NULL;
    errno = 0;
    double v = strtod(text, &end);
    if (errno != 0 || end == text || *end != '\0' || !isfinite(v)) {
        fprintf(stderr, "mds_ik_request: %s is not a finite distance in metres\n", text);
        return -1;
    }
    *out = v;
    return 0;
}

int main(int argc, char **argv)
{
    int arm = MDS_LEFT;
    double target[3] = {0.3, 0.2, 0.0};
    int argi = 1;
    if (argc > 1 && (strcmp(argv[1], "-h") == 0 || strcmp(argv[1], "--help") == 0)) {
        printf("usage: %s [left|right] [x y z]\nPuts a position-only IK request on %s.\n", argv[0],
               MDS_CHAN_IK_NAME);
        return 0;
    }
    if (argi < argc && (strcmp(argv[argi], "left") == 0 || strcmp(argv[argi], "right") == 0)) {
        arm = strcmp(argv[argi], "left") == 0 ? MDS_LEFT : MDS_RIGHT;
        argi++;
    }
    if (argc - argi == 3) {
        for (int i = 0; i < 3; i++)
            if (parse_metres(argv[argi + i], &target[i]) != 0)
                return 2;
    } else if (argc != argi) {
        fprintf(stderr, "usage: %s [left|right] [x y z]\n", argv[0]);
        return 2;
    }

    mds_ik_t ik;
    memset(&ik, 0, sizeof(ik));
    ik.arm[arm].t_x = target[0];
    ik.arm[arm].t_y = target[1];
    ik.arm[arm].t_z = target[2];
    ik.arm[arm].ik_method = 3; /* task DOF: position only */
    ik.move = (int16_t)arm;

    ach_channel_t chan;
    enum ach_status r = ach_open(&chan, MDS_CHAN_IK_NAME, NULL);
    if (r != ACH_OK) {
        fprintf(stderr, "ach_open(%s): %s (run `mds-ach make` first)\n", MDS_CHAN_IK_NAME,
                ach_result_to_string(r));
        return 1;
    }
    r = ach_put(&chan, &ik, sizeof(ik));
    if (r != ACH_OK) {
        fprintf(stderr, "ach_put(%s): %s\n", MDS_CHAN_IK_NAME, ach_result_to_string(r));
        return 1;
    }
    printf("IK request: %s hand to (%.3f, %.3f, %.3f) m on %s\n", arm == MDS_LEFT ? "left" : "right",
           target[0], target[1], target[2], MDS_CHAN_IK_NAME);
    if (ach_close(&chan) != ACH_OK)
        fprintf(stderr, "ach_close failed\n");
    return 0;
}
