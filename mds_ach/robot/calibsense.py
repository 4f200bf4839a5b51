"""Bounds of sense for a joint's calibration numbers: one definition for both readers, the original's XML
(:mod:`mds_ach.robot.anatomy`) and the project's YAML (:mod:`mds_ach.robot.config`).

Why: these numbers become the joint's range and its rad <-> count conversion (``cpr = resolution * gear_ratio *
ticks_per_count``, range ``+-rom/2 * (1 - rom_margin)`` counts about the ROM middle). A hand-edited file with a
margin of 100 % (the range collapses to a point), 150 % (the range turns inside out), a gear ratio of 1e-300 (a
joint "range" of 1e300 rad) or a typo in a unit loads without a word, and every stage above trusts it. So each
number is checked against what it can physically be, and a file with one that cannot is refused, naming the
file, the line and the field (the readers add those; here only the field and why).

The bounds (docs/operator.md *Calibration files*):

* ``rom_margin``, ``safety_margin``: 0 ... 50 % (the original's fingers use 50 %);
* ``resolution``, ``ticks_per_count``: whole numbers >= 1 (encoder lines, quadrature ticks);
* ``gear_ratio``: >= 1 (a reduction: the motor turns that many times per joint turn);
* counts per joint revolution (their product) <= 2^24: a MOVETO target is a float32, exact in whole counts to 2^24;
* ``rom``: >= 1 count and at most one joint revolution (``rom <= cpr``, a travel of <= 2 pi rad);
* ``offset``: |offset| <= 2 pi rad (a motor offset beyond one turn is a wrong unit, e.g. degrees);
* homing numbers (acceleration, velocity, error, buffer, timeout): >= 0.

Every value is finite already (the readers refuse NaN and Inf). Imports: nothing of the project.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

MAX_MARGIN = 0.5
MAX_COUNTS = float(2**24)  # float32 carries whole numbers exactly up to here
ONE_TURN = 2.0 * math.pi
HOMING = ("acceleration", "velocity", "error", "buffer", "timeout")

# The canonical field names (the YAML's); the XML reader maps its parameter names onto these.
RESOLUTION, GEAR_RATIO, TICKS = "encoder.resolution", "encoder.gear_ratio", "encoder.ticks_per_count"
ROM, ROM_MARGIN, SAFETY_MARGIN, OFFSET = "rom", "rom_margin", "safety_margin", "offset"


def _margin(v: float) -> str | None:
    if 0.0 <= v <= MAX_MARGIN:
        return None
    return f"{v:g} ({v * 100:g} %) is not a margin: it must be between 0 and {MAX_MARGIN:g} (0 to 50 %)"


def _whole(v: float) -> str | None:
    return None if v >= 1.0 and v.is_integer() else f"{v:g} is not a whole number >= 1"


def _gear(v: float) -> str | None:
    return None if v >= 1.0 else f"{v:g} is not a reduction gear ratio (>= 1)"


def _offset(v: float) -> str | None:
    return None if abs(v) <= ONE_TURN else f"{v:g} rad is more than one turn (|offset| <= 2 pi); radians?"


def _not_negative(v: float) -> str | None:
    return None if v >= 0.0 else f"{v:g} is negative"


RULES = {RESOLUTION: _whole, TICKS: _whole, GEAR_RATIO: _gear, ROM_MARGIN: _margin, SAFETY_MARGIN: _margin,
         OFFSET: _offset, **{f"homing.{k}": _not_negative for k in HOMING}}


def problem(values: Mapping[str, float | None]) -> tuple[str, str] | None:
    """The first field of one joint's numbers (canonical names, see ``RULES``; None or absent = not given) that
    makes no sense, and why; None when every given one does."""
    for key, rule in RULES.items():
        v = values.get(key)
        why = None if v is None else rule(v)
        if why is not None:
            return key, why
    res, gear, ticks, rom = (values.get(k) for k in (RESOLUTION, GEAR_RATIO, TICKS, ROM))
    if res is None or gear is None or ticks is None:
        return None
    cpr = res * gear * ticks
    product = f"{res:g} x gear_ratio {gear:g} x ticks_per_count {ticks:g}"
    if cpr > MAX_COUNTS:
        return GEAR_RATIO, (f"{cpr:g} counts per revolution (resolution {product}) is more than a float32 MOVETO "
                            f"target carries in whole counts (2^24)")
    if rom is not None and not 1.0 <= rom <= cpr:
        return ROM, (f"{rom:g} counts is not a range of motion between 1 count and one revolution ({cpr:g} counts: "
                     f"resolution {product})")
    return None


def empty_range(lower: float, upper: float) -> str | None:
    """Why a derived joint range is unusable (empty or inverted), or None."""
    return None if lower < upper else f"empty or inverted joint range [{lower:g}, {upper:g}] rad"
