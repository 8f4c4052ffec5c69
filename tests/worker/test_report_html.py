"""report.html: the report's numbers on one static page, every string escaped, links only to files that exist."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

import pytest

from spadscan.worker import end_of_run
from spadscan.worker.report.report_html import REPORT_HTML, format_value, render_html, write_report_html
from spadscan.worker.report.report_html import warnings as page_warnings

PNG = b"\x89PNG\r\n\x1a\n" + b"\0" * 16


def a_report(**extra) -> dict:
    report = {
        "capture": "/data/captures/bunny", "preset": "fast", "device": "cpu", "steps": 1234, "seconds": 97.25,
        "wall_seconds": 112.5, "stopped_by": "budget", "final_loss": 0.0123456,
        "terms": {"pileup": True, "crosstalk": False, "table": True, "tv": False},
        "chamfer_mm": 2.71828, "accuracy_mm": 1.5, "completeness_mm": 3.9, "fscore_5mm": 0.875,
        "normal_error_deg": 12.5, "vertex_normal_error_deg": {"mean": 11.0, "median": 8.25},
        "trace": [{"step": 0, "seconds": 0.0, "loss": None, "chamfer_mm": None, "note": "no surface yet"},
                  {"step": 600, "seconds": 48.5, "loss": 0.031, "chamfer_mm": 4.4},
                  {"step": 1234, "seconds": 97.25, "loss": 0.0123, "chamfer_mm": 2.72}],
        "trace_note": "'seconds' is training time only",
    }
    report.update(extra)
    return report


class Links(HTMLParser):
    """Collects src and href attributes and the names of the tags used."""

    def __init__(self):
        super().__init__()
        self.links: list[str] = []
        self.tags: set[str] = set()

    def handle_starttag(self, tag, attrs):
        self.tags.add(tag)
        self.links += [v for k, v in attrs if k in ("src", "href") and v is not None]


def parse(text: str) -> Links:
    parser = Links()
    parser.feed(text)
    return parser


@pytest.fixture
def folder(tmp_path):
    for name in ("preview.png", "error_vs_time.png", "fit.png", "normals.png"):
        (tmp_path / name).write_bytes(PNG)
    (tmp_path / "mesh.ply").write_text("ply\n")
    (tmp_path / "report.json").write_text("{}\n")
    return tmp_path


def test_the_page_shows_the_reports_numbers_and_trace(folder):
    path = write_report_html(a_report(), folder)
    assert path == folder / REPORT_HTML
    text = path.read_text()
    for shown in ("fast", "cpu", "1234", "97.25 s", "0.01235", "2.718 mm", "1.5 mm", "3.9 mm", "0.875", "12.5 deg",
                  "mean 11, median 8.25", "pileup, table", "crosstalk, tv", "budget", "no surface yet",
                  "training time only"):
        assert shown in text, shown
    trace = text.split("<h2>Trace", 1)[1].split("<h2>", 1)[0]
    assert trace.count("<tr>") == 4  # a header and one row per checkpoint
    assert "48.5" in trace and "4.4" in trace and "600" in trace


def test_links_point_only_at_files_beside_the_page(folder):
    text = write_report_html(a_report(), folder).read_text()
    links = parse(text)
    srcs = {link for link in links.links if link.endswith(".png")}
    assert srcs == {"preview.png", "error_vs_time.png", "fit.png", "normals.png"}
    for link in links.links:
        assert "/" not in link and (folder / link).is_file(), link
    assert "script" not in links.tags and "http" not in text  # nothing fetched from anywhere


def test_missing_pictures_are_named_not_linked(folder):
    (folder / "fit.png").unlink()
    (folder / "normals.png").unlink()
    text = render_html(a_report(), folder)
    links = parse(text).links
    assert "fit.png" not in links and "normals.png" not in links and "preview.png" in links
    assert "no picture (fit.png was not written)" in text


def test_every_string_from_the_report_is_escaped(folder):
    evil = '<script>alert("x")</script>&'
    report = a_report(capture=f"/tmp/{evil}", preset=evil, terms={evil: True},
                      trace=[{"step": 1, "seconds": 1.0, "loss": 0.5, "note": evil, evil: 1}])
    text = render_html(report, folder)
    assert "<script" not in text and evil not in text
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt;&amp;" in text
    assert "script" not in parse(text).tags


def summary_of(text: str) -> str:
    """The page from its top to the pictures: what a reader sees first (the raw JSON dump comes last)."""
    return text.split("<h2>Pictures", 1)[0]


def test_a_baseline_report_without_trace_or_pictures(tmp_path):
    (tmp_path / "mesh.ply").write_text("ply\n")
    text = render_html({"method": "space-carving", "threshold": 5.0, "calibrated": False, "seconds": 1.25,
                        "capture": "c"}, tmp_path)
    assert "space-carving" in text and "1.25 s" in text and "<img" not in text
    assert "<h2>Trace" not in text and 'href="mesh.ply"' in text


def a_baseline(**extra) -> dict:
    return {"method": "space-carving", "capture": "/c/pyramid", "threshold": 5.0,
            "threshold_units": "standard deviations of the matched-filtered background noise (z-score)",
            "calibrated": False, "seconds": 3.008, "capture_state": "complete", **extra}


def test_a_baseline_page_says_run_time_and_the_thresholds_unit(tmp_path):
    (tmp_path / "preview.png").write_bytes(PNG)
    summary = summary_of(render_html(a_baseline(), tmp_path))
    assert "<th>run time</th><td class=num>3.008 s</td>" in summary and "training" not in summary
    assert "5 standard deviations of the matched-filtered background noise (z-score)" in summary
    assert "space-carving baseline" in summary


def test_a_baseline_page_does_not_report_pictures_baselines_never_draw(tmp_path):
    text = render_html(a_baseline(), tmp_path)
    assert "no picture (preview.png was not written)" in text  # a baseline does draw its preview
    assert "error_vs_time.png" not in text and "fit.png" not in text and "Error" not in text


def test_a_picture_the_report_lists_is_reported_missing_even_for_a_baseline(tmp_path):
    text = render_html(a_baseline(files=["fit.png", "mesh.ply"]), tmp_path)
    assert "no picture (fit.png was not written)" in text and "error_vs_time.png" not in text


def test_a_reconstruction_missing_normals_it_computed_says_so(folder):
    (folder / "normals.png").unlink()
    assert "no picture (normals.png was not written)" in render_html(a_report(), folder)
    report = a_report()
    del report["vertex_normal_error_deg"]  # no ground truth, no normals picture: its absence is no news
    assert "normals.png" not in render_html(report, folder)


def test_an_incomplete_capture_is_a_warning_at_the_top(folder):
    note = "cap/c: the capture is running, not complete: reconstructing the 128 views it holds so far"
    summary = summary_of(render_html(a_report(capture_state="running", capture_note=note), folder))
    warning = summary.split("<table>", 1)[0]
    assert "class=warning" in warning and note in warning
    assert "<th>capture state</th><td class=num>running</td>" in summary


def test_an_incomplete_capture_without_its_note_still_warns(folder):
    summary = summary_of(render_html(a_report(capture_state="paused"), folder))
    assert "class=warning" in summary and "the capture is paused, not complete" in summary


def test_a_complete_capture_has_no_warning(folder):
    assert "class=warning" not in render_html(a_report(capture_state="complete"), folder)


def test_the_page_says_a_run_did_not_converge_as_its_report_json_does_once(folder):
    """report.json's warnings are the run's: a run that did not converge says so there (end_of_run.UNCONVERGED, made
    by end_of_run.warnings, which decides what a live job's polish or a run stopped early says instead), and the page
    lists them as they are, adding no line of its own that `spadscan worker --status` and the dashboard would not
    count."""
    unsettled = summary_of(render_html(a_report(capture_state="complete", converged=False,
                                                warnings=[end_of_run.UNCONVERGED]), folder))
    assert "class=warning" in unsettled and unsettled.count("did not converge") == 1, unsettled
    silent = a_report(capture_state="complete", converged=False, warnings=[],
                      live={"views_used": 79, "final_steps": None, "final_budget_s": 120.0})
    assert "did not converge" not in render_html(silent, folder), "the report decides, not the page"
    early = end_of_run.warnings(end_of_run.RunFacts(stopped_by="budget", steps=3, model_converged=False,
                                                    data_terms=[]))
    assert len(early) == 1 and page_warnings(a_report(converged=False, warnings=early)) == early, early


def test_ground_truth_notes_are_in_the_summary(folder):
    note = "/gt/flat.obj: holds no triangles; no metrics"
    scored = "the object above z = -0.1510 m (the ground truth's table top + 5 mm; a reconstruction holds no table)"
    summary = summary_of(render_html(a_report(ground_truth_note=note, ground_truth_scored=scored), folder))
    assert "class=warning" in summary and "ground truth was not used: " + note in summary
    assert "table top + 5 mm" in summary


def test_the_two_normal_errors_are_named_apart(folder):
    summary = summary_of(render_html(a_report(), folder))
    assert "<th>normal error (sampled points)</th><td class=num>12.5 deg</td>" in summary
    assert "<th>per-vertex normal error (normals.png, deg)</th><td class=num>mean 11, median 8.25</td>" in summary


def test_a_trace_without_chamfer_is_loss_against_run_time(folder):
    trace = [{"step": 0, "seconds": 0.0, "loss": None}, {"step": 5, "seconds": 1.0, "loss": 0.5}]
    note = ("'seconds' is training time only: evaluation is excluded; checkpoint Chamfer uses 30000 points per "
            "mesh; 'loss' is the mean since the previous checkpoint")
    text = render_html(a_report(trace=trace, trace_note=note), folder)
    pictures = text.split("<h2>Pictures", 1)[1].split("<h2>", 1)[0]
    assert "Loss against run time" in pictures and "Error" not in pictures
    assert "<h2>Trace: loss against run time</h2>" in text
    shown_note = text.split("<h2>Trace", 1)[1].split("<table>", 1)[0]
    assert "training time only" in shown_note and "mean since the previous" in shown_note
    assert "Chamfer" not in shown_note


def test_a_trace_with_chamfer_keeps_its_note_and_error_title(folder):
    text = render_html(a_report(trace_note="a; checkpoint Chamfer uses 30000 points"), folder)
    assert "<h2>Trace: error against run time</h2>" in text and "checkpoint Chamfer uses 30000 points" in text


@pytest.mark.parametrize("value, text", [(None, "-"), (True, "yes"), (0.000123456, "0.0001235"), (float("nan"), "nan"),
                                         ([1, 2], "[1, 2]"), (7, "7")])
def test_format_value(value, text):
    assert format_value(value) == text


def test_the_written_page_is_complete_and_atomic(folder):
    write_report_html(a_report(), folder)
    write_report_html(a_report(steps=99), folder)
    text = (folder / REPORT_HTML).read_text()
    assert text.rstrip().endswith("</html>") and re.search(r">99<", text)
    assert not [p for p in Path(folder).iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("extra, why", [
    ({"ground_truth": "builtin:sphere", "trace": [{"step": 0, "seconds": 0.0, "loss": 0.5,
                                                   "note": "evaluation skipped: it would not fit in the time budget"}]},
     "scoring them would not fit in the time budget"),
    ({"trace": [{"step": 5, "seconds": 1.0, "loss": 0.5}]}, "no ground truth"),
    ({"ground_truth": "builtin:sphere", "trace": [{"step": 5, "seconds": 1.0, "loss": 0.5, "chamfer_mm": None}]},
     "no surface to score"),
])
def test_a_loss_only_plot_says_why_no_checkpoint_was_scored(folder, extra, why):
    """A short run with a ground truth skips scoring its checkpoints: its caption said 'no ground truth' on a page
    showing the ground truth and a Chamfer."""
    text = render_html(a_report(**extra), folder)
    pictures = text.split("<h2>Pictures", 1)[1].split("<h2>", 1)[0]
    assert f"Loss against run time, on log axes (no checkpoint has a Chamfer: {why})" in pictures


def test_a_baseline_names_its_ground_truth_once(tmp_path):
    """A baseline's report holds the ground truth under both names (`ground_truth`, and `gt` as before)."""
    report = {"method": "space-carving", "threshold": 5.0, "ground_truth": "/gt/pyramid.stl",
              "gt": "/gt/pyramid.stl", "chamfer_mm": 9.2}
    assert summary_of(render_html(report, tmp_path)).count("<th>ground truth</th>") == 1
    del report["ground_truth"]
    assert summary_of(render_html(report, tmp_path)).count("<th>ground truth</th>") == 1


def test_metric_samples_say_how_many_the_deadline_left_measured(folder):
    cut = summary_of(render_html(a_report(n_points=300000, queries=5000), folder))
    assert "<th>metric samples per mesh</th><td class=num>5,000 of 300,000</td>" in cut
    whole = summary_of(render_html(a_report(n_points=300000, queries=300000), folder))
    assert "<th>metric samples per mesh</th><td class=num>300000</td>" in whole
    assert "<th>metric samples per mesh</th><td class=num>300000</td>" in summary_of(
        render_html(a_report(n_points=300000), folder))
