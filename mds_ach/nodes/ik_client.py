"""Client side of the IK node: put an ``MDS_IK`` request on ``mds-ik`` and wait for its ``mds-ik-state`` answer.

Used by the console (``ik left 3 0.3 0.2 0``) and scripts. Legacy clients that only write ``mds-ik`` keep
working; they just do not read the answer. No rclpy here.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import mds_ach as mds
from mds_ach.kinematics.model import arm_name
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs.ik_status import IK_SOLVED, IK_STOPPED_AT_CONTACT, MDS_IK_STATUS, get_message


class IkTimeout(TimeoutError):  # noqa: N818 - the name the console imports
    """No answer from the IK node in time (is ``ik`` running?)."""


@dataclass(frozen=True)
class IkReply:
    seq: int
    status: int
    arm: str
    dof: int
    iterations: int
    error: float
    time: float  # s the node spent solving
    target: tuple[float, ...]
    q: tuple[float, ...]  # [SP, SR, SY, EP, WY, WR]; on failure the best attempt, not applied
    message: str

    @property
    def success(self) -> bool:
        return self.status == IK_SOLVED


def make_request(arm: str | int, dof: int, values: Sequence[float]) -> mds.MDS_IK:
    """An ``MDS_IK`` asking for ``dof`` components (x, y, z, roll, pitch, yaw order) of ``values`` for ``arm``."""
    side = arm_name(arm)
    if isinstance(dof, bool) or not isinstance(dof, int) or not 1 <= dof <= 6:
        raise ValueError(f"dof must be an integer 1..6, got {dof!r}")
    vals = [float(v) for v in values]
    if len(vals) < dof or len(vals) > 6:
        raise ValueError(f"a {dof}-DOF request needs {dof} to 6 values, got {len(vals)}")
    if not all(math.isfinite(v) for v in vals[:dof]):
        raise ValueError(f"target values must be finite numbers, got {vals[:dof]}")
    vals += [0.0] * (6 - len(vals))
    req = mds.MDS_IK()
    index = mds.LEFT if side == "left" else mds.RIGHT
    a = req.arm[index]
    a.t_x, a.t_y, a.t_z, a.r_x, a.r_y, a.r_z = vals
    a.ik_method = dof
    req.move = index
    return req


class IkClient:
    """``with IkClient() as c: reply = c.request('left', 3, [0.3, 0.2, 0.0])``."""

    def __init__(self) -> None:
        self.requests = StructChannel(mds.MDS_CHAN_IK_NAME, mds.MDS_IK)
        self.answers = StructChannel(mds.MDS_CHAN_IK_STATE_NAME, MDS_IK_STATUS)

    def request(self, arm: str | int, dof: int, values: Sequence[float], timeout: float = 10.0) -> IkReply:
        """Send one request and return the node's answer to it; ``IkTimeout`` if none within ``timeout`` s."""
        req = make_request(arm, dof, values)
        index = int(req.move)
        sent = [req.arm[index].t_x, req.arm[index].t_y, req.arm[index].t_z,
                req.arm[index].r_x, req.arm[index].r_y, req.arm[index].r_z]
        self.answers.flush()  # older answers belong to older requests
        self.requests.put(req)
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            st = self.answers.wait(timeout=max(0.0, remaining)) if remaining > 0 else None
            if st is None:
                raise IkTimeout(f"no answer from the IK node on {mds.MDS_CHAN_IK_STATE_NAME} within {timeout:g} s "
                                "(is 'ik' running? start it with 'mds-ach start' or 'ros2 run mds_ach ik')")
            # Match our request (another client may be asking at the same time).
            if int(st.arm) == index and int(st.dof) == dof and list(st.target) == sent:
                return IkReply(seq=int(st.seq), status=int(st.status), arm=arm_name(index), dof=int(st.dof),
                               iterations=int(st.iterations), error=float(st.error), time=float(st.solve_time),
                               target=tuple(st.target), q=tuple(st.q), message=get_message(st))

    def stopped(self, reply: IkReply) -> str | None:
        """Never waits: the node's follow-up to ``reply`` if one arrived (IK_STOPPED_AT_CONTACT, same seq: the
        collision gate stopped the arm at contact and cancelled the command), as its message, else None."""
        while (st := self.answers.next()) is not None:
            if int(st.seq) == reply.seq and int(st.status) == IK_STOPPED_AT_CONTACT:
                return get_message(st)
        return None

    def close(self) -> None:
        self.requests.close()
        self.answers.close()

    def __enter__(self) -> IkClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
