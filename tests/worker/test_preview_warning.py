"""A run whose machine cannot draw off screen says in its report why it has no preview ("no preview.png: <why>", one
line in its "warnings", as the 3D view's is), so that the dashboard, which may run on another machine, says the
worker's reason (spadscan/dashboard/results.py `no_preview`) rather than guessing. The machine is simulated by the
means the product's own check asks (offscreen.check_offscreen: the environment and ctypes.util.find_library)."""

from __future__ import annotations

import ctypes.util
import json

import pytest

from spadscan.dashboard.results import WORKER_CANNOT_DRAW, no_preview
from spadscan.protocol.mesh_io import load_mesh_spec
from spadscan.protocol.schedules import fibonacci_hemisphere
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.simulator import SimSettings, simulate_capture
from spadscan.worker import reconstruct
from worker_helpers import FAST_SMALL

pytestmark = pytest.mark.usefixtures("one_thread")


def cannot_draw_off_screen(monkeypatch) -> None:
    for name in ("DISPLAY", "WAYLAND_DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW"):
        monkeypatch.delenv(name, raising=False)
    find = ctypes.util.find_library
    monkeypatch.setattr(ctypes.util, "find_library", lambda name: None if name in ("EGL", "OSMesa") else find(name))


def test_a_run_that_cannot_draw_its_preview_says_why_in_its_report(tmp_path, monkeypatch, capsys):
    poses = fibonacci_hemisphere(6, 0.3, target=(0, 0, 0.05), min_elevation_deg=15)
    capture = simulate_capture(load_mesh_spec("builtin:sphere")[0], sensor_preset("lcspc-sim"), poses,
                               tmp_path / "cap", settings=SimSettings(rays_per_zone=64), progress=False)
    cannot_draw_off_screen(monkeypatch)
    report = reconstruct.reconstruct_capture(capture, tmp_path / "out", steps=2, device="cpu", overrides=FAST_SMALL,
                                             progress=False, threads=1)
    assert not (tmp_path / "out" / "preview.png").exists()
    (line,) = [w for w in report["warnings"] if w.startswith("no preview.png: ")]
    assert "off screen" in line and "\n" not in line
    assert json.loads((tmp_path / "out" / "report.json").read_text())["warnings"] == report["warnings"]
    assert capsys.readouterr().err.count(line) == 1  # on stderr once, as when it was said there alone
    assert no_preview(report["warnings"]) == {"said": WORKER_CANNOT_DRAW, "why": line}
