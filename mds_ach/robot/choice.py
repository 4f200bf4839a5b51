"""The robot variant chosen with ``mds-ach changerobot``, persisted so the next start uses it.

Why a file: the original copied ``<Robot>.anatomy.xml`` over ``anatomy.xml`` in /etc/mds-ach, so the choice
survived reboots and applied to every later start. Here the choice is one word in
``$MDS_ACH_CONFIG_DIR/robot`` (default ``$XDG_CONFIG_HOME/mds-ach/robot``, i.e. ``~/.config/mds-ach/robot``).
``$MDS_ACH_ROBOT`` still wins when set; the launcher exports the saved choice as ``$MDS_ACH_ROBOT`` to the
nodes it starts, which is where ``mds_ach.robot.config`` reads it.
"""

from __future__ import annotations

import os
from pathlib import Path

from mds_ach.robot.config import DEFAULT_ROBOT, ROBOT_ENV, available_robots

CONFIG_DIR_ENV = "MDS_ACH_CONFIG_DIR"


def config_dir() -> Path:
    """$MDS_ACH_CONFIG_DIR, else $XDG_CONFIG_HOME/mds-ach, else ~/.config/mds-ach."""
    env = os.environ.get(CONFIG_DIR_ENV)
    if env:
        return Path(env)
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "mds-ach"


def robot_file() -> Path:
    return config_dir() / "robot"


def saved_robot() -> str | None:
    """The saved choice, or None when nothing (or something unreadable) was saved."""
    try:
        name = robot_file().read_text(encoding="ascii").strip().lower()
    except (OSError, UnicodeDecodeError):
        return None
    return name if name in available_robots() else None


def save_robot(name: str) -> Path:
    """Validate and persist ``name``; returns the file written. Raises ValueError for an unknown robot."""
    name = name.strip().lower()
    robots = available_robots()
    if name not in robots:
        raise ValueError(f"unknown robot {name!r}; choose one of: {', '.join(robots)}")
    path = robot_file()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(name + "\n", encoding="ascii")
    os.replace(tmp, path)
    return path


def effective_robot(env: dict[str, str] | None = None) -> tuple[str, str]:
    """(robot, where it came from): $MDS_ACH_ROBOT, else the saved choice, else the default."""
    env = os.environ if env is None else env
    if env.get(ROBOT_ENV):
        return env[ROBOT_ENV].strip().lower(), f"${ROBOT_ENV}"
    saved = saved_robot()
    if saved:
        return saved, str(robot_file())
    return DEFAULT_ROBOT, "default"
