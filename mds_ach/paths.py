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


def host_uid() -> int:
    """Our uid as the machine's user accounts see it. Inside the user namespace of a rootless tools/netns-run a
    normal user appears as root (uid 0); /proc/self/uid_map maps that back, so that every terminal of that user,
    inside or outside the namespace, agrees on the runtime directory."""
    uid = os.getuid()
    try:
        with open("/proc/self/uid_map") as f:
            for line in f:
                inside, outside, count = (int(x) for x in line.split())
                if inside <= uid < inside + count:
                    return outside + uid - inside
    except (OSError, ValueError):
        pass
    return uid


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
