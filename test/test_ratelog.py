"""The shared rate-limited log (mds_ach.ratelog): one line per change, repeats counted, bounded at any rate."""

from __future__ import annotations

from mds_ach.ratelog import RateLimitedLog


class _Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_repeats_are_counted_and_summarized_at_most_every_period() -> None:
    clock, lines = _Clock(), []
    log = RateLimitedLog(lambda level, msg: lines.append((level, msg)), every=5.0, clock=clock)
    for i in range(10_000):  # 1 kHz for 10 s, a new value each time, one kind
        clock.t = 100.0 + i * 1e-3
        log("ros", f"value {i}", kind="LSP", level="error")
    assert lines[0] == ("error", "value 0")
    assert len(lines) == 2 and lines[1][1] == "value 5000 [repeated 5000x in 5.0 s, 5001 in all]"
    clock.t += 5.0
    log.tick()  # the burst stopped: its count is still written
    assert lines[-1][1] == "value 9999 [repeated 4999x in 10.0 s, 10000 in all]" and log.total("ros") == 10_000
    log.tick()
    assert len(lines) == 3  # nothing pending: nothing more


def test_a_change_of_kind_is_written_at_once_but_alternating_kinds_stay_bounded() -> None:
    clock, lines = _Clock(), []
    log = RateLimitedLog(lambda level, msg: lines.append(msg), every=5.0, burst=3, clock=clock)
    log("k", "a 1", kind="a")
    log("k", "a 2", kind="a")
    log("k", "b 1", kind="b")
    assert lines == ["a 1", "b 1 [1 earlier not logged; 3 in all]"]
    for i in range(10_000):  # two reasons alternating at 1 kHz for 10 s
        clock.t = 100.0 + i * 1e-3
        log("k", f"x {i}", kind=i % 2)
    assert len(lines) <= 2 * (3 + 1) + 1, lines
    assert log.total("k") == 10_003
    log("other", "first of another stream", kind="a")  # streams are independent
    assert lines[-1] == "first of another stream"
