"""Run every benchmark module and print one table: value, baseline (same run), ratio, target, verdict.

Usage: python -m bench [--only NAME ...] [--quick]
"""

from __future__ import annotations

import argparse
import importlib
import platform
import sys
import time
import traceback

from bench.common import Row

MODULES = ["bench_ach", "bench_libach", "bench_daemon", "bench_events", "bench_ik", "bench_collision", "bench_bridge",
           "bench_tracking", "bench_network", "bench_viewer", "bench_record", "bench_safety",
           "bench_setup"]


def _fmt(v: float | None, unit: str = "") -> str:
    if v is None:
        return "-"
    if abs(v) >= 1000 or (0 < abs(v) < 0.01):
        return f"{v:.3g}{unit}"
    return f"{v:.2f}{unit}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="make bench", description=__doc__)
    ap.add_argument("--only", nargs="*", help="benchmark modules to run (default: all)")
    ap.add_argument("--quick", action="store_true", help="fewer samples (smoke run)")
    args = ap.parse_args(argv)
    rows: list[Row] = []
    failed: list[str] = []
    for name in args.only or MODULES:
        try:
            mod = importlib.import_module(f"bench.{name}")
        except ModuleNotFoundError as exc:
            if exc.name == f"bench.{name}":
                print(f"[skip] {name}: not present", file=sys.stderr)
                continue
            raise
        t0 = time.monotonic()
        print(f"[run] {name} ...", file=sys.stderr, flush=True)
        try:
            rows.extend(mod.run(quick=args.quick))
        except Exception:  # report and continue: one broken benchmark must not hide the others
            traceback.print_exc()
            failed.append(name)
        print(f"[done] {name} in {time.monotonic() - t0:.1f} s", file=sys.stderr, flush=True)
    print()
    print(f"machine: {platform.node()} {platform.machine()} {platform.python_implementation()} "
          f"{platform.python_version()}, {__import__('os').cpu_count()} cpus")
    header = f"| {'group':<10} | {'measurement':<44} | {'value':>10} | {'baseline (same run)':<34} | {'base':>10} " \
             f"| {'ratio':>7} | {'target':<22} | ok |"
    print(header)
    print("|" + "|".join("-" * (len(c)) for c in header.split("|")[1:-1]) + "|")
    for r in rows:
        ok = "-" if r.passed is None else ("yes" if r.passed else "NO")
        ratio = "-" if r.ratio is None else f"{r.ratio:.1f}x"
        print(f"| {r.group:<10} | {r.name:<44} | {_fmt(r.value, ' ' + r.unit):>10} | {r.baseline_name:<34} "
              f"| {_fmt(r.baseline_value, ' ' + r.unit if r.baseline_value is not None else ''):>10} "
              f"| {ratio:>7} | {r.target:<22} | {ok:<2} |")
    if failed:
        print(f"\nbenchmarks that raised: {', '.join(failed)}")
    misses = [r for r in rows if r.passed is False]
    print(f"\n{len(rows)} measurements, {len(misses)} below target")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
