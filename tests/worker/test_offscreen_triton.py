"""A process that draws a picture and later builds a torch optimiser must not die: Mesa loads the system's libLLVM
when VTK opens its first OpenGL context, and triton (which torch's CUDA build ships and imports lazily, e.g. from
torch.optim) brings an LLVM of its own whose start-up crashes (SIGSEGV) once Mesa's is loaded. `offscreen.plotter`
loads triton first where it is installed (a sweep runs the fast preset's pictures and then the paper preset's Adam
in one process)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import textwrap

import pytest

from spadscan.worker.report.offscreen import OffscreenUnavailable, check_offscreen

# A stand-in triton: records, when it is imported, whether any OpenGL or LLVM library is loaded already.
FAKE_TRITON = textwrap.dedent("""
    import os, re
    maps = open("/proc/self/maps").read()
    loaded = sorted(set(re.findall(r"lib(?:LLVM|EGL|GL|OSMesa)[^/\\s]*", maps)))
    with open(os.environ["TRITON_MARK"], "w") as f:
        f.write(",".join(loaded) or "none")
""")

DRAW = textwrap.dedent("""
    from spadscan.worker.report.offscreen import plotter
    p = plotter()
    p.add_mesh(__import__("pyvista").Sphere())
    p.screenshot(return_img=True)
    p.close()
""")


def can_draw() -> None:
    try:
        check_offscreen()
    except OffscreenUnavailable as exc:
        pytest.skip(f"cannot draw off screen here: {exc}")


def test_a_plotter_imports_triton_before_any_opengl_library_is_loaded(tmp_path):
    can_draw()
    (tmp_path / "site" / "triton").mkdir(parents=True)
    (tmp_path / "site" / "triton" / "__init__.py").write_text(FAKE_TRITON)
    mark = tmp_path / "mark.txt"
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "site"), "TRITON_MARK": str(mark)}
    r = subprocess.run([sys.executable, "-c", DRAW], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert mark.exists(), "drawing never imported triton"
    assert mark.read_text() == "none", f"triton came after OpenGL's libraries: {mark.read_text()}"


@pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="no triton (torch's CPU build): nothing clashes")
def test_drawing_then_building_adam_with_the_real_triton_lives(tmp_path):
    can_draw()
    code = DRAW + "import torch\ntorch.optim.Adam([torch.zeros(1, requires_grad=True)])\nprint('alive')\n"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == "alive", (r.returncode, r.stderr[-2000:])
