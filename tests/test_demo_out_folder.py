"""`spadscan demo --out DIR` never replaces a rig.toml it did not write (a lab's own rig, with its hand-eye and ports),
and never writes into a capture: both are refused in one line before anything starts or is created. A rig.toml an
earlier demo run wrote is the demo's to write again, so that a run into the folder of an earlier one goes on."""

from __future__ import annotations

from pathlib import Path

import pytest

from spadscan.cli import main
from spadscan.daemon.config import load_config
from spadscan.demo import (RIG_CONFIG, DemoError, DemoOptions, Processes, check_options, run_demo,
                           write_rig_config)

LAB_RIG = """captures = "/home/lab/spadscan-captures"
[arm]
backend = "ur"
host = "192.168.1.20"
hand_eye = [0.01, 0.02, 0.11, 0.0, 0.0, 1.5708]
[sensor]
backend = "serial"
port = "/dev/ttyACM0"
"""
"""A rig config of the user's own (README step 3), in the folder they point the demo at."""

EARLIER_DEMO_RIG = """# Written by `spadscan demo`: simulated devices only.
captures = "{out}/captures"
"""
"""The first lines of a rig config a demo run into `out` wrote before the header gained its second line."""


@pytest.fixture
def nothing_starts(monkeypatch):
    """Fail the test if the demo starts a process."""
    def start(self, name, argv, log):
        raise AssertionError(f"the demo started {name} although its --out is refused")

    monkeypatch.setattr(Processes, "start", start)


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def one_line_error(capsys) -> str:
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.count("\n") == 1 and "Traceback" not in captured.err, captured
    return captured.err.strip()


def test_the_command_refuses_an_out_holding_the_users_own_rig_config_and_keeps_it(tmp_path, monkeypatch, capsys,
                                                                                   nothing_starts):
    monkeypatch.chdir(tmp_path)
    Path(RIG_CONFIG).write_text(LAB_RIG)
    before = listing(tmp_path)
    assert main(["demo", "--out", "."]) == 1
    err = one_line_error(capsys)
    assert err == ("spadscan: error: rig.toml is not a rig config the demo wrote: the demo would replace it with its "
                   "own; give the demo a new folder (--out DIR), or move rig.toml away"), err
    assert Path(RIG_CONFIG).read_text() == LAB_RIG, "the user's rig config is kept as it was"
    assert listing(tmp_path) == before, "no captures/, logs/ or anything else made beside it"


def test_run_demo_and_write_rig_config_refuse_it_too(tmp_path, nothing_starts):
    (tmp_path / RIG_CONFIG).write_text(LAB_RIG)
    with pytest.raises(DemoError, match="is not a rig config the demo wrote"):
        run_demo(DemoOptions(out=tmp_path), progress_factory=None)
    with pytest.raises(DemoError, match="is not a rig config the demo wrote"):
        write_rig_config(DemoOptions(out=tmp_path), tmp_path / "captures", tmp_path / "d.sock", None)
    assert (tmp_path / RIG_CONFIG).read_text() == LAB_RIG


def test_a_rig_toml_that_is_a_folder_is_refused_naming_why(tmp_path):
    (tmp_path / RIG_CONFIG).mkdir()
    with pytest.raises(DemoError) as info:
        check_options(DemoOptions(out=tmp_path))
    assert str(info.value).startswith(f"{tmp_path / RIG_CONFIG} is not a rig config the demo wrote (Is a directory)")


@pytest.mark.parametrize("earlier", ["this version", "an earlier version"])
def test_the_rig_config_of_an_earlier_demo_run_is_written_anew(tmp_path, sock_dir, earlier):
    """A run into the folder of an earlier run passes the check and replaces the earlier run's config."""
    opts = DemoOptions(out=tmp_path, views=8)
    if earlier == "this version":
        write_rig_config(DemoOptions(out=tmp_path, views=16), tmp_path / "captures", sock_dir / "d.sock", None)
    else:
        (tmp_path / RIG_CONFIG).write_text(EARLIER_DEMO_RIG.format(out=tmp_path.resolve()))
    check_options(opts)
    config = load_config(write_rig_config(opts, tmp_path / "captures", sock_dir / "d.sock", None))
    assert config.scan.views == 8


def test_a_copy_of_a_demo_rig_config_edited_in_another_folder_is_the_users(tmp_path, sock_dir):
    """The demo's header survives a copy: the copy names the captures of the folder it came from, not its own."""
    demo, lab = tmp_path / "demo", tmp_path / "lab"
    demo.mkdir()
    lab.mkdir()
    written = write_rig_config(DemoOptions(out=demo), demo / "captures", sock_dir / "d.sock", None)
    edited = written.read_text().replace("speed = 0.5", "speed = 0.2  # my edit")
    (lab / RIG_CONFIG).write_text(edited)
    with pytest.raises(DemoError, match="is not a rig config the demo wrote"):
        check_options(DemoOptions(out=lab))
    assert (lab / RIG_CONFIG).read_text() == edited
    check_options(DemoOptions(out=demo))  # the demo's own, in its own folder: written anew


@pytest.mark.parametrize("inside", [False, True])
def test_the_command_refuses_an_out_that_is_or_lies_inside_a_capture(tmp_path, monkeypatch, capsys,
                                                                   nothing_starts, inside):
    monkeypatch.chdir(tmp_path)
    Path("cap1").mkdir()
    Path("cap1", "scan.json").write_text("{}")
    before = listing(tmp_path)
    out = "cap1/demo" if inside else "cap1"
    assert main(["demo", "--out", out]) == 1
    err = one_line_error(capsys)
    where = f"lies inside the capture {tmp_path.resolve() / 'cap1'}" if inside else "is a capture"
    assert err == (f"spadscan: error: --out {out} {where} (it holds scan.json): the demo's captures, logs and rig "
                   f"config would be mixed into its measurements; give the demo a new folder (--out DIR)"), err
    assert listing(tmp_path) == before, "nothing written into the capture"


@pytest.mark.parametrize("held", [".spadscan-daemon.lock", ".queue"])
def test_the_command_refuses_an_out_that_is_a_lab_captures_root(tmp_path, monkeypatch, capsys, nothing_starts, held):
    """A daemon's captures root (its lock) or a worker's (its queue) holds the lab's scans: the demo's own daemon,
    worker, logs and rig config are not mixed into them."""
    monkeypatch.chdir(tmp_path)
    Path("caps").mkdir()
    (Path("caps") / held).mkdir() if held == ".queue" else (Path("caps") / held).write_text("")
    before = listing(tmp_path)
    assert main(["demo", "--out", "caps"]) == 1
    err = one_line_error(capsys)
    assert err == (f"spadscan: error: --out caps is a captures root (it holds {held}): the demo's captures, logs and "
                   f"rig config would be mixed into its scans; give the demo a new folder (--out DIR)"), err
    assert listing(tmp_path) == before, "nothing written into the captures root"
