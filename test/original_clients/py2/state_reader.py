#!/usr/bin/env python
# A Python 2 reader written the way the original mds_read.py / example-state-mds-ach.py are: the newest state,
# one joint's position and the time, a loop with raw_input and a conditional one-line print.
# Test input for `mds-ach py2to3` (test/test_py2to3.py).
import mds_ach as mds
import ach

s = ach.Channel(mds.MDS_CHAN_STATE_NAME)
state = mds.MDS_STATE()
while True:
    line = raw_input()
    if line == 'q': break
    [status, framesize] = s.get(state, wait=False, last=True)
    if status == ach.ACH_OK or status == ach.ACH_MISSED_FRAME: print 'pos = ', state.joint[0x4C].pos, '\ttime = ', state.time
    else: print 'no new state (', ach.Channel().result_string(status), ')'
s.close()
