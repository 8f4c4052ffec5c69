"""Fixtures of the sweep tests: the tiny sweep file and a Dask cluster that a test starts and stops."""

from __future__ import annotations

from pathlib import Path

import pytest

from sweep_helpers import DaskCluster, write_tiny


@pytest.fixture
def tiny_sweep(tmp_path) -> Path:
    return write_tiny(tmp_path)


@pytest.fixture
def dask_cluster(tmp_path):
    cluster = DaskCluster(tmp_path / "dask")
    cluster.folder.mkdir()
    try:
        yield cluster.start()
    finally:
        cluster.stop()
