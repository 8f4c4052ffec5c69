"""A scan planned while a ranking lag below 2 was still accepted resumes: its stored lag is raised to the smallest
one a config may give now, instead of the takeover refusing the scan."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spadscan.daemon.scan_job import load_job
from spadscan.protocol.capture_format import MANIFEST

from test_runner_resume import interrupt, make_cfg


@pytest.mark.parametrize("stored", [0, 1])
def test_a_stored_lag_below_2_resumes_with_lag_2(arun, tmp_path, stored):
    cfg = make_cfg(tmp_path)
    arun(interrupt(cfg))
    folder = tmp_path / "caps" / "mix"
    manifest = json.loads((folder / MANIFEST).read_text())
    manifest["schedule"]["next_views_max_lag"] = stored
    (folder / MANIFEST).write_text(json.dumps(manifest))
    job = load_job(folder, np.asarray(cfg.arm.hand_eye))
    assert job.scan.next_views_max_lag == 2 and job.blocked is None
