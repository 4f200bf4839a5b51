"""The viewer's live plot: the last N seconds of commanded (``mds-state`` ``ref``) vs measured (``pos``) for the
joints the user chooses, in a panel of the viewer's page (issue 30).

Why it cannot slow the 3-D view: :meth:`LivePlot.add` only stores the new frame's values in a fixed ring (a few
array writes per joint, on the viewer's own tick, for each state frame it applies: the plot follows the state rate),
and :meth:`LivePlot.refresh` sends the chart at most ``MAX_SEND_HZ`` times a second and only when a sample arrived,
at most ``MAX_POINTS`` points per series (older points thinned out), so a 1 kHz daemon costs the page what a 10 Hz
one does. The chart is viser's uPlot element (drawn by the browser).

Imports: numpy; the GUI object is the viewer's viser server's ``gui`` (duck-typed: no viser import here).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from mds_ach.robot.joints import lookup

DEFAULT_JOINTS = ("LSP", "LEP")
DEFAULT_WINDOW_S = 10.0
WINDOW_RANGE_S = (2.0, 120.0)
CAPACITY = 4096
"""Samples kept (per joint): 120 s at 34 Hz, 4 s at 1 kHz; older ones drop off the ring."""
MAX_POINTS = 600
"""Points per series sent to the page at most (thinned evenly)."""
MAX_SEND_HZ = 20.0
MAX_JOINTS = 4
COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd")


def parse_joints(text: str) -> tuple[list[str], str]:
    """``"LSP, lep"`` -> (["LSP", "LEP"], problem text or ""): unknown names are left out and named."""
    names: list[str] = []
    bad: list[str] = []
    for word in text.replace(",", " ").split():
        try:
            short = lookup(word).short
        except KeyError:
            bad.append(word)
            continue
        if short not in names:
            names.append(short)
    problem = f"unknown joint(s): {', '.join(bad)}" if bad else ""
    if len(names) > MAX_JOINTS:
        problem = (problem + "; " if problem else "") + f"at most {MAX_JOINTS} joints: the first are shown"
        names = names[:MAX_JOINTS]
    return names, problem


class LivePlot:
    """Ring of (time, ref, pos) per joint for every state frame; a uPlot chart of the last ``window`` s."""

    def __init__(self, gui: Any, joints: Sequence[str] = DEFAULT_JOINTS, window: float = DEFAULT_WINDOW_S) -> None:
        self.gui = gui
        self.window = window
        self.t = np.full(CAPACITY, math.nan)
        self.ref = np.full((MAX_JOINTS, CAPACITY), math.nan)
        self.pos = np.full((MAX_JOINTS, CAPACITY), math.nan)
        self.n = 0  # samples written since the start (the ring index is n % CAPACITY)
        self.sent_at = -math.inf
        self.sent_n = 0
        self.sends = 0  # charts sent to the page (tests, bench)
        self.joints, _ = parse_joints(" ".join(joints))
        self.addresses = [lookup(j).address for j in self.joints]
        with gui.add_folder("Live plot", expand_by_default=False):
            self.enabled = gui.add_checkbox("Plot", True, hint="commanded (ref) vs measured (pos), newest at 0 s")
            self.joint_text = gui.add_text("Joints", ", ".join(self.joints),
                                           hint=f"short names, at most {MAX_JOINTS}, e.g. LSP, LEP")
            self.window_slider = gui.add_slider("Seconds", min=WINDOW_RANGE_S[0], max=WINDOW_RANGE_S[1], step=1.0,
                                                initial_value=window)
            self.note = gui.add_markdown("")
            self.chart = gui.add_uplot(data=self._data(0.0), series=self._series(), title="ref vs pos (rad)",
                                       scales={"x": {"time": False}}, aspect=1.4)
        self.joint_text.on_update(lambda _: self.choose(self.joint_text.value))
        self.window_slider.on_update(lambda _: self._set_window(float(self.window_slider.value)))

    def _set_window(self, seconds: float) -> None:
        self.window = min(max(seconds, WINDOW_RANGE_S[0]), WINDOW_RANGE_S[1])
        self.sent_n = -1  # redraw at the next refresh

    def choose(self, text: str) -> None:
        """New joints (from the panel's text field): the ring starts over for them."""
        names, problem = parse_joints(text)
        self.note.content = problem
        if not names or names == self.joints:
            return
        self.joints, self.addresses = names, [lookup(j).address for j in names]
        self.ref[:] = math.nan
        self.pos[:] = math.nan
        self.chart.series = self._series()
        self.sent_n = -1

    def _series(self) -> tuple[dict[str, Any], ...]:
        out: list[dict[str, Any]] = [{"label": "t (s)"}]
        for k, j in enumerate(self.joints):
            out.append({"label": f"{j} ref", "stroke": COLOURS[k], "dash": [6, 4], "width": 1.5})
            out.append({"label": f"{j} pos", "stroke": COLOURS[k], "width": 2})
        return tuple(out)

    def add(self, t: float, state: Any) -> None:
        """One mds-state frame at monotonic time ``t``: the chosen joints' ``ref`` and ``pos``."""
        i = self.n % CAPACITY
        self.t[i] = t
        joints = state.joint
        for k, a in enumerate(self.addresses):
            self.ref[k, i] = joints[a].ref
            self.pos[k, i] = joints[a].pos
        self.n += 1

    def window_data(self, now: float) -> tuple[np.ndarray, ...]:
        """(t - now, ref_0, pos_0, ref_1, ...) of the samples of the last ``window`` s, oldest first, thinned to
        at most MAX_POINTS."""
        return self._data(now)

    def _data(self, now: float) -> tuple[np.ndarray, ...]:
        count = min(self.n, CAPACITY)
        order = (np.arange(self.n - count, self.n) % CAPACITY) if count else np.zeros(0, dtype=int)
        t = self.t[order]
        keep = order[t >= now - self.window] if count else order
        if len(keep) > MAX_POINTS:
            keep = keep[np.linspace(0, len(keep) - 1, MAX_POINTS).round().astype(int)]
        cols: list[np.ndarray] = [self.t[keep] - now]
        for k in range(len(self.joints)):
            cols += [self.ref[k, keep], self.pos[k, keep]]
        return tuple(np.ascontiguousarray(c, dtype=np.float64) for c in cols)

    def refresh(self, now: float) -> bool:
        """Send the chart if a sample arrived (or the view changed) and the last send is 1/MAX_SEND_HZ s old."""
        if not self.enabled.value or self.n == self.sent_n or now - self.sent_at < 1.0 / MAX_SEND_HZ:
            return False
        self.chart.data = self._data(now)
        self.sent_at, self.sent_n = now, self.n
        self.sends += 1
        return True
