"""figure_a.html: the sweep's Figure A with its table, a static page beside the PNGs (no server, no script)."""

from __future__ import annotations

import html
from pathlib import Path

from spadscan.protocol.atomic_files import write_atomic
from spadscan.worker.report.report_html import STYLE

from .plot import method_label, panel_title
from .results import SweepResults, number

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


def _row(results: SweepResults, r: dict) -> str:
    if r["value"] != "":
        where = [_cell(_esc(r["axis"])), _cell(_fmt(r["value"]), "num")]
    else:  # a product sweep's entry: every varied parameter's value
        where = [_cell(_esc(r["axis"])), _cell(_esc(" ".join(f"{a}={_fmt(r.get(a))}" for a in results.grid)))]
    status = _esc(r["status"]) if r["status"] == "done" else f"{_esc(r['status'])}: {_esc(r['reason'])}"
    cells = [*where, _cell(f"<code>{_esc(r['point'])}</code>"),
             _cell(status, "" if r["status"] == "done" else "failed")]
    for m in results.methods:
        v = results.method_value(r, m)
        cells.append(_cell(f"{v:.3f}", "num") if v is not None else _cell("failed", "missing"))
    for m in results.methods:
        if m not in results.presets:
            t = results.method_value(r, m, "threshold")
            cells.append(_cell(f"{t:g}", "num") if t is not None else _cell("-", "missing"))
    return "<tr>" + "".join(cells) + "</tr>"


def _table(results: SweepResults, scene: str) -> str:
    head = ["parameter", "value", "point", "status"] + [f"{method_label(m)}: Chamfer (mm)" for m in results.methods]
    head += [f"{method_label(m)}: threshold" for m in results.methods if m not in results.presets]
    order = {axis: i for i, axis in enumerate(results.grid)}
    rows = sorted((r for r in results.rows if r["scene"] == scene),
                  key=lambda r: (order.get(r["axis"], len(order)), number(r["value"]) or 0.0, r["point"]))
    return "\n".join(["<table>", "<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in head) + "</tr>",
                      *(_row(results, r) for r in rows), "</table>"])


def write_page(results: SweepResults, pictures: dict[str, str], folder) -> Path:
    """Write figure_a.html into `folder`: per scene its picture (`pictures[scene]`, a file name beside the page)
    and its table. Returns the page's path."""
    folder = Path(folder)
    panels = ", ".join(panel_title(i, a) for i, a in enumerate(results.grid)) or "the base condition alone"
    failed = sum(1 for r in results.rows if r["status"] != "done")
    parts = [f"<h1>Sensitivity sweep: {_esc(results.folder.name)}</h1>",
             f"<p>{len(results.rows)} grid entries with a result ({failed} failed), {_esc(results.mode)} sweep; "
             f"panels: {_esc(panels)}. Chamfer distance in millimetres (log axis); each baseline's threshold is "
             f"calibrated per point against the ground truth (its best possible Chamfer). A cross in the strip along a "
             f"panel's top, above the dashed line, is a method that gave no result there. Every number is in "
             f'<a href="results.csv">results.csv</a>; each point\'s record in <code>points/</code>.</p>']
    for scene in results.scenes:
        parts.append(f"<h2>{_esc(scene)}</h2>")
        if scene in pictures:
            parts.append(f'<figure><img src="{_esc(pictures[scene])}" alt="Figure A of {_esc(scene)}"></figure>')
        parts.append(_table(results, scene))
    style = STYLE + ".failed { color: #b00; }\n"
    text = ("<!DOCTYPE html>\n<html lang=en>\n<head>\n<meta charset=utf-8>\n"
            f"<title>spadscan sweep {_esc(results.folder.name)}</title>\n<style>{style}</style>\n</head>\n<body>\n"
            + "\n".join(parts) + "\n</body>\n</html>\n")
    return write_atomic(folder / PAGE, text)


__all__ = ["write_page", "PAGE"]
