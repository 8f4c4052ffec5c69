"""Fixtures of the end-to-end tests: a folder of background processes that are always stopped, and a factory of
daemons on rig configs written into tmp_path, their sockets in the short folder of tests/conftest.py's sock_dir."""

from __future__ import annotations

import pytest

from e2e_helpers import Daemon, Procs, rig_dict, toml_text


@pytest.fixture
def procs(tmp_path):
    """Background processes of the test; every one is stopped at the end, also when the test fails."""
    p = Procs(tmp_path)
    try:
        yield p
    finally:
        p.stop_all()


@pytest.fixture
def make_daemon(tmp_path, procs, sock_dir):
    """make_daemon(captures=None, name='rig', **sections) -> a Daemon (not started) on a rig config written into
    tmp_path; sections: arm=/sensor=/scan=/top= key overrides of e2e_helpers.BASE_RIG."""

    def make(captures=None, name: str = "rig", **sections) -> Daemon:
        captures = tmp_path / "caps" if captures is None else captures
        sock = sock_dir / "ctl.sock"
        rig = tmp_path / f"{name}.toml"
        rig.write_text(toml_text(rig_dict(captures, sock, **sections)))
        return Daemon(procs, rig, sock, captures)

    return make
