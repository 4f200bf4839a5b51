#!/usr/bin/env python
# A Python 2 client written the way the original MDS-Ach examples are (print statements, golems' ach binding,
# the original mds_ach module): set the left shoulder pitch on mds-ref-filter, read the state back.
# Test input for `mds-ach py2to3` (test/test_py2to3.py); it is not run under Python 3 as it is.
import mds_ach as mds
import ach
import time
import sys

s = ach.Channel(mds.MDS_CHAN_STATE_NAME)
rf = ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME)
state = mds.MDS_STATE()
ref = mds.MDS_REF()

[status, framesize] = s.get(state, wait=False, last=True)
print 'state status = ', status, ' framesize = ', framesize

[status, framesize] = rf.get(ref, wait=False, last=True)
jnt = mds.getAddress('LSP', state)
ref.joint[jnt].ref = -0.123
rf.put(ref)
print 'LSP address = ', hex(jnt), ' ref set to ', ref.joint[jnt].ref

print 'joints:',
for name in ['LSP', 'LSR', 'LSY']:
    print hex(mds.getAddress(name, state)),
print
for i in xrange(2):
    print i

try:
    count = int(sys.argv[1])
except IndexError, e:
    count = 0
if count <> 0:
    print >>sys.stderr, 'count = ', count
if mds.__dict__.has_key('MDS_REF'):
    print 'mode', 0644
s.close()
rf.close()
