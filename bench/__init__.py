"""Benchmarks: `make bench` runs every module here and prints one table (baselines measured in the same run).

Test-only helpers the benchmarks share with the tests (simulated hosts, channel readers) live in test/support/,
imported as ``support``; test/ goes on ``sys.path`` here, once, for every benchmark module.
"""

import sys
from pathlib import Path

_TEST_DIR = str(Path(__file__).resolve().parent.parent / "test")
if _TEST_DIR not in sys.path:
    sys.path.append(_TEST_DIR)
