"""Set-up cost: how long `make setup` takes into a fresh virtual environment, and how big that runtime venv is.

`make setup` is what a lab runs on a new machine (the runtime only: no test tools, no benchmark peers). Measured
with pip's cache warm (the dev venv of `make bench` has just downloaded every wheel), into a temporary venv that
is removed afterwards. Where pip's cache stays empty (a proxy that sends no caching headers) the row says so:
that time includes every download. The largest installed distributions are printed to stderr, so a venv over its target
says what makes it big.

The install needs the package registry, which the private network namespace of ``tools/netns-run`` cannot reach:
``make bench`` measures it first, outside (``python -m bench.bench_setup measure FILE``), and the table inside
reads ``FILE`` (``MDS_BENCH_SETUP_RESULT``). Run alone outside the namespace, ``python -m bench --only
bench_setup`` measures directly.

Targets (issue 20): set-up <= 45 s with a warm package cache, venv <= 700 MB.
Skipped with --quick (it installs everything once).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import Row

GROUP = "setup"
REPO = Path(__file__).resolve().parent.parent
MB = 1e6


def tree_size(path: Path) -> int:
    """Bytes on disk of the files under ``path`` (symlinks not followed, hard links counted once)."""
    total, seen = 0, set()
    for root, _dirs, files in os.walk(path):
        for name in files:
            st = os.lstat(os.path.join(root, name))
            if (st.st_dev, st.st_ino) not in seen:
                seen.add((st.st_dev, st.st_ino))
                total += st.st_blocks * 512
    return total


def largest(site: Path, count: int = 8) -> list[tuple[str, int]]:
    """The ``count`` largest top-level entries of site-packages (packages and their data), by size."""
    sizes = [(p.name, tree_size(p) if p.is_dir() else p.stat().st_size) for p in site.iterdir()]
    return sorted(sizes, key=lambda x: -x[1])[:count]


def http_cache_files() -> int:
    """Files in pip's HTTP cache (where downloaded wheels are kept). 0 means the set-up below downloads every wheel
    again: pip caches nothing when it is disabled or when the index (or a proxy before it) answers without caching
    headers, as on this project's development machines."""
    proc = subprocess.run([sys.executable, "-m", "pip", "cache", "dir"], capture_output=True, text=True)
    if proc.returncode != 0 or not proc.stdout.strip():
        return 0
    root = Path(proc.stdout.strip())
    return sum(len(files) for sub in ("http-v2", "http") for _r, _d, files in os.walk(root / sub))


def measure() -> dict:
    """Install the runtime venv with ``make setup`` into a temporary directory: seconds, bytes, largest entries,
    and whether pip's cache had anything (``cached_files``; 0: every wheel was downloaded, so network included)."""
    cached = http_cache_files()
    with tempfile.TemporaryDirectory(prefix="mds-setup-") as tmp:
        venv = Path(tmp) / "venv"
        t0 = time.monotonic()
        proc = subprocess.run(["make", "-s", "setup", f"VENV={venv}"], cwd=REPO, capture_output=True, text=True)
        seconds = time.monotonic() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"make setup failed ({proc.returncode}): {proc.stderr[-2000:]}")
        size = tree_size(venv)
        site = next(venv.glob("lib/python*/site-packages"))
        big = largest(site)
        shutil.rmtree(venv, ignore_errors=True)
    return {"seconds": seconds, "bytes": size, "largest": big, "cached_files": cached}


def run(quick: bool = False) -> list[Row]:
    if quick:
        print("[bench_setup] skipped with --quick (it installs the runtime venv once)", file=sys.stderr)
        return []
    result_file = os.environ.get("MDS_BENCH_SETUP_RESULT", "")
    if os.environ.get("MDS_NETNS_ACTIVE") == "1":
        if not (result_file and Path(result_file).is_file()):
            print("[bench_setup] inside tools/netns-run (no registry) and no result of `python -m bench.bench_setup "
                  "measure FILE` (MDS_BENCH_SETUP_RESULT): skipped", file=sys.stderr)
            return []
        result = json.loads(Path(result_file).read_text())
    else:
        result = measure()
    seconds, size = result["seconds"], result["bytes"]
    print("[bench_setup] largest in the runtime venv: "
          + ", ".join(f"{name} {b / MB:.0f} MB" for name, b in result["largest"]), file=sys.stderr)
    warm = result.get("cached_files", 1) > 0  # results from before the field was added: as they were labelled
    if not warm:
        print("[bench_setup] pip's HTTP cache is empty (disabled, or the index sends no caching headers): the set-up "
              "time includes downloading every wheel, not the warm-cache case the target is for", file=sys.stderr)
    cache = "warm pip cache" if warm else "pip cache empty: downloads included"
    return [
        Row(GROUP, f"make setup into a fresh venv ({cache})", seconds, "s", "", None, "<= 45 s", seconds <= 45.0),
        Row(GROUP, "runtime venv size (make setup)", size / MB, "MB", "", None, "<= 700 MB", size / MB <= 700.0),
    ]


if __name__ == "__main__":
    if sys.argv[1:2] == ["measure"] and len(sys.argv) == 3:
        Path(sys.argv[2]).write_text(json.dumps(measure()))
        raise SystemExit(0)
    from bench.__main__ import main

    raise SystemExit(main(["--only", "bench_setup", *sys.argv[1:]]))
