"""The `spadscan` console script: a thin dispatcher that imports each subcommand only when it runs.

`spadscan ctl status` must never pay for importing torch, so the table below names modules instead of importing them.
Each command module defines `add_arguments(parser)` and `run(args) -> int` and keeps heavy imports inside `run`.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

# name -> (module under spadscan.commands, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("simulate", "render a simulated capture of a mesh (poses, photons, pile-up)"),
    "import-lcspc": ("import_lcspc", "convert an LCSPCData JSON file into a capture folder"),
    "eval": ("evaluate", "compare a mesh with ground truth: Chamfer, accuracy, completeness, F-score"),
    "daemon": ("daemon", "run the acquisition daemon (arm + sensor) from a rig config"),
    "ctl": ("ctl", "talk to a running daemon over its control socket"),
    "worker": ("worker", "watch a captures root and reconstruct every complete scan"),
    "reconstruct": ("reconstruct", "reconstruct one capture into a mesh and a report"),
    "baseline": ("baseline", "run a baseline reconstruction (reprojection, space carving)"),
    "demo": ("demo", "run the whole loop on simulated devices: daemon -> capture -> worker -> mesh"),
}


def _top_parser() -> argparse.ArgumentParser:
    lines = [f"  {name:<14}{help_}" for name, (_, help_) in COMMANDS.items() if _available(name)]
    parser = argparse.ArgumentParser(
        prog="spadscan",
        description="3D scanning with a robot arm and a low-cost single-photon time-of-flight sensor.",
        epilog="commands:\n" + "\n".join(lines) + "\n\nRun `spadscan COMMAND --help` for a command's options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="store_true", help="print the version and exit")
    parser.add_argument("command", nargs="?", help="the command to run")
    return parser


def _available(name: str) -> bool:
    return importlib.util.find_spec(f"spadscan.commands.{COMMANDS[name][0]}") is not None


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] not in COMMANDS or not _available(argv[0]):
        parser = _top_parser()
        if argv and argv[0] == "--version":
            from spadscan import __version__

            print(f"spadscan {__version__}")
            return 0
        if argv and argv[0] not in ("-h", "--help"):
            print(f"spadscan: unknown command {argv[0]!r} (run `spadscan --help` for the list)", file=sys.stderr)
            return 2
        parser.print_help()
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    module = importlib.import_module(f"spadscan.commands.{COMMANDS[name][0]}")
    parser = argparse.ArgumentParser(prog=f"spadscan {name}", description=module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    module.add_arguments(parser)
    args = parser.parse_args(rest)
    return run_command(module.run, args)


def run_command(func, args) -> int:
    """Run a command; turn the project's errors into one-line messages and exit code 1, Ctrl-C into 130."""
    from spadscan.protocol.errors import SpadscanError

    try:
        return int(func(args) or 0)
    except SpadscanError as exc:
        print(f"spadscan: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("spadscan: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        # A file the user named is missing, a disk is full, a socket is gone: one line, not a traceback.
        where = f" ({exc.filename})" if getattr(exc, "filename", None) else ""
        print(f"spadscan: error: {exc.strerror or exc}{where}", file=sys.stderr)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
