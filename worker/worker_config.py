"""How a worker runs (`spadscan worker`): one dataclass with a docstring per setting, checked before any job starts."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from spadscan.protocol.errors import ConfigError

from .watcher import JobOptions


@dataclass
class WorkerConfig:
    """How a worker runs. Times in seconds."""

    root: Path
    """Captures root: its children are scan folders."""
    processes: int = 1
    """Jobs run at once (one child process each)."""
    options: JobOptions = field(default_factory=JobOptions)
    """Preset, budget, device, seed of the jobs this worker queues."""
    queue_dir: Path | None = None
    """Queue folder; default `<root>/.queue`."""
    poll_s: float = 2.0
    """How often the root is scanned and the queue looked at."""
    lease_s: float = 60.0
    """A job whose holder has not renewed its lease for this long is taken over by another worker."""
    max_attempts: int = 3
    """A job whose process dies or whose worker dies is retried until it has been tried this many times."""
    once: bool = False
    """Queue what is there, run until no job is queued or running, then exit."""
    stop_grace_s: float = 10.0
    """On stop, children get SIGTERM and this long to exit before SIGKILL."""
    recon: str | None = None
    """`module:function` replacing the reconstruction (tests only; not on the command line)."""
    child_env: dict[str, str] | None = None
    """Extra environment variables for the job processes."""

    def check(self) -> "WorkerConfig":
        if not (isinstance(self.processes, int) and 1 <= self.processes <= 256):
            raise ConfigError(f"processes {self.processes} must be an integer in [1, 256]")
        for key in ("poll_s", "lease_s", "stop_grace_s"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and 0 < v < 1e6):
                raise ConfigError(f"{key.replace('_s', '')} {v} s must be > 0")
        if not Path(self.root).is_dir():
            raise ConfigError(f"{self.root}: captures root is not a folder")
        return self
