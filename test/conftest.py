"""Shared fixtures: where the reference material lives, a clean /dev/shm per test, polling helper."""

from __future__ import annotations

import glob
import os
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
VENV_BIN = Path(sys.executable).parent


def _shared_dir() -> Path:
    env = os.environ.get("MDS_SHARED_DIR")
    return Path(env) if env else REPO.parent / "shared"


SHARED = _shared_dir()


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The reference material (specs, golden Ach files, MDS configs, CAN logs)."""
    assert SHARED.is_dir(), f"reference material not found at {SHARED} (set MDS_SHARED_DIR)"
    return SHARED


def remove_mds_channels() -> None:
    for path in glob.glob("/dev/shm/achshm-mds*") + glob.glob("/dev/shm/achshm-test*"):
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass


@pytest.fixture
def clean_shm() -> Iterator[None]:
    """No MDS or test channels before or after the test."""
    remove_mds_channels()
    yield
    remove_mds_channels()


def wait_for(predicate: Callable[[], object], timeout: float = 10.0, interval: float = 0.01, what: str = "") -> object:
    """Poll ``predicate`` until it returns a truthy value; fail with ``what`` after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what or predicate}")
        time.sleep(interval)


def in_netns() -> bool:
    return os.environ.get("MDS_NETNS_ACTIVE") == "1"


@pytest.fixture(params=["fast", "pure"])
def ach_impl(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run a test once with the C fast path of ``mds_ach.ach`` and once with its pure-Python code.

    The environment variable reaches child processes too. ``test_ach_fast.py`` fails when the fast path
    could have been built but was not, so "fast" never silently means "pure".
    """
    from mds_ach import ach
    from mds_ach.ach import channel

    if request.param == "pure":
        monkeypatch.setattr(channel, "_achfast", None)  # the module whose Channel consults it (at open)
        monkeypatch.setenv("MDS_ACH_PURE_PYTHON", "1")
    elif not ach.FAST_AVAILABLE:
        pytest.skip("mds_ach.ach._achfast is not built here (no C compiler); test_ach_fast.py reports why")
    return request.param


NOBODY = 65534  # uid and gid of user nobody / group nogroup


def run_as(uid: int, gid: int, func: Callable[[], int], groups: tuple[int, ...] = ()) -> int:
    """Run ``func`` in a forked child as another user (we are root in the test namespace); its return value,
    or 1 after printing the traceback, is the exit status returned here. A fork, not a new interpreter:
    the venv's Python lives under /root, which other users cannot execute."""
    import traceback

    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            os.setgroups(list(groups))
            os.setgid(gid)
            os.setuid(uid)
            code = int(func())
        except BaseException:
            traceback.print_exc()
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    return os.waitstatus_to_exitcode(status)
