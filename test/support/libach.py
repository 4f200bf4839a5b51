"""The project's libach for C clients (``libach/``), for tests and benchmarks: where it is installed, and C
programs built against it the way a C client builds (``pkg-config --cflags --libs ach``).

``make setup`` installs it into the venv (``$VENV/lib/libach.so``, ``$VENV/include/ach.h``,
``$VENV/lib/pkgconfig/ach.pc``). When that copy is missing or older than its sources (a checkout edited since the
last ``make setup``), it is built into a private prefix instead, so the tests always exercise the current code.
"""

from __future__ import annotations

import functools
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from support import REPO

SOURCES = [REPO / "libach" / n for n in ("libach.c", "ach.h", "ach.pc.in", "Makefile")] + [
    REPO / "mds_ach" / "ach" / "achcore.h"]


def _current(prefix: Path) -> bool:
    lib = prefix / "lib" / "libach.so"
    needed = (lib, prefix / "include" / "ach.h", prefix / "lib" / "pkgconfig" / "ach.pc")
    if not all(p.exists() for p in needed):
        return False
    built = lib.resolve().stat().st_mtime
    return all(src.stat().st_mtime <= built for src in SOURCES)


@functools.cache
def prefix() -> Path:
    """The install prefix of an up-to-date libach (the venv's, or a private build of the current sources)."""
    venv = Path(sys.prefix)
    if _current(venv):
        return venv
    own = Path(tempfile.mkdtemp(prefix="mds-libach-"))
    subprocess.run(["make", "-s", "-C", str(REPO / "libach"), "install", f"PREFIX={own}", f"BUILD={own}/build"],
                   check=True, capture_output=True, text=True)
    return own


def flags(pfx: Path | None = None) -> list[str]:
    """Compiler and linker flags for a C client, from ach.pc through pkg-config when it is installed."""
    pfx = pfx or prefix()
    if shutil.which("pkg-config"):
        env = dict(os.environ, PKG_CONFIG_PATH=str(pfx / "lib" / "pkgconfig"))
        out = subprocess.run(["pkg-config", "--cflags", "--libs", "ach"], env=env, check=True, capture_output=True,
                             text=True).stdout
        return out.split()
    return [f"-I{pfx}/include", f"-L{pfx}/lib", f"-Wl,-rpath,{pfx}/lib", "-lach"]


def build(source: Path, out: Path, *extra: str) -> Path:
    """Compile one C program against the library (warnings are errors); returns ``out``."""
    cmd = ["cc", "-O2", "-g", "-Wall", "-Wextra", "-Werror", "-std=gnu11", "-o", str(out), str(source), *extra,
           *flags(), "-lpthread"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"building {source.name} failed:\n{' '.join(cmd)}\n{proc.stderr}")
    return out
