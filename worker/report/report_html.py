"""report.html: one static page per run, next to report.json, that a researcher opens first.

The page needs no server and nothing from the network: the pictures are relative links to the PNG files beside it,
the styling is inline, and there is no script. Every string taken from the report is HTML-escaped.
"""

from __future__ import annotations

import html
import json
import math
import os
from pathlib import Path

REPORT_HTML = "report.html"

PICTURES = (
    ("preview.png", "Reconstruction (top row) and ground truth (bottom row, when given)"),
    ("error_vs_time.png", "Error against run time"),
    ("fit.png", "Measured (dots) against rendered (lines) histograms for a few views"),
    ("normals.png", "Normal error per vertex"),
)
"""(file name, caption) of the pictures the page shows when they exist in the folder."""

NUMBERS = (
    ("preset", "preset", None), ("method", "baseline", None), ("device", "device", None),
    ("device_name", "device name", None), ("steps", "steps", None), ("seconds", "training seconds", "s"),
    ("wall_seconds", "wall seconds", "s"), ("stopped_by", "stopped by", None), ("threshold", "threshold", None),
    ("calibrated", "threshold calibrated against ground truth", None), ("final_loss", "final loss", None),
    ("chamfer_mm", "Chamfer", "mm"), ("accuracy_mm", "accuracy", "mm"), ("completeness_mm", "completeness", "mm"),
    ("fscore_5mm", "F-score at 5 mm", None), ("precision", "precision", None), ("recall", "recall", None),
    ("normal_error_deg", "normal error", "deg"), ("n_points", "metric samples per mesh", None),
    ("capture", "capture", None), ("ground_truth", "ground truth", None), ("gt", "ground truth", None),
    ("ground_truth_scored", "scored", None),
)
"""(report key, label, unit) of the summary table's rows, in order; keys missing from the report are left out."""

TRACE_COLUMNS = ("step", "seconds", "loss", "chamfer_mm", "note")

STYLE = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em 0; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.6em; text-align: left; font-size: 0.9em; }
td.num { text-align: right; font-family: monospace; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
pre { background: #f6f6f6; padding: 0.8em; overflow-x: auto; font-size: 0.8em; }
.missing { color: #999; font-style: italic; }
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


def _summary(report: dict) -> str:
    rows = []
    for key, label, unit in NUMBERS:
        if key in report:
            text = format_value(report[key]) + (f" {unit}" if unit and report[key] is not None else "")
            rows.append(f"<tr><th>{_esc(label)}</th><td class=num>{_esc(text)}</td></tr>")
    terms = report.get("terms")
    if isinstance(terms, dict):
        used = [k for k, v in terms.items() if v] or ["none"]
        left = [k for k, v in terms.items() if not v] or ["none"]
        rows.append(f"<tr><th>model terms used</th><td>{_esc(', '.join(map(str, used)))}</td></tr>")
        rows.append(f"<tr><th>model terms left out</th><td>{_esc(', '.join(map(str, left)))}</td></tr>")
    vne = report.get("vertex_normal_error_deg")
    if isinstance(vne, dict):
        text = ", ".join(f"{k} {format_value(v)}" for k, v in vne.items())
        rows.append(f"<tr><th>vertex normal error (deg)</th><td class=num>{_esc(text)}</td></tr>")
    return "<table>\n" + "\n".join(rows) + "\n</table>"


def _pictures(folder: Path) -> str:
    parts = []
    for name, caption in PICTURES:
        if (folder / name).is_file():
            parts.append(f'<figure><img src="{_esc(name)}" alt="{_esc(caption)}">'
                         f"<figcaption>{_esc(caption)}</figcaption></figure>")
        elif name != "normals.png":  # normals.png exists only with ground truth: its absence is no news
            parts.append(f'<p class=missing>{_esc(caption)}: no picture ({_esc(name)} was not written)</p>')
    return "\n".join(parts)


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


def _files(folder: Path) -> str:
    names = sorted(p.name for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    return "<ul>" + "".join(f'<li><a href="{_esc(n)}">{_esc(n)}</a></li>' for n in names) + "</ul>"


def render_html(report: dict, folder) -> str:
    """The page for `report` (a report.json dict) whose files lie in `folder`, as a string."""
    folder = Path(folder)
    kind = report.get("preset") or report.get("method") or "run"
    title = f"spadscan: {kind} reconstruction of {Path(str(report.get('capture', '?'))).name}"
    sections = [
        f"<h1>{_esc(title)}</h1>",
        "<h2>Summary</h2>", _summary(report),
        "<h2>Pictures</h2>", _pictures(folder),
    ]
    if "trace" in report:
        sections += ["<h2>Trace: error against run time</h2>"]
        if report.get("trace_note"):
            sections.append(f"<p>{_esc(report['trace_note'])}</p>")
        sections.append(_trace(report.get("trace")))
    sections += ["<h2>Files</h2>", _files(folder),
                 "<h2>Full report</h2>", f"<pre>{_esc(json.dumps(report, indent=1, default=str))}</pre>"]
    return ("<!DOCTYPE html>\n<html lang=en>\n<head>\n<meta charset=utf-8>\n"
            f"<title>{_esc(title)}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n"
            + "\n".join(sections) + "\n</body>\n</html>\n")


def write_report_html(report: dict, folder) -> Path:
    """Write `folder`/report.html for `report` (temporary file, then rename). Returns its path."""
    folder = Path(folder)
    path = folder / REPORT_HTML
    tmp = folder / f".{REPORT_HTML}.tmp"
    tmp.write_text(render_html(report, folder), encoding="utf-8")
    os.replace(tmp, path)
    return path
