"""What `spadscan sweep` refuses in its command line before anything runs, the dry run too.

The dry run only reads the sweep file and the results folder: these checks load torch and Dask only for the options that
need them (--device cuda or auto without --scheduler, and --scheduler): a plan-only run loads neither the runner nor
Dask. (It still imports torch, through the presets' configs that the sweep file is checked against: a fast part's config
lives beside its torch code.)
"""

from __future__ import annotations

from spadscan.protocol.errors import ConfigError


def local_device(device: str) -> str:
    """The device the embedded cluster's points run on (this machine is its worker): 'auto' resolved as the
    reconstruction resolves it (CUDA where torch sees a GPU, else the CPU), so that the cluster is sized for it (one
    worker for a GPU, not one per core sharing it) and the points store the device they ran on. Refuses, in one line,
    'cuda' where torch sees no CUDA device, before anything runs: every point would be simulated and run through the
    baselines, then fail."""
    if device not in ("cuda", "auto"):
        return device
    import torch  # only for 'cuda' and 'auto': the checks themselves load nothing heavy

    if torch.cuda.is_available():
        return "cuda"
    if device == "auto":
        return "cpu"
    raise ConfigError("device 'cuda' asked for, but torch sees no CUDA device on this machine, whose local cluster "
                      "would run the points (use --device cpu or auto, or --scheduler with GPU workers)")


def check_workers(scheduler: str | None, workers: int | None) -> None:
    """Refuse, in one line, a --workers that the run could not use (the dry run refuses it too)."""
    if scheduler is not None and workers is not None:
        raise ConfigError("--workers sizes the embedded cluster; a scheduler's workers are the ones started for it "
                          "(dask worker ADDRESS)")
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers {workers} must be at least 1")


def check_scheduler_address(address: str) -> None:
    """Refuse, in one line, a --scheduler that is no Dask address (a missing port, an unknown scheme) or one this
    command cannot connect to (tls://, wss://), before anything is written."""
    # Only with --scheduler: Dask's address parsing imports Dask (a third of a second), which a sweep on the embedded
    # cluster imports when it starts the cluster, and its dry run never.
    from distributed.comm.addressing import get_address_host_port, parse_address

    try:
        get_address_host_port(address)
        scheme = parse_address(address)[0]
    except ValueError as exc:
        raise ConfigError(f"--scheduler {address!r} is not a Dask scheduler's address, e.g. tcp://HOST:8786 "
                          f"({' '.join(str(exc).split())[:200]})") from None
    if scheme in ("tls", "wss"):
        # Certificates and keys (Dask's security configuration), which this command does not take.
        raise ConfigError(f"--scheduler {address}: a {scheme}:// scheduler needs a Dask security configuration "
                          f"(certificates and keys), which `spadscan sweep` does not take; use the scheduler's "
                          f"tcp:// address (e.g. through an SSH tunnel)")


__all__ = ["local_device", "check_workers", "check_scheduler_address"]
