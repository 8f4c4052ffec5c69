"""Run the acquisition daemon: one process that owns the arm and the sensor, scans on request and writes capture
folders under the config's captures root.

    spadscan daemon --config rig.toml            run until SIGTERM, SIGHUP, Ctrl-C or `spadscan ctl shutdown`
    spadscan daemon --config rig.toml --check    validate everything start-up validates, touch no device

The config is checked completely (unknown keys, bad values, missing or unreadable mesh and firmware files, an
unreachable default scan, a missing serial port or I2C bus, a socket path taken by another file or served by another
daemon, a captures root another daemon holds) before any device is touched; `--check` runs the same checks without
connecting, creating the captures root or claiming the socket (reading the config does make the default socket's
private folder, /tmp/spadscan-<uid>, mode 0700, when `socket` is left out). Its exit status is 0 when the config is
valid, 1 with a one-line error otherwise. A daemon already serving the config's socket (this config's own daemon,
running) leaves the config valid: `--check` says so in its line, with the daemon's pid (it asks that daemon for its
`status`, as `spadscan ctl status` does), and exits 0; the captures root is checked unless that daemon holds it. One
daemon runs per captures root: it holds a lock on <captures>/.spadscan-daemon.lock for its life (released by the
kernel if it dies). Control it with `spadscan ctl`; examples/README.md documents every config key.
"""

from __future__ import annotations

import sys


def add_arguments(parser) -> None:
    parser.add_argument("--config", required=True, metavar="RIG.toml", help="rig config (TOML; see examples/)")
    parser.add_argument("--check", action="store_true",
                        help="run every start-up check (config, default scan, mesh, firmware image, sensor port, "
                             "socket and captures root free), then exit without touching devices: exit status 0 "
                             "when the config is valid, also when a daemon already runs on its socket (said on the "
                             "same line), 1 with a one-line error otherwise")
    parser.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"),
                        help="how much the daemon logs to stderr (default: info)")


def utc_formatter():
    """The log's line format: ISO 8601 UTC times ending in Z (2026-12-05T09:02:29.212Z), the clock of scan.json, the
    dashboard and `worker --status`, so that a log line and a status time compare without a zone offset."""
    import logging
    import time

    formatter = logging.Formatter("%(asctime)s.%(msecs)03dZ spadscan daemon: %(levelname)s %(message)s",
                                  datefmt="%Y-%m-%dT%H:%M:%S")
    formatter.converter = time.gmtime
    return formatter


def run(args) -> int:
    import asyncio
    import logging

    from spadscan.daemon.app import check_only, check_startup, serve
    from spadscan.daemon.config import load_config

    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(utc_formatter())
    logging.basicConfig(level=args.log_level.upper(), handlers=[handler])
    cfg = load_config(args.config)
    if args.check:
        plan, running = check_only(cfg)  # running: None, or that a daemon already serves the socket
        rig = (f"{cfg.arm.backend} arm, {cfg.sensor.backend} sensor, default scan of {len(plan)} poses, "
               f"{plan.description['travel_m']:.2f} m of travel")
        if running is None:
            print(f"{cfg.source}: ok ({rig})")
        else:
            print(f"{cfg.source}: the config is valid ({rig}); {running}")
        return 0
    arm, sensor, lock = check_startup(cfg)
    with lock:  # held until the daemon has stopped: another daemon may then take the captures root
        asyncio.run(serve(cfg, arm, sensor, lock))
    return 0
