"""What an operator reads on the dashboard while scans run, in a real headless browser: at phone or half-screen width
the daemon's state, the worker's and the 3D view stay readable; a finished result's warnings are counted, open in
full, and the serious ones stand out; a live fit behind the scan says so and how old it is; the scan in hand says how
long it has run and how long it has left; a live job waiting in the queue, or a worker that does not reconstruct live,
is said as such; a live fit whose worker is gone says it stopped; figures say what they are and in what unit; a
captures root not made yet is waited for; an empty root, a dashboard that stops answering, the daemon's own config
and a scan recorded with no worker running are said."""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import subprocess
import sys
import time
from types import SimpleNamespace

import numpy as np
import trimesh

from dashboard_helpers import complete_scan, serving, status
from page_helpers import add_pose, browser_page, start_scan
from spadscan.commands.dashboard import daemon_running
from spadscan.daemon.root_lock import RootLock
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.dashboard.server import address
from spadscan.dashboard.worker_state import LOOK_S
from spadscan.worker.ambient_light import Ambient, ambient_warning
from spadscan.worker.carving.bounds import BelowFloor, floor_cut_note
from spadscan.worker.end_of_run import (coverage_warning, dark_warning, lost_warning, misfit_warning, pieces_warning,
                                        saturation_warning, specks_warning, tunnels_warning)
from spadscan.worker.lost_returns import LostReturns
from spadscan.worker.recon.scene_data import bound_warning
from spadscan.worker.floor_gap import FloorGap, gap_warning
from spadscan.worker.top_reach import TopReach, top_warning
from spadscan.worker.view_spread import (above_only_warning, far_views_warning, low_only_warning, one_ring_warning,
                                         small_object_warning)
from spadscan.worker.holder import Holder
from spadscan.worker.job_progress import claim_log
from spadscan.worker.jobs import Job
from spadscan.worker.presence import Presence, write_presence
from spadscan.worker.queue import Queue

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
BAR = "reconstruct (fast):  60%|######    | 6/10 s [00:06<00:04, loss=27.3, step=72]\r"

# True where every rect of the element shows: the element itself is what the window shows at each rect's centre
# (not clipped by a box that hides its overflow, nor beyond the window's edge); a line's empty end is no rect of text
SEEN = """(s) => { const e = document.querySelector(s);
  const rects = [...e.getClientRects()].filter(r => r.width > 0 && r.height > 0);
  return rects.length > 0 && rects.every(r => r.right <= innerWidth + 0.5 && r.left >= -0.5 &&
    e.contains(document.elementFromPoint((r.left + r.right) / 2, (r.top + r.bottom) / 2))); }"""
BOX = """(s) => { const b = document.querySelector(s).getBoundingClientRect();
  return [b.left, b.top, b.width, b.height]; }"""


def wait_text(page, selector: str, text: str) -> str:
    page.wait_for_function("([s, t]) => (document.querySelector(s) || {}).textContent?.includes(t)",
                           arg=[selector, text], timeout=WAIT_MS)
    return page.locator(selector).text_content()


def running_job(root, job_id: str, log_text: str = BAR, holder: Holder | None = None) -> None:
    queue = Queue.for_root(root)
    queue.enqueue(Job(id=job_id, scan=job_id.rsplit("-", 1)[0], live=True))
    claim = queue.claim(holder or Holder.current())
    assert claim is not None and claim.job.id == job_id
    log = claim_log(queue.path, queue.job_paths()[job_id][1])
    log.parent.mkdir(parents=True, exist_ok=True)
    log.write_text(log_text)


def worker_present(root, processes: int = 1) -> None:
    """A worker (this process) serving `root`, as its presence file says."""
    write_presence(Queue.for_root(root).path, Presence(Holder.current().to_dict(), str(root), time.time(), processes))


def live_status(scan, **fields) -> None:
    live = scan / "recon" / "live"
    live.mkdir(parents=True, exist_ok=True)
    (live / "status.json").write_text(json.dumps(fields))


