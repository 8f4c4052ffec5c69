"""report.html: one static page per run, next to report.json, that a researcher opens first.

The page needs no server and nothing from the network: the pictures are relative links to the PNG files beside it,
the styling is inline, and the 3D view is view3d.html beside it (folder_view.py: the viewer and its scene in one
file), shown in a frame. The folder can be zipped and mailed as it is. Every string taken from the report is
HTML-escaped.
"""

from __future__ import annotations

import html
import json
import math
from pathlib import Path

from spadscan.protocol.atomic_files import write_atomic

from .folder_view import GT_KEYS, MESH, ensure_view3d
from .view3d import VIEW3D

REPORT_HTML = "report.html"

PICTURES = (
    ("preview.png", "Reconstruction (top row) and, below each view, the ground truth from the same angle at the same "
                    "scale (when given)"),
    ("error_vs_time.png", "Error (Chamfer) and loss against run time, on log axes"),
    ("fit.png", "Measured (dots) against rendered (lines) histograms for a few views"),
    ("coverage.png", ("Where the mesh is measured: each part coloured by the views that see it (red: none, orange: "
                      "one or two; there its shape is the fit's guess, not the data's)")),
    ("normals.png", ("Per-vertex normal error of the mesh (the summary's 'per-vertex normal error', not its "
                     "'normal error (sampled points)')")),
)
"""(file name, caption) of the pictures the page shows when they exist in the folder."""

LOSS_CAPTION = "Loss against run time, on log axes (no checkpoint has a Chamfer: {why})"
"""error_vs_time.png's caption when it plots the loss alone; {why} from `_no_chamfer_reason`."""

RECONSTRUCTION_PICTURES = ("preview.png", "error_vs_time.png", "fit.png")
"""Pictures every reconstruction writes: the page names one that is missing. A baseline writes only preview.png."""

NUMBERS = (
    ("preset", "preset", None), ("method", "baseline", None), ("device", "device", None),
    ("device_name", "device name", None), ("steps", "steps", None), ("seconds", "training seconds", "s"),
    ("wall_seconds", "wall seconds", "s"), ("stopped_by", "stopped by", None), ("converged", "converged", None),
    ("threshold", "threshold", None),
    ("calibrated", "threshold calibrated against ground truth", None), ("final_loss", "final loss", None),
    ("chamfer_mm", "Chamfer", "mm"), ("accuracy_mm", "accuracy", "mm"), ("completeness_mm", "completeness", "mm"),
    ("fscore_5mm", "F-score at 5 mm", None), ("precision", "precision", None), ("recall", "recall", None),
    ("normal_error_deg", "normal error (sampled points)", "deg"), ("n_points", "metric samples per mesh", None),
    ("reprojected_points", "reprojected points", None),
    ("capture", "capture", None), ("capture_state", "capture state", None), ("ground_truth", "ground truth", None),
    ("gt", "ground truth", None), ("ground_truth_scored", "scored against", None),
)
"""(report key, label, unit) of the summary table's rows, in order; keys missing from the report are left out."""

BASELINE_LABELS = {"seconds": "run time"}
"""Labels that differ for a baseline: it does not train."""

UNIT_KEYS = {"threshold": "threshold_units"}
"""Rows whose unit the report gives in another key."""


def metric_samples(report: dict) -> str:
    """The "metric samples per mesh" row: `n_points`, or "5,000 of 300,000" where the metrics' deadline left fewer of
    them measured (`queries`), as the terminal's summary line says: the metrics rest on those alone."""
    points, queries = report.get("n_points"), report.get("queries")
    counts = all(isinstance(n, int) and not isinstance(n, bool) for n in (points, queries))
    if counts and queries < points:
        return f"{queries:,} of {points:,}"
    return format_value(points)


VALUE_TEXTS = {"n_points": metric_samples}
"""Rows whose text draws on more than their own key: f(report) -> text."""

TRACE_COLUMNS = ("step", "seconds", "loss", "chamfer_mm", "note")

