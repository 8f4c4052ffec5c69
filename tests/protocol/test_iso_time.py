"""The one reader of the project's ISO 8601 UTC stamps: an aware time, UTC where a stamp names no zone, None for
anything that is no such time."""

from __future__ import annotations

import datetime as dt

import pytest

from spadscan.protocol.iso_time import parse_utc
from spadscan.protocol.live_status import LiveStatus

UTC = dt.timezone.utc


@pytest.mark.parametrize("text, then", [
    ("2026-11-26T14:15:52.975+00:00", dt.datetime(2026, 11, 26, 14, 15, 52, 975000, tzinfo=UTC)),
    ("2026-11-26T15:15:52+01:00", dt.datetime(2026, 11, 26, 14, 15, 52, tzinfo=UTC)),
    ("2026-11-26T14:15:52Z", dt.datetime(2026, 11, 26, 14, 15, 52, tzinfo=UTC)),
    ("2026-11-26T14:15:52", dt.datetime(2026, 11, 26, 14, 15, 52, tzinfo=UTC)),  # no zone: the project's UTC
])
def test_a_stamp_reads_as_an_aware_time_and_one_without_a_zone_as_utc(text, then):
    got = parse_utc(text)
    assert got == then and got.tzinfo is not None


@pytest.mark.parametrize("text", ["", "yesterday", "2026-13-01T00:00:00+00:00", None, 1795701607.0, ["2026"]])
def test_what_is_no_time_reads_as_none(text):
    assert parse_utc(text) is None


def test_a_live_status_reads_its_time_as_the_stamps_reader_does():
    now = dt.datetime(2026, 11, 26, 14, 0, 10, tzinfo=UTC)
    naive = LiveStatus(views_used=1, views_published=1, steps=0, updated_utc="2026-11-26T14:00:07")
    assert naive.updated() == parse_utc("2026-11-26T14:00:07") and naive.age_s(now) == 3.0
    bad = LiveStatus(views_used=1, views_published=1, steps=0, updated_utc="soon")
    assert bad.updated() is None and bad.age_s(now) is None
