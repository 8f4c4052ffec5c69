"""Sensitivity sweeps: simulate -> reconstruct -> baselines -> metrics over a grid of imaging parameters, on Dask.

A sweep file (TOML, `spec.py`) names the scenes, the base condition and the grids; `plan.py` expands it into points
with stable ids; `point.py` runs one point (on a Dask worker or in this process); `store.py` keeps the results folder
(`points/<id>.json`, `results.csv`, `log.jsonl`); `checks.py` refuses command-line options the run could not use
(loading torch or Dask only for the options that need them); `runner.py` drives a Dask cluster through the points;
`plot.py` draws Figure A. Dask is imported here and nowhere else in spadscan. This package stands above the simulator
(protocol) and the reconstruction, baselines and metrics (worker); neither imports it.
"""
