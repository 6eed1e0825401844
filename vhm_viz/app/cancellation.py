"""Progress and cancellation of the explorer's long operations (no Qt)."""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["Cancelled", "ProgressFn", "no_progress", "never_cancelled"]

#: ``progress(fraction, message)``: fraction in [0, 1].
ProgressFn = Callable[[float, str], None]


class Cancelled(Exception):
    """Raised inside a long operation when the user cancelled it."""


def no_progress(fraction: float, message: str) -> None:
    """A progress callback that reports nothing."""
    return None


def never_cancelled() -> bool:
    """A ``cancelled()`` callback for work nobody cancels."""
    return False
