"""tools/fit_sensor.py: options that point at the wrong place are one line, before any fit runs."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parents[1] / "tools" / "fit_sensor.py"


@pytest.fixture
def tool():
    spec = importlib.util.spec_from_file_location("fit_sensor_tool", TOOL)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def dataset(tmp_path):
    """A folder laid out as LCSPCData is (simulated/<scene>/<scene>.json and .obj, real/pyramid/), files empty:
    the checks read no file."""
    root = tmp_path / "lcspc"
    (root / "simulated" / "sphere").mkdir(parents=True)
    for suffix in (".json", ".obj"):
        (root / "simulated" / "sphere" / f"sphere{suffix}").write_text("")
    (root / "real" / "pyramid").mkdir(parents=True)
    for name in ("pyramid.json", "pyramid2.stl"):
        (root / "real" / "pyramid" / name).write_text("")
    return root


@pytest.fixture
def no_fit(tool, monkeypatch):
    """The fits replaced by a record of their calls: a check must come before them."""
    calls = []
    monkeypatch.setattr(tool, "fit_lcspc", lambda *a, **k: calls.append("lcspc") or ({}, {}, 0.0))
    monkeypatch.setattr(tool, "tmf_pulse_table", lambda *a, **k: calls.append("tmf") or ((1.0,), 0))
    monkeypatch.setattr(tool, "fit_tmf", lambda *a, **k: calls.append("tmf") or {})
    return calls


@pytest.mark.parametrize("options, message", [
    (["--tmf"], "real/pyramid/pyramid.json not found (--dataset is LCSPCData's folder"),  # one level too deep
    ([], "scene 'sphere': "),
])
def test_a_dataset_folder_one_level_off_is_one_line(tool, dataset, capsys, no_fit, options, message):
    """--dataset DIR/simulated: an IndexError traceback (the mean of no reference histograms) with --tmf."""
    assert tool.main(["--dataset", str(dataset / "simulated"), *options]) == 1
    err = capsys.readouterr().err
    assert err.startswith("fit_sensor: ") and err.count("\n") == 1 and message in err, err
    assert no_fit == []


def test_an_unknown_scene_is_one_line_naming_those_there(tool, dataset, capsys, no_fit):
    assert tool.main(["--dataset", str(dataset), "--scenes", "nope", "--rays", "64", "--iters", "1"]) == 1
    err = capsys.readouterr().err
    assert err == f"fit_sensor: scene 'nope': {dataset}/simulated/nope/nope.json not found (scenes there: sphere)\n"
    assert no_fit == []


def test_zero_rays_is_one_line(tool, dataset, capsys, no_fit):
    assert tool.main(["--dataset", str(dataset), "--scenes", "sphere", "--rays", "0"]) == 1
    assert capsys.readouterr().err == "fit_sensor: --rays 0 must be at least 1 (rays per view over the fitting cone)\n"
    assert no_fit == []


@pytest.mark.parametrize("options", [["--tmf"], ["--scenes", "sphere"]])
def test_a_json_path_in_a_missing_folder_is_refused_before_the_fit(tool, dataset, tmp_path, capsys, no_fit,
                                                                   options):
    """It failed with a traceback only once the fit (hours, for a full one) had run."""
    out = tmp_path / "nodir" / "out.json"
    assert tool.main(["--dataset", str(dataset), *options, "--json", str(out)]) == 1
    assert capsys.readouterr().err == f"fit_sensor: --json {out}: the folder {out.parent} does not exist\n"
    assert no_fit == []
    assert tool.main(["--dataset", str(dataset), *options, "--json", str(tmp_path / "out.json")]) == 0
    assert no_fit and (tmp_path / "out.json").is_file()


def test_a_damaged_dataset_file_is_one_line(tool, dataset, capsys):
    (dataset / "simulated" / "sphere" / "sphere.json").write_text("not json")
    assert tool.main(["--dataset", str(dataset), "--scenes", "sphere", "--rays", "16", "--iters", "1"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("fit_sensor: ") and err.count("\n") == 1, err
