"""CPU hogs: busy-loop processes at normal priority, so that every process of the stack waits for a CPU.

Each hog ends by itself after ``seconds`` (a hog left behind by a killed parent stops on its own), and ``close()``
kills them all at once. Used by the adversarial scenario's overload phase (``bench/adversary.py``, ``make soak``).
"""

from __future__ import annotations

import subprocess
import sys
from types import TracebackType

_HOG = "import sys, time\nend = time.monotonic() + float(sys.argv[1])\nwhile time.monotonic() < end:\n    pass\n"


class CpuHogs:
    """``count`` busy-loop processes for at most ``seconds`` each."""

    def __init__(self, count: int, seconds: float) -> None:
        if count < 0 or not seconds > 0:
            raise ValueError(f"CpuHogs: count >= 0 and seconds > 0, got {count}, {seconds}")
        self.procs = [subprocess.Popen([sys.executable, "-c", _HOG, f"{seconds:.3f}"]) for _ in range(count)]

    def close(self) -> None:
        for p in self.procs:
            p.kill()
        for p in self.procs:
            p.wait()

    def __enter__(self) -> CpuHogs:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()
