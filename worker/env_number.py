"""A whole number read from an environment variable, one rule for every variable a worker or job reads."""

from __future__ import annotations

MAX_DIGITS = 12  # more is no count of threads or processes; and int() of thousands of digits is slow, then refused


def whole_number(raw: str, least: int, most: int) -> int | None:
    """`raw` (an environment variable's value) as a whole number in [least, most], or None where it is not one.
    Spaces and line ends around it are allowed; ASCII digits only: int() also takes signs, underscores and other
    scripts' digits, which no program or person setting these variables means."""
    text = raw.strip()
    if not (text.isascii() and text.isdigit() and len(text) <= MAX_DIGITS):
        return None
    value = int(text)
    return value if least <= value <= most else None


__all__ = ["whole_number"]
