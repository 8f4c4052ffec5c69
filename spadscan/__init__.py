"""spadscan: 3D scanning with a robot arm and a low-cost single-photon time-of-flight sensor."""

__version__ = "0.1.0"
