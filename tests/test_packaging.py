"""The distribution ships every package and maps the three halves under the spadscan namespace."""

from __future__ import annotations

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"spadscan": "spadscan", "protocol": "spadscan.protocol", "daemon": "spadscan.daemon",
           "worker": "spadscan.worker"}


def _config() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_package_folder_is_listed():
    listed = set(_config()["packages"])
    found = set()
    for folder, name in FOLDERS.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((name, *rel)))
    missing = found - listed
    assert not missing, f"packages missing from pyproject.toml: {sorted(missing)}"


def test_halves_install_under_the_namespace_only():
    mapping = _config()["package-dir"]
    assert mapping == {"spadscan": "spadscan", "spadscan.protocol": "protocol", "spadscan.daemon": "daemon",
                       "spadscan.worker": "worker"}
    assert not any(p.split(".")[0] in ("daemon", "worker", "protocol") for p in _config()["packages"])