def recording(path, poses: int, planned: int = 40):
    """A scan being recorded: `poses` of `planned` published, one a half second (120 poses a minute)."""
    writer, planned_poses = start_scan(path, planned)
    for i in range(poses):
        add_pose(writer, planned_poses, i, t_s=10.0 + 0.5 * i)
    return writer


def started_ago(scan, seconds: float) -> None:
    """The scan began `seconds` ago, as its scan.json says."""
    manifest = json.loads((scan / "scan.json").read_text())
    then = _dt.datetime.now(_dt.timezone.utc) - _dt.timedelta(seconds=seconds)
    manifest["created_utc"] = then.isoformat(timespec="milliseconds")
    (scan / "scan.json").write_text(json.dumps(manifest))


def test_at_phone_and_half_screen_width_the_state_and_the_3d_view_are_read_and_nothing_scrolls_sideways(tmp_path):
    from spadscan.worker.report.view3d import view3d_html

    complete_scan(tmp_path / "mug", 2)
    final = tmp_path / "mug" / "recon" / "mug-fast"
    final.mkdir(parents=True)
    (final / "report.json").write_text(json.dumps({"preset": "fast", "chamfer_mm": 2.5}))
    # the report's viewer page, as the worker writes it, made where no off-screen OpenGL is (the layout is the point)
    view = view3d_html(trimesh.creation.icosphere(subdivisions=2, radius=0.05), title="mug (fast)")
    (final / "view3d.html").write_text(view, encoding="utf-8")
    for width in (400, 960):
        with serving(tmp_path, daemon_running=daemon_running) as server, browser_page(width, 800) as (page, seen):
            page.goto(address(server))
            wait_text(page, "#daemon", "no daemon running")
            assert page.evaluate(SEEN, "#daemon"), f"the daemon's state is cut off at {width} px"
            assert page.evaluate(SEEN, "#worker"), f"the worker's state is cut off at {width} px"
            page.locator('#scans tr[data-scan="mug"] a.pick').first.click()
            page.locator("#viewer-3d:not([hidden])").wait_for(timeout=WAIT_MS)
            assert page.evaluate("() => document.documentElement.scrollWidth") <= width
            view, hist, card = (page.evaluate(BOX, s) for s in ("#viewer-3d", "#hist", "#current"))
            assert hist[2] <= card[2], "the histograms overflow their card"
            if width == 400:  # one column: the 3D view below the scan in hand, the window's width
                assert view[1] > card[1] + card[3] and view[2] >= 300, view
        assert not seen.errors, seen.errors


def end_of_run_warnings() -> tuple[list[str], list[str]]:
    """(the warnings of a run, as the worker words them; which of them are serious)"""
    serious = [misfit_warning(SimpleNamespace(relative_misfit=0.9), measured=True),
               pieces_warning(SimpleNamespace(count=9, share_apart=0.12)),
               specks_warning(SimpleNamespace(specks=63, specks_share=0.05)),
               tunnels_warning(SimpleNamespace(tunnels=37), 0),
               coverage_warning(SimpleNamespace(share_few=0.3, few_heights_m=(0.1, 0.2), few_views=3)),
               saturation_warning(SimpleNamespace(saturated=True, saturated_histograms=30, histograms=32)),
               lost_warning(LostReturns(returns=200, lost=176, heights_m=(0.1, 0.2))),
               bound_warning(0.2, 0.16, 0.6),
               floor_cut_note(0.0, "the default floor", BelowFloor(5, 48, 0.055), None, "give another floor"),
               dark_warning({"restarted_at_step": 200, "albedo": 0.15}),
               above_only_warning(48.0, 80.0, 64), one_ring_warning(30.0, 31.0, 32), low_only_warning(-1.0, 23.0, 128),
               far_views_warning(sensor_preset("lcspc-sim"), np.full(64, 0.74)),
               small_object_warning(sensor_preset("lcspc-sim"), np.full(64, 0.45), 0.03),
               ambient_warning(Ambient(background=3e-3, background_photons=15.0, return_bin=336, stopped_share=0.64,
                                       returns=256)),
               top_warning(TopReach(top_z=0.18, vertices=400, unseen=390, width_m=0.12)),
               gap_warning(FloorGap(floor_z=0.0, bottom_z=0.047, source="config"))]
    assert all(serious), serious  # (each made to say so)
    mild = ["the run stopped on its time budget well before convergence: its data term was still falling (4.8 % over "
            "the last fifth of its 150 steps; a larger --budget-s gives a better mesh)",
            "the machine was busy: this run had 0.41 of a CPU core on average and made about 2x fewer steps (150) "
            "than it would alone; stop other work or give it a larger time budget"]
    return [mild[0], *serious, mild[1]], serious


