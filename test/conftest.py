"""Shared fixtures only (a clean /dev/shm per test, the reference material, both ach code paths); the helpers
they use, and every other shared helper, live in ``support`` (test/support/)."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from support import NOBODY, SHARED, other_ids_missing, remove_mds_channels

from mds_ach import ach

# The tests never read this machine's calibration files (a lab PC has /etc/mds-ach): no original installation
# unless a test makes one in a temporary directory (MDS_ACH_ETC), no anatomy from the caller's shell.
os.environ["MDS_ACH_ETC"] = "/nonexistent/mds-ach-etc-of-the-tests"
os.environ.pop("MDS_ACH_ANATOMY", None)
os.environ.pop("MDS_ACH_OVERLAY", None)


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """The reference material (specs, golden Ach files, MDS configs, CAN logs)."""
    assert SHARED.is_dir(), f"reference material not found at {SHARED} (set MDS_SHARED_DIR)"
    return SHARED


@pytest.fixture
def clean_shm() -> Iterator[None]:
    """No MDS or test channels before or after the test."""
    remove_mds_channels()
    yield
    remove_mds_channels()


@pytest.fixture
def other_user() -> int:
    """The uid (and gid) of user nobody, for a test that acts as another user (``support.run_as``): skipped with
    what is missing where this namespace has no second uid (tools/netns-run as a normal user without uidmap and a
    /etc/subuid range)."""
    reason = other_ids_missing()
    if reason:
        pytest.skip(reason)
    return NOBODY


@pytest.fixture(params=["fast", "pure"])
def ach_impl(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run a test once with the C fast path of ``mds_ach.ach`` and once with its pure-Python code.

    The environment variable reaches child processes too. ``test_ach_fast.py`` fails when the fast path
    could have been built but was not, so "fast" never silently means "pure".
    """
    from mds_ach.ach import channel

    if request.param == "pure":
        monkeypatch.setattr(channel, "_achfast", None)  # the module whose Channel consults it (at open)
        monkeypatch.setenv("MDS_ACH_PURE_PYTHON", "1")
    elif not ach.FAST_AVAILABLE:
        pytest.skip("mds_ach.ach._achfast is not built here (no C compiler); test_ach_fast.py reports why")
    return request.param


@pytest.fixture
def golden_names() -> Iterator[None]:
    """The golden channels carry their names in the header (shared/ach-golden), so tests must use those names;
    removed before and after."""
    names = ("golden_empty", "golden_small", "golden_wrap")

    def clean() -> None:
        for name in names:
            if ach.exists(name):
                ach.unlink(name)

    clean()
    yield
    clean()
