"""golems/ach's own tools (``achd``, ``ach``), for the tests that check behaviour against the original programs.

They are never part of this project (no code of theirs is committed): a lab has them installed (the Debian
package, or ``make install`` of github.com/golems/ach), or a developer builds them anywhere and points
``$MDS_ACH_GOLEMS_BIN`` at the directory holding ``achd`` and ``ach``. ``tool(name)`` finds one, else the test
is skipped naming what is missing -- only then: a tool that is there but fails makes the test fail.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

ENV = "MDS_ACH_GOLEMS_BIN"


def _is_golems(path: Path) -> bool:
    """Is ``path`` golems' tool (its ``-V`` names ach's version line), not some other program of that name?"""
    try:
        proc = subprocess.run([str(path), "-V"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return proc.stdout.startswith(f"{path.name} ") and "Georgia Tech" in proc.stdout


def find(name: str) -> Path | None:
    """golems' ``name`` (achd, ach) from ``$MDS_ACH_GOLEMS_BIN``, else from PATH; None if neither has it."""
    where = os.environ.get(ENV)
    if where:
        path = Path(where) / name
        if not path.exists():
            raise AssertionError(f"${ENV}={where} has no {name}")
        assert _is_golems(path), f"{path} is not golems' {name} ({path} -V)"
        return path
    found = shutil.which(name)
    return Path(found) if found and _is_golems(Path(found)) else None


def tool(name: str) -> Path:
    """golems' ``name``; skips the test when it is not installed (set ${ENV} to a build's directory)."""
    path = find(name)
    if path is None:
        pytest.skip(f"golems' {name} is not installed (build github.com/golems/ach and set ${ENV} to the "
                    f"directory holding {name})")
    return path


class Inetd:
    """golems' ``achd serve`` the way a lab runs it, under inetd (``8076 stream tcp nowait nobody achd achd
    serve``): every accepted connection runs one ``achd serve`` with the socket as its stdin and stdout. Listens on
    127.0.0.1, any free port (``port``); ``with Inetd(achd) as srv: ...`` stops it and every server it ran."""

    def __init__(self, achd: Path) -> None:
        import socket
        import threading

        self.achd = achd
        self._sock = socket.socket()
        self._sock.bind(("127.0.0.1", 0))
        self._sock.listen(16)
        self._sock.settimeout(0.2)
        self.port = self._sock.getsockname()[1]
        self.procs: list[subprocess.Popen] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._accept, daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except OSError:
                continue
            with conn:
                conn.settimeout(None)
                self.procs.append(subprocess.Popen([str(self.achd), "serve"], stdin=conn.fileno(),
                                                   stdout=conn.fileno(), stderr=subprocess.DEVNULL))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self._sock.close()
        for proc in self.procs:
            proc.terminate()
        for proc in self.procs:
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)

    def __enter__(self) -> Inetd:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
