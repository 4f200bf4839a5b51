# Simple joint demo of the original MDS-Ach (Python 3 spelling): read the state, then command the left
# shoulder pitch (LSP) to -0.123 rad through the smoothing input mds-ref-filter, twice, half a second apart.
import time

import ach

import mds_ach as mds


def mainLoop():
    s = ach.Channel(mds.MDS_CHAN_STATE_NAME)
    rf = ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME)
    r = ach.Channel(mds.MDS_CHAN_REF_NAME)
    state = mds.MDS_STATE()
    ref = mds.MDS_REF()
    ref_filt = mds.MDS_REF()
    for _ in range(2):
        # newest frames
        [status, framesize] = s.get(state, wait=False, last=True)
        [status, framesize] = r.get(ref, wait=False, last=True)
        [status, framesize] = rf.get(ref_filt, wait=False, last=True)

        jntn = mds.getAddress('LSP', state)
        print('Address = ', jntn)
        print('Reference = ', state.joint[jntn].ref)
        print('State = ', state.joint[jntn].pos)

        # LSP to -0.123 rad through the filter (smooth)
        ref_filt.joint[jntn].ref = -0.123
        rf.put(ref_filt)
        time.sleep(0.5)
    s.close()
    r.close()
    rf.close()


if __name__ == '__main__':
    mainLoop()
