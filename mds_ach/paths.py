"""Where the package's data files are: the source tree when run from a checkout, else the ament share dir."""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

PACKAGE = "mds_ach"
# Executables in a bin/ directory (the venv's, a prefix's) carry this prefix so that none shadows a shell builtin or a
# common command (`read`, `daemon`, `filter`); in <prefix>/lib/mds_ach (what `ros2 run mds_ach <node>` runs) they keep
# the bare node name. setup.py applies the same rule.
BIN_PREFIX = "mds-ach-"
CHANNEL_PREFIX_ENV = "MDS_ACH_CHANNEL_PREFIX"  # read here for the runtime dir; checked and used in robot/contracts
_SOURCE_ROOT = Path(__file__).resolve().parent.parent


@lru_cache(maxsize=1)
def share_dir() -> Path:
    """``<repo>`` in a checkout (it has urdf/ and config/), else ``share/mds_ach`` of the install prefix."""
    if (_SOURCE_ROOT / "urdf").is_dir() and (_SOURCE_ROOT / "config").is_dir():
        return _SOURCE_ROOT
    try:  # only an installed ROS package gets here; a checkout (or pip install) may lack ament_index_python
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory(PACKAGE))
    except Exception as exc:  # PackageNotFoundError or missing AMENT_PREFIX_PATH
        raise FileNotFoundError(
            f"cannot find the {PACKAGE} data files: not in a source checkout and the ament index has no "
            f"'{PACKAGE}' (AMENT_PREFIX_PATH={os.environ.get('AMENT_PREFIX_PATH', '')!r})"
        ) from exc


def config_path(name: str) -> Path:
    """A file in ``config/``, e.g. ``config_path('joints.yaml')``."""
    return share_dir() / "config" / name


def urdf_path(name: str = "mds.urdf") -> Path:
    return share_dir() / "urdf" / name


def bin_name(node: str) -> str:
    """The name of ``node``'s executable in a bin/ directory: ``mds-ach-daemon`` for ``daemon``."""
    return node if node.startswith("mds-ach") else BIN_PREFIX + node


IDENTITY_MAP = [(0, 0, 4294967295)]  # /proc/self/uid_map outside any user namespace
OVERFLOW_UID = 65534  # what a user namespace shows for an owner it does not map (/proc/sys/kernel/overflowuid)


def _uid_map() -> list[tuple[int, int, int]]:
    try:
        with open("/proc/self/uid_map") as f:
            return [(int(a), int(b), int(c)) for a, b, c in (line.split() for line in f)]
    except (OSError, ValueError):
        return IDENTITY_MAP


def outside_uid(uid: int) -> int | None:
    """``uid`` as this process sees it, as the machine's accounts see it: mapped through /proc/self/uid_map inside a
    user namespace; None for an id the namespace does not map (it shows every such owner as ``OVERFLOW_UID``)."""
    ranges = _uid_map()
    if ranges == IDENTITY_MAP:
        return uid
    return next((out + uid - inside for inside, out, count in ranges if inside <= uid < inside + count), None)


def host_uid() -> int:
    """Our uid as the machine's user accounts see it. Inside the user namespace of a rootless tools/netns-run a
    normal user appears as root (uid 0); /proc/self/uid_map maps that back, so that every terminal of that user,
    inside or outside the namespace, agrees on the runtime directory."""
    uid = os.getuid()
    found = outside_uid(uid)
    return uid if found is None else found


def user_label(uid: int) -> str:
    """A file owner or process user as the machine names it, ``alice (uid 1000)``: inside the user namespace of a
    rootless ``make run`` the user is uid 0 and every owner the namespace does not map (root's files after ``sudo
    make run`` among them) shows as uid 65534, so the ids seen here would name the wrong users (issue 28)."""
    import pwd

    outside = outside_uid(uid)
    unmapped = (f"a user this user namespace does not map (shown here as uid {uid}; root, if the files come from "
                "'sudo make run')")
    if outside is None:
        return unmapped
    try:
        name = f"{pwd.getpwuid(outside).pw_name} (uid {outside})"
    except KeyError:
        name = f"uid {outside}"
    if uid == OVERFLOW_UID and _uid_map() != IDENTITY_MAP:  # mapped here (--map-auto), yet also every unmapped owner
        return f"{pwd.getpwuid(uid).pw_name if _known(uid) else name} or {unmapped}"
    return name


def _known(uid: int) -> bool:
    import pwd

    try:
        pwd.getpwuid(uid)
    except KeyError:
        return False
    return True


def runtime_dir() -> Path:
    """Pid files and logs of `mds-ach start`: $MDS_ACH_RUNTIME_DIR, else $XDG_RUNTIME_DIR/mds-ach, else
    /tmp/mds-ach-<uid> (the uid outside a user namespace: see host_uid). A second system on this host, whose
    channels carry a prefix ($MDS_ACH_CHANNEL_PREFIX, mds_ach.robot.contracts), gets its own by default:
    ``mds-ach-<prefix>`` / ``/tmp/mds-ach-<uid>-<prefix>``, so its pid files never stand for the first one's."""
    env = os.environ.get("MDS_ACH_RUNTIME_DIR")
    if env:
        return Path(env)
    prefix = os.environ.get(CHANNEL_PREFIX_ENV, "").strip("-_.")
    suffix = f"-{prefix}" if prefix else ""
    xdg = os.environ.get("XDG_RUNTIME_DIR")
    return Path(xdg) / f"mds-ach{suffix}" if xdg else Path(f"/tmp/mds-ach-{host_uid()}{suffix}")
