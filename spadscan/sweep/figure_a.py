"""`spadscan sweep-plot`'s work: Figure A of each scene as a PNG, and one HTML page with the pictures and tables."""

from __future__ import annotations

import re
from pathlib import Path

from .page import write_page
from .plot import figure_png
from .results import read_results


def picture_name(scene: str, scenes: list) -> str:
    """figure_a.png for a sweep of one scene; figure_a-<n>-<scene>.png (n: its place in `scenes`, from 1; the name
    file-name-safe) for each of several. The number keeps scenes apart whose safe names coincide (a/b.obj, a_b.obj)."""
    if len(scenes) <= 1:
        return "figure_a.png"
    safe = re.sub(r'[^A-Za-z0-9_.-]+', '_', scene).strip('_') or 'scene'
    return f"figure_a-{scenes.index(scene) + 1}-{safe}.png"


def plot_sweep(folder) -> tuple[list[Path], Path]:
    """Draw the sweep in `folder` into `folder`; returns (the PNGs, the page)."""
    folder = Path(folder)
    results = read_results(folder)
    scenes = [s for s in results.scenes if any(r["scene"] == s for r in results.rows)]
    pictures = {scene: picture_name(scene, results.scenes) for scene in scenes}
    pngs = [figure_png(results, scene, folder / name) for scene, name in pictures.items()]
    return pngs, write_page(results, pictures, folder)


__all__ = ["plot_sweep", "picture_name"]
