"""Run the acquisition daemon: one process that owns the arm and the sensor, scans on request and writes capture
folders under the config's captures root.

    spadscan daemon --config rig.toml            run until SIGTERM, Ctrl-C or `spadscan ctl shutdown`
    spadscan daemon --config rig.toml --check    validate the config and the default scan plan, touch nothing

The config is checked completely (unknown keys, bad values, missing files, an unreachable default scan) before any
device is touched. Control it with `spadscan ctl`; examples/README.md documents every config key.
"""

from __future__ import annotations

import sys


def add_arguments(parser) -> None:
    parser.add_argument("--config", required=True, metavar="RIG.toml", help="rig config (TOML; see examples/)")
    parser.add_argument("--check", action="store_true",
                        help="validate the config and the default scan plan, then exit without touching devices")
    parser.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"),
                        help="how much the daemon logs to stderr (default: info)")


def run(args) -> int:
    import asyncio
    import logging

    from spadscan.daemon.app import check_startup, serve
    from spadscan.daemon.config import load_config

    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s spadscan daemon: %(levelname)s %(message)s")
    cfg = load_config(args.config)
    if args.check:
        from spadscan.daemon.scan_plan import build_plan

        plan = build_plan(cfg.scan, cfg.arm, where=f"{cfg.source}: [scan] defaults")
        print(f"{cfg.source}: ok ({cfg.arm.backend} arm, {cfg.sensor.backend} sensor, default scan of {len(plan)} "
              f"poses, {plan.description['travel_m']:.2f} m of travel)")
        return 0
    arm, sensor = check_startup(cfg)
    asyncio.run(serve(cfg, arm, sensor))
    return 0