STYLE = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em 0; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; font-size: 0.9em; }
td.num { text-align: right; font-family: monospace; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
pre { background: #f6f6f6; padding: 0.8em; overflow-x: auto; font-size: 0.8em; }
.missing { color: #999; font-style: italic; }
.warning { background: #fff3cd; border: 1px solid #e0b000; padding: 0.5em 0.8em; margin: 0.5em 0; }
iframe.view3d { width: 100%; height: 560px; border: 1px solid #ddd; }
"""


def _esc(value) -> str:
    return html.escape(str(value), quote=True)


def format_value(value) -> str:
    """A report value as plain text: floats to 4 significant digits, None as a dash, lists and dicts as JSON."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.4g}" if math.isfinite(value) else str(value)
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    return str(value)


def is_baseline(report: dict) -> bool:
    """A baseline's report names its method and no preset; it has no training, trace, fit or error_vs_time."""
    return "method" in report and "preset" not in report


def warnings(report: dict) -> list[str]:
    """What makes the run's result doubtful or unscored, for the top of the page: the run's own warnings (report.json's
    "warnings", one line each, as every reader counts them: a run that did not converge says so there,
    end_of_run.UNCONVERGED, and the page adds no line of its own about it), an incomplete capture and a named ground
    truth that could not be used."""
    own = report.get("warnings")
    found = [str(w) for w in own if str(w).strip()] if isinstance(own, list) else []
    state = report.get("capture_state")
    note = str(report.get("capture_note") or f"the capture is {state}, not complete")
    if state not in (None, "complete") and note not in found:  # reports of earlier versions left it out of "warnings"
        found.append(note)
    if report.get("ground_truth_note"):
        found.append(f"the named ground truth was not used: {report['ground_truth_note']}")
    return found


def _warnings_html(report: dict) -> str:
    return "\n".join(f"<p class=warning><strong>Warning:</strong> {_esc(w)}</p>" for w in warnings(report))


def _row(report: dict, key: str, label: str, unit) -> str:
    if is_baseline(report):
        label = BASELINE_LABELS.get(key, label)
    unit = (report.get(UNIT_KEYS[key]) or unit) if key in UNIT_KEYS else unit
    value = VALUE_TEXTS[key](report) if key in VALUE_TEXTS else format_value(report[key])
    text = value + (f" {unit}" if unit and report[key] is not None else "")
    return f"<tr><th>{_esc(label)}</th><td class=num>{_esc(text)}</td></tr>"


def _summary(report: dict) -> str:
    hidden = {"gt"} if "ground_truth" in report else set()  # a baseline's report holds both names of one file
    rows = [_row(report, key, label, unit) for key, label, unit in NUMBERS if key in report and key not in hidden]
    terms = report.get("terms")
    if isinstance(terms, dict):
        used = [k for k, v in terms.items() if v] or ["none"]
        left = [k for k, v in terms.items() if not v] or ["none"]
        rows.append(f"<tr><th>model terms used</th><td>{_esc(', '.join(map(str, used)))}</td></tr>")
        rows.append(f"<tr><th>model terms left out</th><td>{_esc(', '.join(map(str, left)))}</td></tr>")
    vne = report.get("vertex_normal_error_deg")
    if isinstance(vne, dict):
        text = ", ".join(f"{k} {format_value(v)}" for k, v in vne.items())
        rows.append(f"<tr><th>per-vertex normal error (normals.png, deg)</th><td class=num>{_esc(text)}</td></tr>")
    return "<table>\n" + "\n".join(rows) + "\n</table>"


def expected_pictures(report: dict) -> set[str]:
    """The pictures whose absence the page reports: those the report lists as written, those every reconstruction
    writes, and normals.png where per-vertex normal errors were computed for it. Others (a baseline's missing
    error_vs_time.png) are left out without comment: not writing them is no failure."""
    files = report.get("files")
    expected = {"preview.png"} | (set(map(str, files)) if isinstance(files, list) else set())
    if not is_baseline(report):
        expected |= set(RECONSTRUCTION_PICTURES)
    if "vertex_normal_error_deg" in report:
        expected.add("normals.png")
    return expected


def _caption(name: str, caption: str, report: dict) -> str:
    if name == "error_vs_time.png" and "trace" in report and not chamfer_in_trace(report):
        return LOSS_CAPTION.format(why=_no_chamfer_reason(report))
    return caption


def _no_chamfer_reason(report: dict) -> str:
    """Why no checkpoint was scored: the trace says when scoring would not fit in the budget (a short run with a
    ground truth), else the report names no ground truth, else there was no surface to score."""
    trace = report.get("trace")
    if isinstance(trace, list) and any(isinstance(p, dict) and "evaluation skipped" in str(p.get("note", ""))
                                       for p in trace):
        return "scoring them would not fit in the time budget"
    if not any(report.get(key) for key in GT_KEYS):
        return "no ground truth"
    return "no surface to score"


def _pictures(folder: Path, report: dict) -> str:
    parts = []
    expected = expected_pictures(report)
    for name, caption in PICTURES:
        caption = _caption(name, caption, report)
        if (folder / name).is_file():
            parts.append(f'<figure><img src="{_esc(name)}" alt="{_esc(caption)}">'
                         f"<figcaption>{_esc(caption)}</figcaption></figure>")
        elif name in expected:
            parts.append(f'<p class=missing>{_esc(caption)}: no picture ({_esc(name)} was not written)</p>')
    return "\n".join(parts)


def _view3d(folder: Path) -> str:
    if (folder / VIEW3D).is_file():
        return (f'<iframe class=view3d src="{VIEW3D}" title="3D view"></iframe>\n'
                f'<p>Drag to turn, shift-drag to pan, the wheel to zoom; the panel shows or hides each layer. '
                f'<a href="{VIEW3D}">Open the 3D view on its own page</a>.</p>')
    if (folder / MESH).is_file():
        return f"<p class=missing>no 3D view ({VIEW3D} was not written)</p>"
    return ""


def chamfer_in_trace(report: dict) -> bool:
    """Whether any trace checkpoint has a Chamfer (none without a ground truth)."""
    trace = report.get("trace")
    return isinstance(trace, list) and any(isinstance(p, dict) and p.get("chamfer_mm") is not None for p in trace)


def trace_note(report: dict) -> str:
    """The report's trace_note, less its clauses ('; '-separated) about checkpoint Chamfer when no checkpoint has
    one: they describe a measurement that was not made."""
    note = str(report.get("trace_note") or "")
    if chamfer_in_trace(report):
        return note
    return "; ".join(c for c in note.split("; ") if "chamfer" not in c.lower())


def _trace(trace) -> str:
    if not isinstance(trace, list) or not trace:
        return "<p class=missing>no trace recorded</p>"
    rows = [dict(p) for p in trace if isinstance(p, dict)]
    extra = sorted({k for p in rows for k in p} - set(TRACE_COLUMNS))
    cols = [c for c in TRACE_COLUMNS if any(c in p for p in rows)] + extra
    head = "".join(f"<th>{_esc(c)}</th>" for c in cols)
    body = "\n".join("<tr>" + "".join(f"<td class=num>{_esc(format_value(p.get(c)))}</td>" for c in cols) + "</tr>"
                     for p in rows)
    return f"<table>\n<tr>{head}</tr>\n{body}\n</table>"


def _files(folder: Path, report: dict) -> str:
    """The run's files: those its report lists (a folder may hold the user's own files besides), else the folder's."""
    listed = report.get("files")
    names = (sorted(str(n) for n in listed) if isinstance(listed, list) else
             sorted(p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith(".")))
    return "<ul>" + "".join(f'<li><a href="{_esc(n)}">{_esc(n)}</a></li>' for n in names) + "</ul>"


def render_html(report: dict, folder) -> str:
    """The page for `report` (a report.json dict) whose files lie in `folder`, as a string."""
    folder = Path(folder)
    kind = report.get("preset") or (f"{report['method']} baseline" if is_baseline(report) else "run")
    title = f"spadscan: {kind} reconstruction of {Path(str(report.get('capture', '?'))).name}"
    sections = [
        f"<h1>{_esc(title)}</h1>",
        _warnings_html(report), "<h2>Summary</h2>", _summary(report),
    ]
    view = _view3d(folder)
    if view:
        sections += ["<h2>3D view</h2>", view]
    sections += ["<h2>Pictures</h2>", _pictures(folder, report)]
    if "trace" in report:
        measured = "error" if chamfer_in_trace(report) else "loss"
        sections += [f"<h2>Trace: {measured} against run time</h2>"]
        if trace_note(report):
            sections.append(f"<p>{_esc(trace_note(report))}</p>")
        sections.append(_trace(report.get("trace")))
    sections += ["<h2>Files</h2>", _files(folder, report),
                 "<h2>Full report</h2>", f"<pre>{_esc(json.dumps(report, indent=1, default=str))}</pre>"]
    return ("<!DOCTYPE html>\n<html lang=en>\n<head>\n<meta charset=utf-8>\n"
            f"<title>{_esc(title)}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n"
            + "\n".join(sections) + "\n</body>\n</html>\n")


def write_report_html(report: dict, folder) -> Path:
    """Write `folder`/report.html for `report` (temporary file, then rename), and its 3D view beside it when the
    folder holds a mesh and no view of it yet. Returns the page's path."""
    folder = Path(folder)
    ensure_view3d(report, folder)
    return write_atomic(folder / REPORT_HTML, render_html(report, folder))
