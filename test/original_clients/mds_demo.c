/* A C client written for the original MDS-Ach: it includes only "mds.h", which (as the original header did)
 * brings <ach.h> and the libc headers, then moves the left elbow (LEP) to -0.2 rad through mds-ref-filter.
 * Built unchanged against this project's include/mds.h and libach (test/test_original_clients.py). */
#include "mds.h"
#include <stdio.h>

ach_channel_t chan_ref;   /* desired references (the original's filter input) */
ach_channel_t chan_state; /* the daemon's feedback */

int main(int argc, char **argv)
{
	(void)argc;
	(void)argv;
	int r = ach_open(&chan_ref, MDS_CHAN_REF_FILTER_NAME, NULL);
	assert(ACH_OK == r);
	r = ach_open(&chan_state, MDS_CHAN_STATE_NAME, NULL);
	assert(ACH_OK == r);

	struct mds_ref H_ref;
	struct mds_state H_state;
	memset(&H_ref, 0, sizeof(H_ref));
	memset(&H_state, 0, sizeof(H_state));

	size_t fs = 0;
	r = ach_get(&chan_state, &H_state, sizeof(H_state), &fs, NULL, ACH_O_LAST);
	if (ACH_OK != r && ACH_MISSED_FRAME != r) {
		fprintf(stderr, "mds-state: %s\n", ach_result_to_string((ach_status_t)r));
		return 1;
	}
	assert(sizeof(H_state) == fs);
	r = ach_get(&chan_ref, &H_ref, sizeof(H_ref), &fs, NULL, ACH_O_LAST);
	if (ACH_OK != r && ACH_MISSED_FRAME != r) {
		fprintf(stderr, "mds-ref-filter: %s\n", ach_result_to_string((ach_status_t)r));
		return 1;
	}
	printf("%s (%s, 0x%04x): pos = %f ref = %f\n", H_state.joint[LEP].name, H_state.joint[LEP].nameshort,
	       LeftElbowFlex, H_state.joint[LEP].pos, H_state.joint[LEP].ref);

	H_ref.joint[LEP].ref = -0.2;
	r = ach_put(&chan_ref, &H_ref, sizeof(H_ref));
	assert(ACH_OK == r);

	r = ach_close(&chan_ref);
	assert(ACH_OK == r);
	r = ach_close(&chan_state);
	assert(ACH_OK == r);
	return TRUE == 1 ? 0 : 1;
}
