"""A check the TMF8820 backends share: their captures must be described by the `tmf8820` sensor model."""

from __future__ import annotations

from spadscan.protocol.errors import ConfigError


def check_tmf8820_preset(section, where: str) -> None:
    """ConfigError unless the [sensor] preset describes a TMF8820."""
    if section.preset != "tmf8820":
        raise ConfigError(f"{where} preset {section.preset!r} does not describe a TMF8820 (backend "
                          f"{section.backend!r} needs preset 'tmf8820')")
