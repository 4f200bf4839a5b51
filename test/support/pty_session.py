"""Drive a program through a pseudo-terminal, like pexpect: the console and the read monitor are terminal
programs (line editing, cbreak keys, Ctrl-C from the tty, window size), so they are tested as a user sees them."""

from __future__ import annotations

import errno
import fcntl
import os
import pty
import re
import select
import signal
import struct
import termios
import time


class PtySession:
    """``with PtySession(argv, env) as s: s.expect('prompt'); s.send('q')``; ``wait()`` gives the exit status."""

    def __init__(self, argv: list[str], env: dict[str, str] | None = None, rows: int = 40, cols: int = 120) -> None:
        pid, fd = pty.fork()
        if pid == 0:  # child: the pty is already its controlling terminal and stdio
            try:
                for sig in (signal.SIGINT, signal.SIGQUIT, signal.SIGPIPE):  # as in a user's shell, even if
                    signal.signal(sig, signal.SIG_DFL)  # the test runner was started with them ignored
                fcntl.ioctl(0, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))
                os.execvpe(argv[0], argv, env if env is not None else os.environ)
            finally:
                os._exit(127)
        self.pid, self.fd = pid, fd
        self.buffer = ""
        self.pos = 0  # search start: text before it was matched already
        self.status: int | None = None

    # -- I/O ---------------------------------------------------------------------------------------

    def _read(self, timeout: float) -> bool:
        """Read what is available within ``timeout`` s; False at end of output."""
        ready, _, _ = select.select([self.fd], [], [], timeout)
        if not ready:
            return True
        try:
            data = os.read(self.fd, 65536)
        except OSError as exc:
            if exc.errno == errno.EIO:  # the child closed the terminal
                return False
            raise
        if not data:
            return False
        self.buffer += data.decode("utf-8", "replace")
        return True

    def expect(self, pattern: str | re.Pattern[str], timeout: float = 10.0) -> re.Match[str] | str:
        """Wait for ``pattern`` (text or regex) after the previous match; fail with the output seen."""
        deadline = time.monotonic() + timeout
        while True:
            if isinstance(pattern, str):
                i = self.buffer.find(pattern, self.pos)
                if i >= 0:
                    self.pos = i + len(pattern)
                    return pattern
            else:
                m = pattern.search(self.buffer, self.pos)
                if m:
                    self.pos = m.end()
                    return m
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._read(min(remaining, 0.1)):
                raise AssertionError(f"did not see {pattern!r} within {timeout} s; output so far:\n"
                                     f"{self.buffer[-3000:]!r}")

    def send(self, text: str) -> None:
        os.write(self.fd, text.encode())

    def resize(self, rows: int, cols: int) -> None:
        """Change the window size; the kernel sends SIGWINCH to the program."""
        fcntl.ioctl(self.fd, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))

    def terminate(self, sig: int = signal.SIGTERM) -> None:
        os.kill(self.pid, sig)

    # -- exit --------------------------------------------------------------------------------------

    def poll(self) -> int | None:
        if self.status is None:
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                self.status = os.waitstatus_to_exitcode(status)
        return self.status

    def wait(self, timeout: float = 10.0) -> int:
        """Exit status (negative: killed by that signal), draining output meanwhile; fails on timeout."""
        deadline = time.monotonic() + timeout
        while self.poll() is None:
            if time.monotonic() > deadline:
                raise AssertionError(f"still running after {timeout} s; output:\n{self.buffer[-3000:]!r}")
            if not self._read(0.05):
                time.sleep(0.02)
        while self._read(0):  # whatever is left
            if not select.select([self.fd], [], [], 0)[0]:
                break
        return self.status  # type: ignore[return-value]

    def close(self) -> None:
        if self.poll() is None:
            os.kill(self.pid, signal.SIGKILL)
            os.waitpid(self.pid, 0)
            self.status = -signal.SIGKILL
        try:
            os.close(self.fd)
        except OSError:
            pass

    def __enter__(self) -> PtySession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
