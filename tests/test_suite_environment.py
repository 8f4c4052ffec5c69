"""The suite's tests run alike on a developer's machine and in CI: the user's own spadscan variables do not reach
them, file modes bind root's commands however root holds its capabilities, and a machine that cannot draw off screen
skips the drawing tests, saying why."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PRODUCT = [REPO / "spadscan", REPO / "daemon", REPO / "worker", REPO / "protocol"]

# By its path: `import conftest` finds whichever folder's conftest pytest loaded first.
_spec = importlib.util.spec_from_file_location("suite_conftest", Path(__file__).with_name("conftest.py"))
conftest = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(conftest)

CHILD_ENV = "import os, sys; print(sorted(n for n in sys.argv[1:] if n in os.environ))"


def test_no_product_variable_reaches_a_test_or_its_commands():
    """Run by the test below in a pytest whose environment holds every one of them (here, as ever, none)."""
    assert not [name for name in conftest.PRODUCT_ENV if name in os.environ]
    child = subprocess.run([sys.executable, "-c", CHILD_ENV, *conftest.PRODUCT_ENV], capture_output=True,
                           text=True, timeout=60)
    assert child.stdout.strip() == "[]", child.stderr


def test_the_users_product_variables_are_left_out_of_the_tests():
    # As a developer's shell holds them while their own daemon runs.
    env = {**os.environ, **{name: "/nowhere/of/the/tests" for name in conftest.PRODUCT_ENV}}
    inner = f"{Path(__file__).relative_to(REPO)}::test_no_product_variable_reaches_a_test_or_its_commands"
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist", inner],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0 and "1 passed" in run.stdout, run.stdout[-3000:] + run.stderr[-3000:]


def test_every_spadscan_variable_the_product_reads_is_left_out():
    named = set()
    for folder in PRODUCT:
        for source in folder.rglob("*.py"):
            named.update(re.findall(r"\bSPADSCAN_[A-Z0-9_]+\b", source.read_text()))
    assert named and named <= set(conftest.PRODUCT_ENV), sorted(named - set(conftest.PRODUCT_ENV))


@pytest.mark.skipif(os.geteuid() != 0, reason="only root holds capabilities that override file modes")
def test_root_holding_the_override_as_inheritable_and_ambient_is_refused_a_shut_file_all_the_same(tmp_path):
    """Older Docker hands root the capabilities in its inheritable and ambient sets, from which exec gives them back:
    permissions_apply's prefix must drop them there too, or say why it cannot (a skip)."""
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("no setpriv to hand the capabilities over with")
    shut = tmp_path / "shut"
    shut.write_text("")
    shut.chmod(0o000)
    caps = "+dac_override,+dac_read_search"
    holder = [setpriv, f"--inh-caps={caps}", f"--ambient-caps={caps}"]
    if subprocess.run(holder + ["true"], capture_output=True, timeout=60).returncode != 0:
        pytest.skip("this root may not hold the capabilities as inheritable and ambient")
    child = "\n".join([
        "import subprocess, sys",
        f"sys.path.insert(0, {str(Path(__file__).parent)!r})",
        "from process_helpers import permissions_apply",
        "try:",
        "    prefix = permissions_apply()",
        "except BaseException as exc:  # pytest.skip: why permissions cannot apply here",
        "    print('skipped:', exc)",
        "    sys.exit(0)",
        f"r = subprocess.run(prefix + ['cat', {str(shut)!r}], capture_output=True)",
        "print('opened' if r.returncode == 0 else 'refused')",
    ])
    said = subprocess.run(holder + [sys.executable, "-c", child], capture_output=True, text=True, timeout=120)
    assert said.stdout.strip() == "refused", said.stdout + said.stderr


NO_OPENGL_PLUGIN = '''
import ctypes.util

_find = ctypes.util.find_library
ctypes.util.find_library = lambda name: None if name in ("EGL", "OSMesa") else _find(name)
'''
"""A pytest plugin that makes this machine one without EGL or OSMesa, as the product's check finds them."""


def test_without_an_off_screen_opengl_the_drawing_tests_skip_saying_why_and_the_no_renderer_test_runs(tmp_path):
    (tmp_path / "no_opengl.py").write_text(NO_OPENGL_PLUGIN)
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(tmp_path), env.get("PYTHONPATH")]))
    tests = ["tests/worker/test_report_pictures.py::test_the_preview_without_ground_truth_is_one_row",
             "tests/worker/test_report_pictures.py::test_a_machine_that_cannot_draw_off_screen_gets_a_warning_and_no_"
             "picture",
             "tests/worker/test_report_view3d.py::test_a_built_in_ground_truth_is_a_layer_too"]
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", "-p", "no:xdist",
                          "-p", "no_opengl", *tests], cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    said = run.stdout[-3000:] + run.stderr[-3000:]
    assert run.returncode == 0 and "1 passed, 2 skipped" in run.stdout, said
    skips = [line for line in run.stdout.splitlines() if line.startswith("SKIPPED")]
    assert len(skips) == 2 and all("no EGL or OSMesa" in line and "libegl1" in line for line in skips), said
