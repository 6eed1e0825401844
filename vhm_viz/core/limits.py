"""The documented range of every numeric setting, and the one check that enforces it.

Scenes, the :class:`~vhm_viz.core.deformer.Deformer`, bindings, the filters and the command
line all validate their settings here, so a value is refused the same way wherever it
comes from: with a :class:`~vhm_viz.core.errors.SettingError` that names the field and its
range (``solver.max_iterations must be an integer in [1, 1000000]; got 1e+12``).

The ranges (:data:`RANGES`) are wide enough for every real use and narrow enough that a
value inside them cannot exhaust memory, hang, or make the numbers meaningless:

==================  ==========================  ===============================================
setting             range                       why the bounds
==================  ==========================  ===============================================
``alpha``           [1e-4, 100]                 below, the smoothness term cannot regularise the
                                                least squares (E_rigid of the bar > 0.3, then
                                                garbage); above, the map is as stiff as it gets
``max_iterations``  integer [1, 1,000,000]      the solver keeps a history of every iterate
                                                (32 bytes each); plain iteration needs ~20,000
``tolerance``       (0, 0.1]                    a distance of local matrices to the fixed point
                                                (dimensionless); 0.1 is already 6 degrees
``steps``           integer [1, 1000]           each step is a full solve
``anderson_window`` integer [0, 100]            cost per iteration grows with its square
``memory_budget``   integer [1, 2**40] bytes    per chunk of basis evaluation
``chunk_size``      integer [1, 10,000,000]     points per chunk of the numpy reference basis
``anchor_count``    integer [1, 10,000]         anchors (automatic or along rigidity lines);
                                                the solver's matrices grow with their square
                                                (10,000 anchors: about 14 GB)
``contraction``     [0, 1)                      a contraction rate
``resolution``      integer [1, 200]            cells per unit length of the bundled bar
==================  ==========================  ===============================================
"""

from __future__ import annotations

import math
import numbers
from typing import NamedTuple

from vhm_viz.core.errors import SettingError

__all__ = ["RANGES", "Range", "check_integer_at_least", "check_setting"]


class Range(NamedTuple):
    """Closed (or half-open) interval of a setting."""

    low: float
    high: float
    integer: bool = False
    low_open: bool = False
    high_open: bool = False

    def describe(self) -> str:
        """``[1, 1000000]``, ``(0, 0.1]``, ..."""
        lo = "(" if self.low_open else "["
        hi = ")" if self.high_open else "]"
        kind = "an integer" if self.integer else "a number"
        return f"{kind} in {lo}{_fmt(self.low)}, {_fmt(self.high)}{hi}"

    def contains(self, value: float) -> bool:
        """Whether ``value`` lies in the interval."""
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below


def _fmt(x: float) -> str:
    if float(x).is_integer() and abs(x) < 1e16:
        return str(int(x))
    return f"{x:g}"


#: Every numeric setting's range (see the module documentation for the reasons).
RANGES: dict[str, Range] = {
    "alpha": Range(1e-4, 100.0),
    "max_iterations": Range(1, 1_000_000, integer=True),
    "tolerance": Range(0.0, 0.1, low_open=True),
    "steps": Range(1, 1000, integer=True),
    "anderson_window": Range(0, 100, integer=True),
    "memory_budget": Range(1, 2**40, integer=True),
    "chunk_size": Range(1, 10_000_000, integer=True),
    "anchor_count": Range(1, 10_000, integer=True),
    "contraction": Range(0.0, 1.0, high_open=True),
    "resolution": Range(1, 200, integer=True),
}


def check_setting(kind: str, value, field: str | None = None):
    """Return ``value`` (an ``int`` or ``float``) if it is in the range of ``kind``.

    Parameters
    ----------
    kind : str
        A key of :data:`RANGES`.
    value : object
        The value given. Booleans and strings are refused; an integral float is accepted
        for an integer setting (JSON writes ``1e3`` as a float).
    field : str, optional
        The name to report (``solver.max_iterations``); default ``kind``.

    Returns
    -------
    int or float

    Raises
    ------
    SettingError
        Wrong type or out of range; the message names ``field`` and the range.
    """
    rng = RANGES[kind]
    return _checked(field or kind, value, rng, rng.describe())


def check_integer_at_least(field: str, value, low: int, why: str = "") -> int:
    """Return ``value`` as an ``int`` if it is an integer of at least ``low``.

    For the settings bounded below only, such as a grid's resolution or a face budget,
    whose upper limit is the memory at hand. As :func:`check_setting`: booleans and
    strings are refused, an integral float is accepted.

    Raises
    ------
    SettingError
        Not an integer, or below ``low``; the message names ``field``, ``low`` and ``why``.
    """
    return _checked(field, value, Range(low, math.inf, integer=True),
                    f"an integer of at least {low}{why}")  # fmt: skip


def _checked(name: str, value, rng: Range, must: str):
    """``value`` as an ``int`` or ``float`` if it is a number in ``rng``, else the error.

    Booleans and strings are refused; an integral float is accepted for an integer range
    (JSON writes ``1e3`` as a float). ``must`` says what it must be, for the message.
    """
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if ok:
        number = float(value)
        ok = math.isfinite(number) and (not rng.integer or number.is_integer())
        ok = ok and rng.contains(number)
    if not ok:
        shown = repr(value) if not isinstance(value, float) else f"{value:g}"
        raise SettingError(name, f"must be {must}; got {shown[:40]}")
    return int(value) if rng.integer else float(value)