def test_a_results_warnings_are_counted_opened_in_full_from_their_count_and_the_serious_ones_stand_out(tmp_path):
    warnings, serious = end_of_run_warnings()
    complete_scan(tmp_path / "nowk", 2)
    result = tmp_path / "nowk" / "recon" / "nowk-fast"
    result.mkdir(parents=True)
    (result / "report.json").write_text(json.dumps({"preset": "fast", "chamfer_mm": 6.09, "converged": False,
                                                    "warnings": warnings}))
    with serving(tmp_path) as server, browser_page(1280, 700) as (page, seen):
        (recon,) = status(server)["scans"][0]["recons"]
        assert recon["summary"]["warning_levels"] == ["serious" if w in serious else "mild" for w in warnings]
        page.goto(address(server))
        head = wait_text(page, "#viewer-notes .warnings-head", "warnings")
        # the lines listed, report.json's alone (its "stopped ... before convergence" says it did not converge): as
        # many as the scans table counts
        assert head.startswith(f"{len(warnings)} warnings, {len(serious)} of them serious"), head
        closed = page.locator("#viewer-notes .warning").first  # the serious first: the closed box shows them
        assert "serious" in closed.get_attribute("class") and page.evaluate(SEEN, "#viewer-notes .warning.serious")
        assert page.evaluate(SEEN, "#viewer-notes .warnings-head"), "the count is out of sight"
        count = page.locator('#scans tr[data-scan="nowk"] a[data-warnings]')
        assert "serious" in count.get_attribute("class")  # the scans table's count stands out too
        count.click()  # the count leads to them, opened in full
        page.wait_for_function("() => document.querySelector('#viewer-notes').classList.contains('open')",
                               timeout=WAIT_MS)
        lines = page.locator("#viewer-notes .warning")
        mild = [w for w in warnings if w not in serious]
        assert lines.all_text_contents() == [*serious, *mild]
        assert count.get_attribute("data-warnings") == str(len(warnings))
        for i in range(lines.count()):  # each in full: not cut by its box, nor by the notes' box
            assert lines.nth(i).evaluate("e => e.scrollWidth <= e.clientWidth && e.scrollHeight <= e.clientHeight + 1")
        notes = page.locator("#viewer-notes")
        assert notes.evaluate("e => e.scrollHeight <= e.clientHeight + 1"), "the open box still hides some"
        grave = page.locator("#viewer-notes .warning.serious")
        assert grave.all_text_contents() == serious
        colour = "e => getComputedStyle(e).backgroundColor"
        assert grave.first.evaluate(colour) != page.locator("#viewer-notes .warning.mild").first.evaluate(colour)
        page.locator("#warnings-toggle").click()  # and closed again: the panel as it was
        assert not notes.evaluate("e => e.classList.contains('open')")
    assert not seen.errors, seen.errors


def test_a_live_fit_behind_the_scan_says_of_how_many_views_and_how_old_it_is(tmp_path):
    scan = tmp_path / "live1"
    recording(scan, 21)
    then = _dt.datetime.now(_dt.timezone.utc) - _dt.timedelta(seconds=12)
    live_status(scan, views_used=8, views_published=8, steps=0, chamfer_mm=50.1, state="live", job="live1-fast",
                updated_utc=then.isoformat())
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        heading = wait_text(page, "#viewer-name", "live")
        assert heading.startswith("live1 / live, following the scan (fit of 8 of 21 views, 0 steps)"), heading
        assert re.search(r", updated \d+ s ago$", heading), heading  # however young: the age is always said
    assert not seen.errors, seen.errors


