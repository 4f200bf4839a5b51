"""The simulated daemon (``--nocan --no-ros``) and the ROS bridge as child processes of a test module, with a probe
node in the test's process: the one set-up and tear-down of the bridge harnesses (test_bridge, test_bridge_lifecycle,
test_tf), so a failed wait shows both logs the same way and every module checks the bridge's clean exit."""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

from support import VENV_BIN, in_netns, remove_mds_channels
from support.spin import Spinner


class BridgeProcs(Spinner):
    """Start with :meth:`start_daemon`, then :meth:`start_bridge`; :meth:`close` stops both and returns the bridge's
    exit code (0: it shut down cleanly on SIGTERM)."""

    log: Path
    daemon_log: Path
    daemon: subprocess.Popen[bytes]
    bridge: subprocess.Popen[bytes]

    def start_daemon(self, tmp: Path, *args: str) -> None:
        self.log, self.daemon_log = tmp / "bridge.log", tmp / "daemon.log"
        self.daemon = subprocess.Popen([str(VENV_BIN / "mds-ach-daemon"), "--nocan", "--no-ros", *args],
                                       stdout=self.daemon_log.open("w"), stderr=subprocess.STDOUT)

    def start_bridge(self, *ros_args: str) -> None:
        cmd = [str(VENV_BIN / "mds-ach-bridge")] + (["--ros-args", *ros_args] if ros_args else [])
        self.bridge = subprocess.Popen(cmd, stdout=self.log.open("w"), stderr=subprocess.STDOUT)

    def bridge_log(self) -> str:
        daemon = self.daemon_log.read_text() if self.daemon_log.exists() else ""
        return (self.log.read_text() if self.log.exists() else "") + "\n--- daemon:\n" + daemon[-3000:]

    def stop_bridge(self) -> int:
        if self.bridge.poll() is None:
            self.bridge.send_signal(signal.SIGTERM)
        return self.bridge.wait(timeout=15)

    def stop_daemon(self) -> None:
        if self.daemon.poll() is None:
            os.kill(self.daemon.pid, signal.SIGCONT)  # a test may have stopped it (a stalled daemon)
            self.daemon.terminate()
            self.daemon.wait(timeout=10)

    def close(self) -> int:
        self.close_node()
        rc = self.stop_bridge()
        self.stop_daemon()
        return rc


H = TypeVar("H", bound=BridgeProcs)


def module_harness(make: Callable[[], H]) -> Iterator[H]:
    """The body of a module-scoped fixture: fresh channels, the harness, and after the module its clean shutdown."""
    assert in_netns(), "run the suite through tools/netns-run (make test)"
    remove_mds_channels()
    h = make()
    try:
        yield h
    finally:
        rc = h.close()
        remove_mds_channels()
    assert rc == 0, f"bridge exited with {rc} on SIGTERM; log:\n{h.bridge_log()}"
