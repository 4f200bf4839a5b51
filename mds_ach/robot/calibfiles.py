"""Which calibration files the joint table comes from at run time: the original installation's XML, else YAML.

Why: a lab that ran the original MDS-Ach keeps its calibration in ``/etc/mds-ach`` -- ``anatomy.xml`` (the Xitome
anatomy, rewritten by the Xitome homing procedure; the original installs it as ``configs/anatomy.xml``) and
``configs/mdsach.xml`` (short names, offsets, directions, enable flags) -- and re-reads it at every start. To be a
drop-in replacement the stack reads those files as they are, with no conversion step to forget.

The one rule (:func:`resolve`), first match wins:

1. ``--anatomy FILE`` / ``--overlay FILE`` (``mds-ach start``, the daemon), passed here as arguments;
2. ``$MDS_ACH_ANATOMY`` / ``$MDS_ACH_OVERLAY`` (``MDS_ACH_ANATOMY=none``: ignore the XML, use the packaged YAML);
3. ``<etc>/anatomy.xml`` or ``<etc>/configs/anatomy.xml`` with ``<etc>/configs/mdsach.xml``, where ``<etc>`` is
   ``$MDS_ACH_ETC`` or ``/etc/mds-ach`` (tests point it at a temporary directory, never at the real /etc);
4. nothing: the packaged YAML (``config/joints.yaml`` + the robot variant), see :mod:`mds_ach.robot.config`.

Without an explicit overlay, ``mdsach.xml`` is looked for in ``<etc>/configs/``, then beside the anatomy.

``changerobot`` (:func:`install_anatomy`) copies a robot's anatomy over the active ``anatomy.xml``, as the
original's script did.

Imports: nothing of the project (the robot layer's leaf).
"""

from __future__ import annotations

import filecmp
import os
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

ETC_ENV = "MDS_ACH_ETC"
ANATOMY_ENV = "MDS_ACH_ANATOMY"
OVERLAY_ENV = "MDS_ACH_OVERLAY"
DEFAULT_ETC = Path("/etc/mds-ach")
NO_XML = ("none", "yaml")  # $MDS_ACH_ANATOMY values that switch the XML off
ANATOMY_NAME = "anatomy.xml"
OVERLAY_NAME = "mdsach.xml"
# The original's robots (scripts/mds-ach ChangeRobot): name -> file in <etc>/configs.
ROBOT_ANATOMIES = {"isaac": "Isaac.anatomy.xml", "lucas": "Lucas.anatomy.xml", "octavia": "Octavia.anatomy.xml"}


class CalibrationError(ValueError):
    """Calibration files that were asked for but cannot be used; the message names the file and what to do."""


@dataclass(frozen=True)
class CalibrationFiles:
    """The anatomy and overlay the joint table is read from, and which rule chose them."""

    anatomy: Path
    overlay: Path
    origin: str  # "--anatomy", "$MDS_ACH_ANATOMY" or the etc directory

    def describe(self) -> str:
        return f"{self.anatomy} + {self.overlay} ({self.origin})"


def etc_dir(env: Mapping[str, str] | None = None) -> Path:
    """``$MDS_ACH_ETC``, else ``/etc/mds-ach``: the original installation's home."""
    env = os.environ if env is None else env
    return Path(env[ETC_ENV]) if env.get(ETC_ENV) else DEFAULT_ETC


def installed_anatomy(etc: Path) -> Path | None:
    """The anatomy of an original installation in ``etc``: ``anatomy.xml`` or ``configs/anatomy.xml`` (where the
    original's Makefile puts it). Both present with different content is ambiguous and refused."""
    found = [p for p in (etc / ANATOMY_NAME, etc / "configs" / ANATOMY_NAME) if p.is_file()]
    if len(found) == 2 and not filecmp.cmp(found[0], found[1], shallow=False):
        raise CalibrationError(f"{found[0]} and {found[1]} both exist and differ: remove the stale one, or choose "
                               f"with --anatomy FILE or ${ANATOMY_ENV}")
    return found[0] if found else None


def resolve(anatomy: str | Path | None = None, overlay: str | Path | None = None,
            env: Mapping[str, str] | None = None) -> CalibrationFiles | None:
    """The calibration files by the rule of the module doc, or None: use the packaged YAML."""
    env = os.environ if env is None else env
    etc = etc_dir(env)
    origin = "--anatomy"
    if anatomy is None:
        text = env.get(ANATOMY_ENV, "").strip()
        if text.lower() in NO_XML:
            return None
        if text:
            anatomy, origin = Path(text), f"${ANATOMY_ENV}"
        else:
            anatomy, origin = installed_anatomy(etc), str(etc)
            if anatomy is None:
                return None
    anatomy = Path(anatomy)
    if not anatomy.is_file():
        raise CalibrationError(f"{anatomy}: no such anatomy file (given by {origin})")
    if overlay is None and env.get(OVERLAY_ENV, "").strip():
        overlay = Path(env[OVERLAY_ENV].strip())
    if overlay is None:
        candidates = [etc / "configs" / OVERLAY_NAME, anatomy.parent / OVERLAY_NAME]
        overlay = next((p for p in candidates if p.is_file()), None)
        if overlay is None:
            raise CalibrationError(f"{anatomy}: no {OVERLAY_NAME} overlay (looked in "
                                   f"{', '.join(str(p.parent) for p in candidates)}); give --overlay FILE or "
                                   f"${OVERLAY_ENV}")
    overlay = Path(overlay)
    if not overlay.is_file():
        raise CalibrationError(f"{overlay}: no such overlay file")
    return CalibrationFiles(anatomy.absolute(), overlay.absolute(), origin)


def robot_anatomy(name: str, etc: Path) -> Path | None:
    """``<etc>/configs/<Robot>.anatomy.xml`` for one of the original's robot names, if installed."""
    file = ROBOT_ANATOMIES.get(name.strip().lower())
    path = etc / "configs" / file if file else None
    return path if path is not None and path.is_file() else None


def install_anatomy(source: Path, etc: Path) -> list[Path]:
    """Copy ``source`` over the anatomy of ``etc`` (each of ``anatomy.xml`` and ``configs/anatomy.xml`` that exists,
    so the two never disagree; where none exists, ``configs/anatomy.xml``, the original's place), atomically: a
    reader sees the old or the new file. Returns the files written."""
    targets = [p for p in (etc / ANATOMY_NAME, etc / "configs" / ANATOMY_NAME) if p.is_file()]
    targets = targets or [etc / "configs" / ANATOMY_NAME]
    for target in targets:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".anatomy.", dir=target.parent)
        os.close(fd)
        try:
            shutil.copyfile(source, tmp)
            os.chmod(tmp, 0o644)
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    return targets
