"""One row of the benchmark report, plus small statistics helpers shared by every benchmark."""

from __future__ import annotations

import statistics
from dataclasses import dataclass


@dataclass
class Row:
    """A measurement next to the baseline measured in the same run.

    ``ratio`` is baseline / value for times (higher = better than baseline) unless ``higher_is_better``.
    """

    group: str
    name: str
    value: float
    unit: str
    baseline_name: str = ""
    baseline_value: float | None = None
    target: str = ""
    passed: bool | None = None
    higher_is_better: bool = False

    @property
    def ratio(self) -> float | None:
        if self.baseline_value is None or self.value == 0 or self.baseline_value == 0:
            return None
        return self.value / self.baseline_value if self.higher_is_better else self.baseline_value / self.value


def percentile(samples: list[float], q: float) -> float:
    """q in [0, 100]; nearest-rank on the sorted samples."""
    if not samples:
        return float("nan")
    data = sorted(samples)
    k = min(len(data) - 1, max(0, round(q / 100.0 * (len(data) - 1))))
    return data[k]


def median(samples: list[float]) -> float:
    return statistics.median(samples) if samples else float("nan")
