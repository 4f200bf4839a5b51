"""``import mds_ik as ik``: the original MDS-Ach module name of the IK functions (``getIK``, ``getFkArm``,
``getPosCurrentFromOrder``, ``getRot``, ``getJacobian``, ``getIK3dof``, ...), installed as a top-level module so
the original scripts' import line works unchanged. It *is* :mod:`mds_ach.kinematics.ik` (the same module
object, like ``mds_ach.ik``), so there is one implementation.
"""

import sys

from mds_ach.kinematics import ik as _impl

sys.modules[__name__] = _impl
