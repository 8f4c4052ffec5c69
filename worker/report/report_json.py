"""report.json: one JSON object per run, written atomically, with every number made JSON-safe."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from spadscan.protocol.atomic_files import write_atomic

REPORT = "report.json"


def json_safe(value):
    """A copy of value with numpy scalars and arrays made plain, tuples made lists and non-finite floats None."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, Path):
        return str(value)
    return value


def write_report(out_dir, report: dict) -> Path:
    """Write out_dir/report.json (temporary file, fsync, rename). Returns its path."""
    out_dir = Path(out_dir)
    return write_atomic(out_dir / REPORT, json.dumps(json_safe(report), indent=1) + "\n")
