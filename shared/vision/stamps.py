"""Time stamps as TUM files write them (no OpenCV here: `splittag watch` in a light install uses it)."""

from __future__ import annotations


def format_stamp_nanos(nanos: int) -> str:
    """A stamp in nanoseconds (>= 0, as parse_stamp_nanos reads them) as exact decimal seconds."""
    secs, frac = divmod(nanos, 1_000_000_000)
    return f"{secs}.{frac:09d}"