def test_the_scan_in_hand_says_how_long_it_has_run_and_its_time_left(tmp_path):
    scan = tmp_path / "s1"
    recording(scan, 10)  # 10 of 40 poses at 120 a minute: 15 s left at the last pose
    started_ago(scan, 75)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        assert status(server)["current"]["eta_s"] == 15.0
        page.goto(address(server))
        said = wait_text(page, "#current-time", "running for")
        assert re.fullmatch(r"running for 1:(1[5-9]|[2-5]\d), about \d+ s left", said), said
        assert re.fullmatch(r"\d+ s ago", page.locator("#current-updated").text_content())
        assert re.fullmatch(r"\d+ s ago", page.locator('#scans tr[data-scan="s1"] td').nth(3).text_content())
        # the estimate is the server's at the last pose, counted down while the next pose can come at the scan's
        # pace; well past that the pose is late: the scan is not said to end in seconds (it counted down to "its
        # end due" with 30 poses still to take)
        for chunk in scan.glob("chunk-*"):  # every pose published 40 s earlier than it was: none since
            then = chunk.stat().st_mtime - 40.0
            os.utime(chunk, (then, then))
        manifest = json.loads((scan / "scan.json").read_text())
        manifest["updated_utc"] = (_dt.datetime.now(_dt.timezone.utc) - _dt.timedelta(seconds=40)).isoformat()
        (scan / "scan.json").write_text(json.dumps(manifest))
        said = wait_text(page, "#current-time", "late")
        assert re.fullmatch(r"running for 1:(1[5-9]|[2-5]\d), its next pose late \(the last came 4\d s ago; 15 s left "
                            r"at its pace then\)", said), said
        # a scan that stands still was started, not running, for however long it stands
        manifest["paused"] = {"reason": "paused by user"}
        (scan / "scan.json").write_text(json.dumps(manifest))
        said = wait_text(page, "#current-time", "started")
        assert re.fullmatch(r"started \d+ s ago \(paused\)", said), said
    assert not seen.errors, seen.errors


def test_a_live_job_waiting_in_the_queue_and_a_worker_that_does_not_reconstruct_live_are_said(tmp_path):
    complete_scan(tmp_path / "q1", 2)
    running_job(tmp_path, "q1-fast")  # the worker's one process at q1's final run
    recording(tmp_path / "q2", 3)
    Queue.for_root(tmp_path).enqueue(Job(id="q2-fast", scan="q2", live=True))
    worker_present(tmp_path)
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        assert wait_text(page, "#viewer-name", "queued") == (
            "q2 / live reconstruction queued: waiting for q1-fast to finish (the worker runs 1 job at a time; "
            "`--processes 2` runs 2)")
    unfollowed = tmp_path / "other"
    recording(unfollowed / "s3", 3)
    started_ago(unfollowed / "s3", 3 * LOOK_S)  # a live worker would have queued it at its first pose
    worker_present(unfollowed)
    with serving(unfollowed) as server, browser_page() as (page, seen_too):
        page.goto(address(server))
        assert wait_text(page, "#viewer-name", "live") == (
            "s3 / no live reconstruction: the worker does not reconstruct live (`--live` not given); it "
            "reconstructs the scan once complete")
    assert not seen.errors + seen_too.errors


def test_a_live_fit_whose_worker_is_gone_says_it_stopped_with_the_command_that_brings_one_back(tmp_path):
    recording(tmp_path / "k1", 12)
    live_status(tmp_path / "k1", views_used=8, views_published=8, steps=40, chamfer_mm=47.94, state="live",
                job="k1-fast")
    ended = subprocess.Popen([sys.executable, "-c", "pass"])
    ended.wait()  # its pid names no process: the job's worker is gone
    running_job(tmp_path, "k1-fast", "", holder=Holder(**{**Holder.current().to_dict(), "pid": ended.pid,
                                                           "pid_start": ""}))
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        heading = wait_text(page, "#viewer-name", "gone")
        assert heading.startswith(f"k1 / live fit stopped at 8 views of 12 (its worker is gone: start one with "
                                  f"`spadscan worker --root {tmp_path.resolve()}`)"), heading
        assert "following" not in heading
    assert not seen.errors, seen.errors


