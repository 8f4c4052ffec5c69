"""recon/live/status.json: written whole (a temporary file renamed over it), read back with every field checked, one
line for a bad one, and readable without numpy (the daemon-side `spadscan ctl` reads it)."""

from __future__ import annotations

import datetime as dt
import json
import subprocess
import sys

import pytest

from spadscan.protocol.errors import CaptureError
from spadscan.protocol.live_status import LiveStatus, read_status, status_path, write_status


def test_a_status_round_trips_with_the_issue_fields(tmp_path):
    path = write_status(tmp_path, LiveStatus(views_used=12, views_published=14, steps=480, converged=False,
                                             chamfer_mm=2.5, views_planned=64, job="mug-fast"))
    data = json.loads(path.read_text())
    assert {"views_used", "views_published", "steps", "updated_utc", "converged", "chamfer_mm"} <= set(data)
    assert (data["views_used"], data["views_published"], data["steps"], data["chamfer_mm"]) == (12, 14, 480, 2.5)
    assert dt.datetime.fromisoformat(data["updated_utc"]).tzinfo is not None
    back = read_status(path)
    assert back.views_used == 12 and back.state == "live" and back.job == "mug-fast"
    assert [p.name for p in tmp_path.iterdir()] == ["status.json"]  # no temporary file left behind


def test_chamfer_and_the_final_start_are_written_only_when_known(tmp_path):
    data = json.loads(write_status(tmp_path, LiveStatus(views_used=1, views_published=1, steps=0)).read_text())
    assert "chamfer_mm" not in data and "final_start" not in data
    write_status(tmp_path, LiveStatus(views_used=1, views_published=1, steps=0, state="final", final_start="hull"))
    assert read_status(tmp_path / "status.json").final_start == "hull"


def test_warnings_are_written_only_when_there_are_some_and_read_back(tmp_path):
    data = json.loads(write_status(tmp_path, LiveStatus(views_used=1, views_published=1, steps=0)).read_text())
    assert "warnings" not in data
    write_status(tmp_path, LiveStatus(views_used=1, views_published=1, steps=0, warnings=("no preview.png: why",)))
    back = read_status(tmp_path / "status.json")
    assert back.warnings == ("no preview.png: why",) and back.summary().endswith(", no preview.png: why")


def test_a_capture_folder_reads_its_live_status(tmp_path):
    write_status(status_path(tmp_path).parent.mkdir(parents=True) or status_path(tmp_path).parent,
                 LiveStatus(views_used=3, views_published=3, steps=7, state="final"))
    assert read_status(tmp_path).state == "final"


def test_unknown_keys_are_accepted(tmp_path):
    path = tmp_path / "status.json"
    path.write_text(json.dumps({"views_used": 1, "views_published": 2, "steps": 3, "later_key": [1]}))
    assert read_status(path).views_published == 2


@pytest.mark.parametrize("change, says", [
    ({"views_used": -1}, "views_used"), ({"steps": 2.5}, "steps"), ({"converged": "yes"}, "converged"),
    ({"state": "dancing"}, "state"), ({"chamfer_mm": float("nan")}, "chamfer_mm"), ({"note": 3}, "note"),
    ({"final_start": "scratch"}, "final_start"), ({"warnings": "no preview.png"}, "warnings"),
    ({"warnings": [3]}, "warnings"),
])
def test_a_malformed_status_is_one_line_naming_the_field(tmp_path, change, says):
    path = tmp_path / "status.json"
    path.write_text(json.dumps({"views_used": 1, "views_published": 1, "steps": 0, **change}))
    with pytest.raises(CaptureError, match=says) as err:
        read_status(path)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("text", ["", "{", "[1]", '{"views_used": 1}'])
def test_a_torn_or_foreign_file_is_one_line(tmp_path, text):
    path = tmp_path / "status.json"
    path.write_text(text)
    with pytest.raises(CaptureError, match="status"):
        read_status(path)


def test_a_missing_status_says_so(tmp_path):
    with pytest.raises(CaptureError, match="no live status"):
        read_status(tmp_path)


def test_a_status_refuses_to_write_what_it_could_not_read(tmp_path):
    with pytest.raises(CaptureError, match="steps"):
        write_status(tmp_path, LiveStatus(views_used=1, views_published=1, steps=-3))
    assert not (tmp_path / "status.json").exists()


def test_summary_names_views_steps_and_the_last_update():
    now = dt.datetime(2026, 11, 26, 14, 0, 10, tzinfo=dt.timezone.utc)
    status = LiveStatus(views_used=24, views_published=30, steps=900, converged=True, chamfer_mm=1.234,
                        views_planned=64, updated_utc="2026-11-26T14:00:07.000+00:00")
    assert status.summary(now) == ("live reconstruction following the scan: 24/30 views of 64 planned, 900 steps, "
                                   "converged, Chamfer 1.23 mm, updated 3 s ago")


def test_reading_a_status_loads_no_numpy(tmp_path):
    write_status(tmp_path, LiveStatus(views_used=1, views_published=1, steps=0))
    code = ("import sys; from spadscan.protocol.live_status import read_status; "
            f"read_status({str(tmp_path / 'status.json')!r}); print('numpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
