# IK solver API example of the original MDS-Ach (Python 3 spelling): solve the left arm locally with
# mds_ik.getIK for the hand at (0.3, 0.2, 0.0) m from the current references, put the joints on
# mds-ref-filter and print the desired, returned and difference positions.
import numpy as np

import ach
import mds_ik as ik

import mds_ach as mds

JOINTS = ['LSP', 'LSR', 'LSY', 'LEP', 'LWY', 'LWR']  # the order getIK uses: SP, SR, SY, EP, WY, WR


def mainLoop():
    r = ach.Channel(mds.MDS_CHAN_REF_FILTER_NAME)
    s = ach.Channel(mds.MDS_CHAN_STATE_NAME)
    state = mds.MDS_STATE()
    ref = mds.MDS_REF()
    [status, framesize] = s.get(state, wait=False, last=True)
    [status, framesize] = r.get(ref, wait=False, last=True)

    eff_end = np.array([0.3, 0.2, 0.0, 0.0, 0.0, 0.0])
    arm = 'left'
    eff_joint_space_current = [state.joint[mds.getAddress(j, state)].ref for j in JOINTS]

    dof = 3
    order = ['p_x', 'p_y', 'p_z']
    err = np.array([0.01, 0.01, 0.01])
    stepNum = 1000
    eff_end = eff_end[:dof]

    jnt_return = ik.getIK(eff_joint_space_current, eff_end, order, arm, err, stepNum)
    if jnt_return[1] == -1:
        print('no IK found within ', stepNum, ' steps')
        quit()
    eff_joint_space_current = jnt_return[0]

    for j, value in zip(JOINTS, eff_joint_space_current):
        ref.joint[mds.getAddress(j, state)].ref = value
    r.put(ref)

    A = ik.getFkArm(eff_joint_space_current, arm)
    eff_end_ret = ik.getPosCurrentFromOrder(A, order)
    eff_end_dif = eff_end - eff_end_ret
    print('N-3 DOF IK Solution - for ', arm, ' arm')
    print('des:\tx = ', round(eff_end[0], 5), '\ty = ', round(eff_end[1], 5), '\tz = ', round(eff_end[2], 5))
    print('ret:\tx = ', round(eff_end_ret[0], 5), '\ty = ', round(eff_end_ret[1], 5), '\tz = ', round(eff_end_ret[2], 5))
    print('dif:\tx = ', round(eff_end_dif[0], 5), '\ty = ', round(eff_end_dif[1], 5), '\tz = ', round(eff_end_dif[2], 5))


if __name__ == '__main__':
    mainLoop()
