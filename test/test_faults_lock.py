"""Fault injection: a client holding a channel lock (stopped inside a get). The daemon skips and counts, never
stalls.
"""


from __future__ import annotations

import signal
import subprocess
import time

from support import VENV_BIN, wait_for
from support.channels import Newest
from support.faults import LockHolder

import mds_ach as mds
from mds_ach.robot.channels import StructChannel
from mds_ach.robot.msgs import MDS_CMD, MDS_STATE
from mds_ach.robot.msgs import daemon_status as ds

# ============================================================================================ 4. a lock held too long

def test_daemon_keeps_cycling_while_a_client_holds_the_state_lock(clean_shm: None) -> None:
    """A client stopped while it holds the ``mds-state`` lock (a reader SIGSTOPped inside its get, a debugger)
    must not freeze the daemon: each put waits at most a tenth of the period for the lock, is skipped and counted
    (``lock_timeouts``, logged at most every 5 s); the loop goes on querying the bus, taking references and
    answering commands, and ``mds-state`` flows again as soon as the lock is free."""
    daemon = subprocess.Popen([str(VENV_BIN / "mds-ach-daemon"), "--nocan", "--no-ros", "--sim-ideal", "--rate", "50"],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    status_in = Newest(mds.MDS_CHAN_DAEMON_STATUS_NAME, ds.MDS_DAEMON_STATUS)
    state_in = StructChannel(mds.MDS_CHAN_STATE_NAME, MDS_STATE)
    cmd_out = StructChannel(mds.MDS_CHAN_BOARD_CMD_NAME, MDS_CMD)
    holder = None
    status = status_in.require  # the newest mds-daemon-status, or the last one seen

    try:
        wait_for(lambda: state_in.latest(), 30, what="mds-state from the daemon")
        wait_for(status_in.get, 10, what="mds-daemon-status")
        holder = LockHolder(mds.MDS_CHAN_STATE_NAME)
        held_since = time.monotonic()
        before = wait_for(status, 10)
        cmd_out.put(MDS_CMD(seq=77, cmd=mds.MDS_CMD_ENABLE, address=0))
        during = wait_for(lambda: (st := status()).cmd_seq == 77 and st.cycle >= before.cycle + 25
                          and st.lock_timeouts >= before.lock_timeouts + 10 and st, 20,
                          what="the daemon cycling, answering mds-cmd and counting lock timeouts while locked")
        assert during.cmd_result == ds.CMD_OK
        assert during.tx_frames > before.tx_frames and during.rx_frames > before.rx_frames  # queries, replies
        assert during.channel_errors == before.channel_errors  # a busy lock is not a broken channel
        while time.monotonic() - held_since < 3.0:  # the whole 3 s: the loop never stops
            cycle = status().cycle
            wait_for(lambda c=cycle: status().cycle > c + 5, 5, what="cycles while the lock is held")
        assert holder.holding()  # still holding the lock all this time
        holder.release()
        released = time.monotonic()
        fresh = wait_for(lambda: (st := state_in.latest()) is not None and st.time > released and st, 10,
                         what="mds-state after the lock was released")
        assert fresh.time > released
        skipped = status().lock_timeouts
        time.sleep(0.3)
        assert status().lock_timeouts == skipped  # nothing skipped once the lock is free
    finally:
        if holder is not None:
            holder.close()
        daemon.send_signal(signal.SIGTERM)
        out, _ = daemon.communicate(timeout=30)
        for ch in (status_in, state_in, cmd_out):
            ch.close()
    warnings = [line for line in out.splitlines() if "lock held by another process" in line]
    assert 1 <= len(warnings) <= 2 and mds.MDS_CHAN_STATE_NAME in warnings[0], out[-3000:]
    assert daemon.returncode == 0, out[-3000:]
