"""Draw a sweep's Figure A: one panel per parameter, Chamfer distance (log axis) against it, every method.

Reads DIR/sweep.json and DIR/results.csv (written by `spadscan sweep`, also while it runs) and writes into DIR
figure_a.png (for a sweep of several scenes, figure_a-<n>-<scene>.png for each: n is the scene's place in the sweep
file, from 1, and <scene> its name made file-name-safe, e.g. figure_a-2-builtin_cup.png) and figure_a.html: the
pictures and a table of every point. Points where a method gave no result are crosses on the panel's top edge;
results whose run warned are hollow markers (and marked in the table, their warnings beside them); a product
sweep's lines are named by the other parameters' values in each panel's legend. A sweep without a grid is one panel:
each method's Chamfer distance at the base condition.

Example:
  spadscan sweep-plot sweep-small
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("folder", metavar="DIR", help="the --out folder of a `spadscan sweep`")


def run(args) -> int:
    from spadscan.sweep.figure_a import plot_sweep

    pngs, page = plot_sweep(args.folder)
    print(f"wrote {page} (open this first), " + ", ".join(p.name for p in pngs))
    return 0
