"""A Ctrl-C or a SIGTERM that comes while the embedded cluster starts ends the sweep once the start is done: its one
interrupted line (no traceback), exit status 130, the cluster closed with no process left, the stored points kept.
A Ctrl-C there used to be lost (the sweep ran to its end); a SIGTERM broke into Dask's start with a traceback."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from spadscan.sweep.fingerprint import Expected
from spadscan.sweep.plan import make_plan
from spadscan.sweep.spec import load_spec
from spadscan.sweep.store import SweepDir

from test_sweep_cluster import wait_for

pytestmark = pytest.mark.slow

TWO_POINTS = """
[sweep]
scenes = ["builtin:sphere"]
baselines = []

[base]
views = 4
rays_per_zone = 256

[grid]
views = [4, 6]

[fast]
steps = 5
set = { "field.resolution" = 20, "field.hull_resolution" = 40, mesh_resolution = 48, trace_checkpoints = 1, \
trace_mesh_resolution = 24, trace_points = 1000 }

[metrics]
points = 5000
calibration_points = 5000
"""

DURING_START = """
import os
import signal
import sys
from pathlib import Path

from spadscan.sweep import runner


class SignallingNanny(runner.ExitNotingNanny):
    \"\"\"The cluster's first nanny sends the signal to this process as it starts (on Dask's event-loop thread, while
    the main thread waits for the cluster).\"\"\"

    sent = False

    async def start_unsafe(self):
        if not SignallingNanny.sent:
            SignallingNanny.sent = True
            Path(sys.argv[2]).write_text("sent")
            os.kill(os.getpid(), getattr(signal, sys.argv[1]))
        return await super().start_unsafe()


if __name__ == "__main__":
    runner.ExitNotingNanny = SignallingNanny
    from spadscan.cli import main

    sys.exit(main(sys.argv[3:]))
"""


def session_processes(sid: int) -> list[int]:
    """The live (not zombie) processes of session `sid`."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            found.append(int(entry.name))
    return found


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_a_signal_while_the_local_cluster_starts_ends_the_sweep_in_one_line(sig, tmp_path):
    sweep_file = tmp_path / "two.toml"
    sweep_file.write_text(TWO_POINTS)
    plan = make_plan(load_spec(sweep_file))
    out = tmp_path / "out"
    store = SweepDir(out)
    store.open(plan)
    store.close()
    done, to_run = sorted(plan.points.values(), key=lambda t: t.params["views"])
    store.write_point({"id": done.id, "status": "done", "reason": None, "params": done.params,
                       "methods": {"fast": {"status": "done", "chamfer_mm": 3.0}},
                       "fingerprints": Expected(done, "cpu").fingerprints})
    kept = (out / "points" / f"{done.id}.json").read_text()
    script = tmp_path / "during_start.py"
    script.write_text(DURING_START)
    sent = tmp_path / "sent"
    sweep = subprocess.Popen([sys.executable, str(script), sig, str(sent), "sweep", str(sweep_file), "--out",
                              str(out), "--workers", "1", "--no-progress"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _, err = sweep.communicate(timeout=300)
        wait_for(lambda: not session_processes(sweep.pid), 60, "the cluster's processes ending with the sweep")
    finally:
        if sweep.poll() is None or session_processes(sweep.pid):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(sweep.pid, signal.SIGKILL)
            sweep.wait()
    assert sent.read_text() == "sent"
    assert sweep.returncode == 130, err
    lines = err.splitlines()
    assert lines[-1].startswith(f"spadscan sweep: interrupted; the points finished are kept in {out}"), err
    assert "Traceback" not in err and "Error" not in err, err
    assert not (out / "points" / f"{to_run.id}.json").exists()  # ended before any point was given out
    assert (out / "points" / f"{done.id}.json").read_text() == kept
    assert json.loads(kept)["status"] == "done"
