"""``mds_ach.ik`` is ``mds_ach.kinematics.ik`` (kept for users' scripts: ``from mds_ach import ik``)."""

import sys

from mds_ach.kinematics import ik as _impl

sys.modules[__name__] = _impl
