"""The robot variant chosen with ``mds-ach changerobot``, persisted so the next start uses it.

Why a file: the original copied ``<Robot>.anatomy.xml`` over ``anatomy.xml`` in /etc/mds-ach, so the choice
survived reboots and applied to every later start. Here the choice is one word in
``$MDS_ACH_CONFIG_DIR/robot`` (default ``$XDG_CONFIG_HOME/mds-ach/robot``, i.e. ``~/.config/mds-ach/robot``).
``$MDS_ACH_ROBOT`` still wins when set; the launcher exports the saved choice as ``$MDS_ACH_ROBOT`` to the
nodes it starts, which is where ``mds_ach.robot.config`` reads it.

This module is the one robot-choice rule (explicit name, else ``$MDS_ACH_ROBOT``, else the saved choice, else
``default``) and the list of robots there are; :mod:`mds_ach.robot.config` builds on it, never the reverse.

Imports: :mod:`mds_ach.paths` only.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path

from mds_ach.paths import config_path

CONFIG_DIR_ENV = "MDS_ACH_CONFIG_DIR"
ROBOT_ENV = "MDS_ACH_ROBOT"
DEFAULT_ROBOT = "default"


ROBOT_NAME_MAX = 64
"""The longest robot name: a name is one word (a file stem under config/robots, an anatomy in /etc/mds-ach)."""
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot be a robot's name (length, characters), or None; whether it exists is checked later
    (``available_robots``, ``config.robot_name``)."""
    if len(name) > ROBOT_NAME_MAX:
        return f"a robot name has at most {ROBOT_NAME_MAX} characters (got {len(name)})"
    if not _NAME.fullmatch(name.strip()):
        return f"invalid robot name {name!r}: letters, digits, '_', '.' and '-', starting with a letter or digit"
    return None


def available_robots(config_dir: Path | None = None) -> tuple[str, ...]:
    """``default`` plus every ``config/robots/<name>.yaml`` overlay of the package (or of ``config_dir``)."""
    robots = (config_dir or config_path("")) / "robots"
    extra = sorted(p.stem for p in robots.glob("*.yaml")) if robots.is_dir() else []
    return tuple(dict.fromkeys((DEFAULT_ROBOT, *extra)))


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


def effective_robot(env: Mapping[str, str] | None = None, robot: str | None = None) -> tuple[str, str]:
    """(robot, where it came from): ``robot`` if given, else $MDS_ACH_ROBOT, else the saved choice, else the
    default. The name is normalised, not validated (``config.robot_name`` refuses unknown ones)."""
    if robot:
        return robot.strip().lower(), "argument"
    env = os.environ if env is None else env
    if env.get(ROBOT_ENV):
        return env[ROBOT_ENV].strip().lower(), f"${ROBOT_ENV}"
    saved = saved_robot()
    if saved:
        return saved, str(robot_file())
    return DEFAULT_ROBOT, "default"
