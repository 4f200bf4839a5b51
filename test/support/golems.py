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
