"""Reading and writing the times the project writes: ISO 8601 stamps in UTC (`2026-11-26T14:15:52.975+00:00`, as
`datetime.isoformat` writes them) in its files and records. Standard library only: the daemon-side client reads them
without loading numpy."""

from __future__ import annotations

import datetime as _dt


def parse_utc(text) -> _dt.datetime | None:
    """`text`, an ISO 8601 time, as an aware time; one that names no zone is read as UTC (every stamp the project
    writes is UTC); None when it is no such time (not a string, empty, malformed): a reader shows it as unknown
    rather than stopping on it."""
    if not isinstance(text, str):
        return None
    try:
        then = _dt.datetime.fromisoformat(text)
    except ValueError:
        return None
    return then if then.tzinfo else then.replace(tzinfo=_dt.timezone.utc)


def utc_now() -> str:
    """Now, as the project writes a time: ISO 8601 in UTC, to the millisecond (`2026-11-26T14:15:52.975+00:00`)."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="milliseconds")


__all__ = ["parse_utc", "utc_now"]
