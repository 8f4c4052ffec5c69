"""A scan's name stays inside the captures root: `check_scan_name` refuses names with paths or hidden names, and a
name that is a link leading out of the root (a scan created there would write its capture elsewhere)."""

from __future__ import annotations

import pytest

from spadscan.protocol.errors import ConfigError
from spadscan.daemon.scan_job import check_scan_name


@pytest.mark.parametrize("name", ["", "../up", "a/b", ".hidden", "..", "-dash", "x" * 101, 7, None])
def test_names_that_are_not_one_plain_folder_name_are_refused(tmp_path, name):
    with pytest.raises(ConfigError):
        check_scan_name(name, tmp_path)


def test_a_plain_name_is_returned_as_it_is(tmp_path):
    assert check_scan_name("bunny_2026-12.v1+a", tmp_path) == "bunny_2026-12.v1+a"


@pytest.mark.parametrize("target_exists", [True, False])
def test_a_link_in_the_root_that_leads_out_of_it_is_refused(tmp_path, target_exists):
    root, outside = tmp_path / "captures", tmp_path / "elsewhere"
    root.mkdir()
    if target_exists:
        outside.mkdir()
    (root / "scan1").symlink_to(outside)
    with pytest.raises(ConfigError, match="escapes the captures root"):
        check_scan_name("scan1", root)


def test_a_link_to_a_folder_in_the_root_is_taken(tmp_path):
    (tmp_path / "real").mkdir()
    (tmp_path / "alias").symlink_to(tmp_path / "real")
    assert check_scan_name("alias", tmp_path) == "alias"
