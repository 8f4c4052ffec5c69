"""For the tests of the pages (report.html's 3D view, the dashboard): a real headless browser, and scans written
pose by pose as the daemon writes them.

The browser is the system's Chromium driven by Playwright, started and stopped by the test. Tests that need it are
skipped, saying why, where no Chromium is installed (tests/run.sh installs Debian's when it runs as root).
Playwright is never let to download a browser of its own."""

from __future__ import annotations

import io
import os
import shutil
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from process_helpers import short_socket_dir

CHROMIUM = Path("/usr/bin/chromium")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run"]


@dataclass
class Seen:
    """What the page did: console errors, uncaught exceptions and every URL it requested."""

    errors: list[str] = field(default_factory=list)
    requests: list[str] = field(default_factory=list)


def require_chromium() -> None:
    if not CHROMIUM.is_file():
        pytest.skip(f"no Chromium at {CHROMIUM} (on Debian: apt-get install chromium; tests/run.sh does it as root)")
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        pytest.skip("Playwright's Python package is not installed (pip install -e '.[test]')")


@contextmanager
def browser_page(width: int = 1100, height: int = 900):
    """(page, seen) of a fresh headless Chromium; everything is closed on the way out."""
    require_chromium()
    from playwright.sync_api import sync_playwright

    seen = Seen()
    # Chromium makes its SingletonSocket in TMPDIR: under a long one (a CI's, a pytest's) the socket's path passes the
    # 107 bytes a Unix socket may have and Chromium does not start. It gets a short folder of its own instead.
    scratch = short_socket_dir()
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=FLAGS,
                                         env={**os.environ, "TMPDIR": str(scratch)})
            try:
                page = browser.new_page(viewport={"width": width, "height": height})
                page.on("console", lambda m: seen.errors.append(m.text) if m.type == "error" else None)
                page.on("pageerror", lambda e: seen.errors.append(f"uncaught: {e}"))
                page.on("request", lambda r: seen.requests.append(r.url))
                yield page, seen
            finally:
                browser.close()
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def screenshot_pixels(target) -> np.ndarray:
    """(H, W, 3) uint8 pixels of a Playwright page or element's screenshot."""
    import matplotlib.image

    return (matplotlib.image.imread(io.BytesIO(target.screenshot()), format="png")[..., :3] * 255).astype(np.uint8)


def drawn_share(pixels: np.ndarray, background=(255, 255, 255), tolerance: int = 12) -> float:
    """Share of the pixels that differ from the background colour."""
    diff = np.abs(pixels.astype(int) - np.asarray(background)[None, None, :]).max(axis=2)
    return float(np.mean(diff > tolerance))


def start_scan(path: Path, planned: int, radius_m: float = 0.5):
    """A CaptureWriter for a running scan of `planned` poses on a hemisphere around the origin (the TMF8820 model),
    publishing a chunk per pose as the daemon does. Returns (writer, poses (planned, 4, 4))."""
    from spadscan.protocol.capture_writer import CaptureWriter
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.sensor_presets import tmf8820

    poses = fibonacci_hemisphere(planned, radius_m)
    writer = CaptureWriter.create(path, tmf8820(), planned_poses=poses, chunk_size=1,
                                  schedule={"views": planned})
    return writer, poses


def add_pose(writer, poses: np.ndarray, index: int, t_s: float | None = None) -> None:
    """Publish pose `index`: one frame whose zones see a return at 0.5 m over a flat background."""
    from spadscan.protocol.capture_format import Measurement

    sensor = writer.sensor
    hist = np.full((sensor.n_zones, sensor.n_bins), 3, np.uint32)
    peak = int(round(sensor.zero_bin + 0.5 / sensor.bin_width_m))
    hist[:, peak - 1:peak + 2] = 200 + 10 * np.arange(sensor.n_zones)[:, None]
    t = float(index) if t_s is None else t_s
    writer.append(Measurement(hist, poses[index], index, meta={"t_start": t, "t_end": t + 0.25}))
    writer.flush()
