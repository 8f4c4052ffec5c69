"""The plan-only run (`spadscan sweep --dry-run`) stays light: it reads the sweep file and the results folder and
loads nothing it needs only to run the points."""

from __future__ import annotations

import json
import subprocess
import sys

from sweep_helpers import write_tiny

HEAVY = ("torch", "dask", "distributed", "spadscan.sweep.runner")


def dry_run_imports(*args: str) -> list[str]:
    """The modules of HEAVY that a dry run of the CLI in a child process imported (it must succeed)."""
    code = (
        "import json, sys\n"
        "from spadscan.cli import main\n"
        f"assert main({list(args)!r}) == 0\n"
        f"print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.splitlines()[-1])


def test_a_dry_run_imports_neither_dask_nor_the_runner(tmp_path):
    tiny = str(write_tiny(tmp_path))
    imported = dry_run_imports("sweep", tiny, "--out", str(tmp_path / "out"), "--dry-run")
    assert not {"dask", "distributed", "spadscan.sweep.runner"} & set(imported), imported
