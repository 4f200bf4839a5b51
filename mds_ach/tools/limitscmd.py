"""``mds-ach limits``: the published joint limits (what each joint can follow) and MoveIt's ``joint_limits.yaml``.

``mds-ach limits`` prints each joint's range, velocity and acceleration from the limit authority
(``mds_ach.kinematics.limits``: the running daemon's ``mds-limits``, else computed the same way).
``--moveit-yaml [PATH]`` writes them as MoveIt's ``joint_limits.yaml`` (default ``config/joint_limits.yaml``, ``-``
for stdout); with ``--check`` nothing is written and the exit status says whether the file is up to date.
Exit status 0 ok, 1 failure (a bad joint table, an out-of-date file with ``--check``), 2 usage error.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mds_ach import paths
from mds_ach.kinematics import limits as authority
from mds_ach.robot import config
from mds_ach.robot.joints import BY_ADDRESS


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--robot", help="robot variant (default: the running daemon's, else the chosen one)")
    p.add_argument("--moveit-yaml", nargs="?", const="", metavar="PATH",
                   help=f"write MoveIt's joint_limits.yaml (default: config/{authority.MOVEIT_YAML}; '-': stdout)")
    p.add_argument("--check", action="store_true",
                   help="with --moveit-yaml: write nothing, exit 1 if the file differs from the limits")


def table_text(limits: authority.EffectiveLimits) -> str:
    """One line per joint with limits: range, velocity, acceleration; a heading naming where they come from."""
    where = "mds-limits (the running daemon's)" if limits.published else "computed (no daemon published mds-limits)"
    lines = [f"{limits.describe()}: {limits.source}; {where}",
             f"{'joint':<6} {'lower':>9} {'upper':>9} {'velocity':>9} {'accel':>9}",
             f"{'':<6} {'rad':>9} {'rad':>9} {'rad/s':>9} {'rad/s^2':>9}"]
    for address, joint in sorted(BY_ADDRESS.items()):
        rng, dyn = limits.range(address), limits.motion(address)
        if rng is not None and dyn is not None:
            lines.append(f"{joint.short:<6} {rng[0]:>9.4f} {rng[1]:>9.4f} {dyn[0]:>9.4f} {dyn[1]:>9.4f}")
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    try:
        limits = authority.current_limits(args.robot)
    except (config.ConfigError, FileNotFoundError, KeyError) as exc:
        print(f"mds-ach limits: {exc}", file=sys.stderr)
        return 1
    if args.moveit_yaml is None:
        if args.check:
            print("mds-ach limits: --check needs --moveit-yaml", file=sys.stderr)
            return 2
        sys.stdout.write(table_text(limits))
        return 0
    text = authority.moveit_yaml(limits)
    if args.moveit_yaml == "-":
        sys.stdout.write(text)
        return 0
    path = Path(args.moveit_yaml) if args.moveit_yaml else paths.config_path(authority.MOVEIT_YAML)
    if args.check:
        current = path.read_text() if path.exists() else ""
        if current != text:
            print(f"mds-ach limits: {path} is out of date (robot {limits.robot}); run: mds-ach limits --moveit-yaml "
                  f"--robot {limits.robot}", file=sys.stderr)
            return 1
        print(f"{path} is up to date (robot {limits.robot})")
        return 0
    try:
        path.write_text(text)
    except OSError as exc:
        print(f"mds-ach limits: cannot write {path}: {exc}", file=sys.stderr)
        return 1
    print(f"wrote {path} (robot {limits.robot}: {limits.source})")
    return 0