def test_figures_say_what_they_are_and_their_units(tmp_path):
    from spadscan.dashboard.scans import plot_histograms
    from spadscan.protocol.sensor_presets import tmf8820

    sensor = tmf8820()
    assert sensor.zero_bin > 0 and plot_histograms(sensor.n_zones * [[1] * sensor.n_bins], sensor)["first_m"] >= 0
    recording(tmp_path / "vase", 3)
    running_job(tmp_path, "vase-fast")
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        assert wait_text(page, "#worker", "reconstructing") == \
            "worker: reconstructing vase-fast (60 % of its training time)"
        page.locator("#hist polyline").first.wait_for(state="attached", timeout=WAIT_MS)
        texts = page.locator("#hist text").all_text_contents()
        assert float(texts[0].removesuffix(" m")) >= 0, texts  # the axis starts at 0 m, not before
        assert re.fullmatch(r"peak \d+ counts per bin", texts[2]), texts
        assert page.locator("#hist-legend span").all_text_contents() == [str(z) for z in range(1, 10)]
        assert all("°" in c for c in page.locator("#preview-columns .label").all_text_contents())
    assert not seen.errors, seen.errors


def test_a_captures_root_not_made_yet_is_served_and_waited_for(tmp_path):
    root = tmp_path / "captures"
    with serving(root) as server, browser_page() as (page, seen):
        st = status(server)
        assert st["root_missing"] is True and st["scans"] == []
        page.goto(address(server))
        assert wait_text(page, "#waiting-root", "waiting") == (
            f"waiting for the captures root {root.resolve()} to appear (the daemon creates it at its first scan)")
        complete_scan(root / "first", 1)  # the daemon's first scan
        page.locator('#scans tr[data-scan="first"]').wait_for(timeout=WAIT_MS)
        assert page.locator("#waiting-root").is_hidden()
    assert not seen.errors, seen.errors


def test_an_empty_root_a_silent_dashboard_the_daemons_config_and_a_scan_with_no_worker_are_said(tmp_path):
    with serving(tmp_path, daemon_running=daemon_running) as server, browser_page() as (page, seen):
        page.goto(address(server))
        assert wait_text(page, "#scans tbody", "no scans") == (
            f"no scans in {tmp_path.resolve()} yet (a scan is a sub-folder holding scan.json); they are listed as "
            "they appear")
        with RootLock(tmp_path):  # a daemon records s1
            writer = recording(tmp_path / "s1", 2, planned=2)
            said = wait_text(page, "#worker", "s1")
            assert said.startswith("no worker is running: scan s1 is recorded and nothing reconstructs it") and \
                "--live" in said, said
            assert page.locator("#worker").get_attribute("class") == "down"
            writer.finish()
        manifest = json.loads((tmp_path / "s1" / "scan.json").read_text())
        manifest["rig"]["config"] = "/etc/spadscan/lab rig.toml"
        (tmp_path / "s1" / "scan.json").write_text(json.dumps(manifest))
        assert wait_text(page, "#daemon", "lab rig") == \
            " · no daemon running: start one with `spadscan daemon --config '/etc/spadscan/lab rig.toml'`"
        Queue.for_root(tmp_path).enqueue(Job(id="s1-fast", scan="s1"))  # queued, and no worker to take it
        said = wait_text(page, "#worker", "queued")
        assert said.startswith("1 job queued and no worker is running: start one with") and \
            page.locator("#worker").get_attribute("class") == "down", said
        server.shutdown()  # the dashboard stops answering: what the page shows is greyed
        server.server_close()
        page.wait_for_function("() => document.body.classList.contains('offline')", timeout=WAIT_MS)
        assert float(page.locator("#main").evaluate("e => getComputedStyle(e).opacity")) < 1
    assert not [e for e in seen.errors if "Failed to load resource" not in e], seen.errors
