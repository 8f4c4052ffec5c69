"""The project's exceptions. Library code raises these; only the CLI turns them into exit codes and one-line messages."""


class SpadscanError(Exception):
    """Base of every error spadscan raises on purpose. Its message is one line a user can act on."""


class SensorModelError(SpadscanError):
    """A sensor model record is malformed or inconsistent."""


class CaptureError(SpadscanError):
    """A capture folder is missing, malformed, corrupt or in the wrong state."""


class MeshError(SpadscanError):
    """A mesh file cannot be read or is unusable (empty, non-finite, wrong units)."""


class SimulationError(SpadscanError):
    """A simulation request is out of range (bad pose schedule, photon settings, sensor)."""


class DatasetError(SpadscanError):
    """A dataset file does not have the expected structure."""


class ConfigError(SpadscanError):
    """A configuration file or option is invalid."""


class DeviceError(SpadscanError):
    """A device failed, timed out or reported a fault. The message names the device and what it waited for."""
