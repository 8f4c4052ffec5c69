"""figure_a.html: the sweep's Figure A with its table, a static page beside the PNGs (no server, no script)."""

from __future__ import annotations

import html
from pathlib import Path

from spadscan.protocol.atomic_files import write_atomic
from spadscan.worker.report.report_html import STYLE

from .plot import method_label, panel_title
from .results import SweepResults, number, value_key

PAGE = "figure_a.html"


def _esc(value) -> str:
    return html.escape(str(value), quote=True)


def _fmt(value) -> str:
    v = number(value)
    if v is None:
        return _esc(value)
    return f"{v:.4g}"


def _cell(text: str, css: str = "", title: str = "") -> str:
    attrs = (f' class="{css}"' if css else "") + (f' title="{_esc(title)}"' if title else "")
    return f"<td{attrs}>{text}</td>"


EDGE_TEXT = "at the edge of the tried thresholds"
WARN_MARK = "\u26a0"
"""The mark of a Chamfer distance whose run warned (the warnings on hover, and in the row's last cell)."""


def _chamfer_cell(results: SweepResults, r: dict, method: str) -> str:
    v = results.method_value(r, method)
    if v is None:
        return _cell("failed", "missing")
    warnings = results.method_warnings(r, method)
    if not warnings:
        return _cell(f"{v:.3f}", "num")
    mark = f' <span class="warn" title="{_esc(chr(10).join(warnings))}">{WARN_MARK}&#8239;{len(warnings)}</span>'
    return _cell(f"{v:.3f}{mark}", "num warned")


def _threshold_cell(results: SweepResults, r: dict, method: str) -> str:
    t = results.method_value(r, method, "threshold")
    if t is None:
        return _cell("-", "missing")
    edge = results.threshold_edge(r, method)
    if not edge:
        return _cell(f"{t:g}", "num")
    which = "the only one tried" if edge == "only" else f"the {edge} tried"
    return _cell(f'{t:g} <span class="edge">{EDGE_TEXT} ({_esc(which)})</span>', "num",
                 f"{EDGE_TEXT}: a threshold beyond them, never tried, may do better ([baselines] thresholds)")


def _warnings_cell(results: SweepResults, r: dict) -> str:
    """Each warned method's warnings, folded (a click opens them; no script)."""
    parts = []
    for m in results.methods:
        lines = results.method_warnings(r, m)
        if lines:
            noun = "warning" if len(lines) == 1 else "warnings"
            parts.append(f"<details><summary>{_esc(method_label(m))}: {len(lines)} {noun}</summary><ul>"
                         + "".join(f"<li>{_esc(line)}</li>" for line in lines) + "</ul></details>")
    return _cell("".join(parts), "warnings") if parts else _cell("-", "missing")


def _row(results: SweepResults, r: dict) -> str:
    if r["value"] != "":
        where = [_cell(_esc(r["axis"])), _cell(_fmt(r["value"]), "num")]
    elif results.grid:  # a product sweep's entry: every varied parameter's value
        where = [_cell(_esc(r["axis"])), _cell(_esc(" ".join(f"{a}={_fmt(r.get(a))}" for a in results.grid)))]
    else:  # a sweep without a grid
        where = [_cell(_esc(r["axis"])), _cell("the base condition alone")]
    status = _esc(r["status"]) if r["status"] == "done" else f"{_esc(r['status'])}: {_esc(r['reason'])}"
    cells = [*where, _cell(f"<code>{_esc(r['point'])}</code>"),
             _cell(status, "" if r["status"] == "done" else "failed")]
    cells += [_chamfer_cell(results, r, m) for m in results.methods]
    cells += [_threshold_cell(results, r, m) for m in results.methods if m not in results.presets]
    cells.append(_warnings_cell(results, r))
    return "<tr>" + "".join(cells) + "</tr>"


def _order(results: SweepResults):
    """The sort key of a scene's rows: along each axis in the sweep file's order by value (one-at-a-time), or by
    every axis's value in that order (a product: the first axis varies slowest)."""
    order = {axis: i for i, axis in enumerate(results.grid)}

    def key(r: dict) -> tuple:
        if r["value"] == "" and r["axis"] not in order:  # a product entry, or the base condition alone
            return (len(order), *(value_key(r.get(a)) for a in results.grid), r["point"])
        return (order.get(r["axis"], len(order)), value_key(r["value"]), r["point"])

    return key


def _table(results: SweepResults, scene: str) -> str:
    head = ["parameter", "value", "point", "status"] + [f"{method_label(m)}: Chamfer (mm)" for m in results.methods]
    head += [f"{method_label(m)}: threshold" for m in results.methods if m not in results.presets]
    head.append("warnings")
    rows = sorted((r for r in results.rows if r["scene"] == scene), key=_order(results))
    return "\n".join(["<table>", "<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in head) + "</tr>",
                      *(_row(results, r) for r in rows), "</table>"])


def write_page(results: SweepResults, pictures: dict[str, str], folder) -> Path:
    """Write figure_a.html into `folder`: per scene its picture (`pictures[scene]`, a file name beside the page)
    and its table. Returns the page's path."""
    folder = Path(folder)
    panels = ", ".join(panel_title(i, a) for i, a in enumerate(results.grid)) or "the base condition alone"
    failed = sum(1 for r in results.rows if r["status"] != "done")
    warned = sum(1 for r in results.rows if any(results.method_warnings(r, m) for m in results.methods))
    parts = [f"<h1>Sensitivity sweep: {_esc(results.folder.name)}</h1>",
             f"<p>{len(results.rows)} grid entries with a result ({failed} failed, {warned} with warnings), "
             f"{_esc(results.mode)} sweep; panels: {_esc(panels)}. Chamfer distance in millimetres (log axis); each "
             f"baseline's threshold is calibrated per point against the ground truth (its best possible Chamfer), "
             f"and marked where it is {EDGE_TEXT} (one beyond them might do better). A cross in the strip along a "
             f"panel's top, above the dashed line, is a method that gave no result there. A hollow marker, and "
             f"{WARN_MARK} in the table, is a result whose run warned: it did not converge, or it says why its result "
             f"is doubtful (hover over {WARN_MARK}, or open the row's warnings). Every number is in "
             f'<a href="results.csv">results.csv</a>; each point\'s record in <code>points/</code>.</p>']
    for scene in results.scenes:
        parts.append(f"<h2>{_esc(scene)}</h2>")
        if scene in pictures:
            parts.append(f'<figure><img src="{_esc(pictures[scene])}" alt="Figure A of {_esc(scene)}"></figure>')
        parts.append(_table(results, scene))
    style = STYLE + (".failed { color: #b00; }\n.warn, .edge { color: #a60; font-weight: bold; cursor: help; }\n"
                     ".edge { display: block; font-size: smaller; font-family: sans-serif; }\n"
                     ".warnings { font-size: smaller; max-width: 36em; }\n.warnings ul { margin: 0.2em 0; "
                     "padding-left: 1.2em; }\n")
    text = ("<!DOCTYPE html>\n<html lang=en>\n<head>\n<meta charset=utf-8>\n"
            f"<title>spadscan sweep {_esc(results.folder.name)}</title>\n<style>{style}</style>\n</head>\n<body>\n"
            + "\n".join(parts) + "\n</body>\n</html>\n")
    return write_atomic(folder / PAGE, text)


__all__ = ["write_page", "PAGE"]
