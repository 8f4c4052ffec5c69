"""`find_interrupted`: which scan folders a restarted daemon takes over: only its own captures that say 'running'
(not complete, aborted, or aborted with the record still pending), the one updated last first."""

from __future__ import annotations

import json

from spadscan.daemon.scan_job import ABORT_PENDING, WRITER, find_interrupted


def scan(root, name, state, updated, writer=WRITER):
    folder = root / name
    folder.mkdir()
    manifest = {"state": state, "updated_utc": updated, "rig": {"writer": writer}}
    (folder / "scan.json").write_text(json.dumps(manifest))
    return folder


def test_only_the_daemon_s_running_scans_are_taken_over_newest_first(tmp_path, caplog):
    older = scan(tmp_path, "older", "running", "2026-01-01T10:00:00Z")
    newer = scan(tmp_path, "newer", "running", "2026-01-02T10:00:00Z")
    scan(tmp_path, "done", "complete", "2026-01-03T10:00:00Z")
    scan(tmp_path, "ended", "aborted", "2026-01-03T10:00:00Z")
    scan(tmp_path, "imported", "running", "2026-01-03T10:00:00Z", writer="spadscan-import")
    pending = scan(tmp_path, "pending", "running", "2026-01-03T10:00:00Z")
    (pending / ABORT_PENDING).write_text("{}")
    scan(tmp_path, ".hidden", "running", "2026-01-03T10:00:00Z")
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "scan.json").write_text("{not json")
    assert find_interrupted(tmp_path) == [newer, older]
    assert "not taking over" in caplog.text and "imported" in caplog.text


def test_a_missing_root_has_nothing_to_take_over(tmp_path):
    assert find_interrupted(tmp_path / "nowhere") == []
