"""figure_a.html: the sweep's Figure A with its table, a static page beside the PNGs (no server, no script)."""

from __future__ import annotations

import html
import os
from pathlib import Path

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


def _table(results: SweepResults, scene: str) -> str:
    head = ["parameter", "value", "point", "status"] + [f"{method_label(m)}: Chamfer (mm)" for m in results.methods]
    head += [f"{method_label(m)}: threshold" for m in results.methods if m not in results.presets]
    lines = ["<table>", "<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in head) + "</tr>"]
    order = {axis: i for i, axis in enumerate(results.grid)}
    rows = sorted((r for r in results.rows if r["scene"] == scene),
                  key=lambda r: (order.get(r["axis"], len(order)), number(r["value"]) or 0.0, r["point"]))
    for r in rows:
        value = r["value"] if r["value"] != "" else " ".join(f"{a}={_fmt(r.get(a))}" for a in results.grid)
        status = r["status"]
        cells = [_esc(r["axis"]), f'<td class="num">{_fmt(value)}</td>' if r["value"] != "" else _esc(value),
                 f"<code>{_esc(r['point'])}</code>",
                 _esc(status) if status == "done" else f'<span class="failed" title="{_esc(r["reason"])}">'
                                                       f'{_esc(status)}: {_esc(r["reason"])}</span>']
        tds = [c if c.startswith("<td") else f"<td>{c}</td>" for c in cells]
        for m in results.methods:
            v = results.method_value(r, m)
            tds.append(f'<td class="num">{v:.3f}</td>' if v is not None else
                       '<td class="missing">failed</td>')
        for m in results.methods:
            if m not in results.presets:
                t = results.method_value(r, m, "threshold")
                tds.append(f'<td class="num">{t:g}</td>' if t is not None else '<td class="missing">-</td>')
        lines.append("<tr>" + "".join(tds) + "</tr>")
    lines.append("</table>")
    return "\n".join(lines)


def write_page(results: SweepResults, pictures: dict[str, str], folder) -> Path:
    """Write figure_a.html into `folder`: per scene its picture (`pictures[scene]`, a file name beside the page)
    and its table. Returns the page's path."""
    folder = Path(folder)
    panels = ", ".join(panel_title(i, a) for i, a in enumerate(results.grid)) or "the base condition alone"
    failed = sum(1 for r in results.rows if r["status"] != "done")
    parts = [f"<h1>Sensitivity sweep: {_esc(results.folder.name)}</h1>",
             f"<p>{len(results.rows)} grid entries with a result ({failed} failed), {_esc(results.mode)} sweep; "
             f"panels: {_esc(panels)}. Chamfer distance in millimetres (log axis); each baseline's threshold is "
             f"calibrated per point against the ground truth (its best possible Chamfer). A cross on a panel's top "
             f"edge is a method that gave no result there. Every number is in "
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
    path = folder / PAGE
    tmp = folder / f".{PAGE}.tmp"
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)
    return path


__all__ = ["write_page", "PAGE"]
