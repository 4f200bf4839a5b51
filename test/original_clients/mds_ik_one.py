# IK, one target, of the original MDS-Ach (Python 3 spelling): ask the IK module for the left hand at
# (0.3, 0.2, 0.0) m, a 3-DOF (position) task, on the mds-ik channel.
import ach

import mds_ach as mds


def mainLoop():
    k = ach.Channel(mds.MDS_CHAN_IK_NAME)
    ikc = mds.MDS_IK()
    dof = 3
    eff = [0.3, 0.2, 0.0, 0.0, 0.0, 0.0]  # x, y, z, rx, ry, rz
    armi = mds.LEFT
    ikc.move = armi
    ikc.arm[armi].ik_method = dof
    ikc.arm[armi].t_x = eff[0]
    ikc.arm[armi].t_y = eff[1]
    ikc.arm[armi].t_z = eff[2]
    ikc.arm[armi].r_x = eff[3]
    ikc.arm[armi].r_y = eff[4]
    ikc.arm[armi].r_z = eff[5]
    print(eff)
    k.put(ikc)


if __name__ == '__main__':
    mainLoop()
