"""A job process that may not write a file as large as it needs (`ulimit -f`) leaves no file cut short where its
results are read, and fails once with the limit named, rather than crashing (a bare 'File too large', no file named)
through every attempt the queue gives it."""

from __future__ import annotations

import errno
import json
import subprocess
import sys
from pathlib import Path

from spadscan.worker.jobs import EXIT_INPUT, _ended_in_error

LIMITED = """
import resource, sys
from pathlib import Path
resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, resource.RLIM_INFINITY))
from spadscan.worker.jobs import ground_truth
path, note = ground_truth({"scene": {"builtin": "sphere"}}, Path(sys.argv[1]))
print(path, "|", note)
"""


def test_a_ground_truth_cut_short_by_a_size_limit_is_removed_and_said(tmp_path):
    out = subprocess.run([sys.executable, "-c", LIMITED, str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    path, note = out.stdout.strip().split(" | ")
    assert path == "None" and "File too large" in note and note.endswith("no metrics"), out.stdout
    assert not (tmp_path / "ground_truth.ply").exists(), "a file cut short would be scored against"


def test_a_file_too_large_fails_the_job_with_the_limit_named(tmp_path, capsys):
    outcome = tmp_path / "outcome.json"
    code = _ended_in_error(OSError(errno.EFBIG, "File too large"), outcome, tmp_path / "out")
    said = json.loads(outcome.read_text())
    assert code == EXIT_INPUT and said["kind"] == "input", said
    assert said["error"].startswith(f"file too large: a file in {tmp_path / 'out'} could not be written")
    assert "ulimit -f" in said["error"] and "Traceback" not in capsys.readouterr().err
