"""The dashboard names every live state as the protocol does: a live job given back to the queue reads "queued
again", with the age of its last status at once (no process rewrites it); a run from scratch, which has no live fit,
reads "finishing: the final run" without a "(0 views, 0 steps)" that looks like a fit gone wrong."""

from __future__ import annotations

import datetime as _dt
import json
import re
from pathlib import Path

from dashboard_helpers import complete_scan, serving
from page_helpers import browser_page
from spadscan.dashboard.server import address
from spadscan.protocol.live_status import SAID, STATES

WAIT_MS = 60_000  # generous: a poll a second, on a busy machine
PAGE = Path(__file__).resolve().parents[2] / "spadscan" / "dashboard" / "page.html"


def test_the_pages_live_states_are_the_protocols():
    """`spadscan ctl` and the demo say each state as protocol's SAID; the page has its own copy, kept the same."""
    table = re.search(r"const LIVE_SAID = (\{.*?\});", PAGE.read_text(), re.S)[1]
    said = json.loads(re.sub(r"(\w+):", r'"\1":', table))
    assert said == SAID and set(said) == set(STATES)


def test_a_given_back_live_job_reads_queued_again_and_a_run_from_scratch_shows_no_empty_fit(tmp_path):
    now = _dt.datetime.now(_dt.timezone.utc)

    def live(name, **fields):
        complete_scan(tmp_path / name, 1)
        (tmp_path / name / "recon" / "live").mkdir(parents=True)
        (tmp_path / name / "recon" / "live" / "status.json").write_text(json.dumps(
            {"views_published": 60, "job": f"{name}-fast", **fields}))

    live("back", state="queued", views_used=38, steps=563, chamfer_mm=68.6505,
         note="its worker was stopped; the job is back in the queue",
         updated_utc=(now - _dt.timedelta(seconds=5)).isoformat())  # young: only its state says it is not rewritten
    live("scratch", state="final", views_used=0, steps=0,
         note="scan scratch was already complete when its live job started (or was retried): reconstructing it from "
              "scratch",
         updated_utc=(now + _dt.timedelta(minutes=10)).isoformat())  # fresh all along
    with serving(tmp_path) as server, browser_page() as (page, seen):
        page.goto(address(server))
        picks = {name: page.locator(f'#scans tr[data-scan="{name}"] a.pick') for name in ("back", "scratch")}
        picks["back"].wait_for(timeout=WAIT_MS)
        picks["scratch"].wait_for(timeout=WAIT_MS)
        back = picks["back"].text_content()  # 5 s ago, or a little more on a busy machine
        # the stopped attempt's figures, never the job's now (a status of an earlier version: no figures_utc)
        assert back.startswith("live, queued again (the stopped attempt's fit: 38 views, 563 steps), its Chamfer "
                               "against the ground truth on its 38 views: 68.65 mm, updated ") and \
            back.endswith(" s ago"), back
        assert page.locator('#scans tr[data-scan="back"] .note').text_content().endswith("back in the queue")
        assert picks["scratch"].text_content() == "live, finishing: the final run on 60 views"
        assert page.locator('#scans tr[data-scan="scratch"] .note').text_content().endswith("from scratch")
    assert not seen.errors, seen.errors
