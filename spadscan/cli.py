"""The `spadscan` console script: a thin dispatcher that imports each subcommand only when it runs.

`spadscan ctl status` must never pay for importing torch, so the table below names modules instead of importing them.
Each command module defines `add_arguments(parser)` and `run(args) -> int` and keeps heavy imports inside `run`.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import re
import sys

from spadscan.parent_watch import watch_parent_from_env
from spadscan.protocol.disk_full import is_disk_full  # the command line's name for it, kept
from spadscan.protocol.folders import file_in_the_way

# name -> (module under spadscan.commands, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("simulate", "render a simulated capture of a mesh (poses, photons, pile-up)"),
    "import-lcspc": ("import_lcspc", "convert an LCSPCData JSON file into a capture folder"),
    "eval": ("evaluate", "compare a mesh with ground truth: Chamfer, accuracy, completeness, F-score"),
    "daemon": ("daemon", "run the acquisition daemon (arm + sensor) from a rig config"),
    "ctl": ("ctl", "talk to a running daemon over its control socket"),
    "calibrate": ("calibrate", "calibrate the rig from a capture (hand-eye: the flange-to-sensor transform)"),
    "worker": ("worker", "watch a captures root and reconstruct every complete scan"),
    "reconstruct": ("reconstruct", "reconstruct one capture into a mesh and a report"),
    "baseline": ("baseline", "run a baseline reconstruction (reprojection, space carving)"),
    "demo": ("demo", "run the whole loop on simulated devices: daemon -> capture -> worker -> mesh"),
    "dashboard": ("dashboard", "serve a local web page that follows the scans, the queue and the reconstructions"),
    "sweep": ("sweep", "sensitivity sweep on Dask: simulate -> reconstruct -> baselines -> metrics over a grid"),
    "sweep-plot": ("sweep_plot", "draw a sweep's Figure A (Chamfer against each parameter) and its HTML table"),
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

            return run_command(lambda _: print(f"spadscan {__version__}"), None)
        if argv and argv[0] not in ("-h", "--help"):
            print(f"spadscan: unknown command {argv[0]!r} (run `spadscan --help` for the list)", file=sys.stderr)
            return 2
        parser.print_help()
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    watch_parent_from_env()  # a child of `spadscan demo` stops when the demo is gone (parent_watch.py)
    module = importlib.import_module(f"spadscan.commands.{COMMANDS[name][0]}")
    parser = argparse.ArgumentParser(prog=f"spadscan {name}", description=module.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    module.add_arguments(parser)
    args = parser.parse_args(_negative_lists_attached(rest))
    empty = _empty_option(rest, FOLDER_OPTIONS)
    if empty:
        print(f"spadscan: error: {empty} is empty (an unset shell variable?): give the folder", file=sys.stderr)
        return 1
    empty = _empty_option(rest, FILE_OPTIONS)
    if empty:
        print(f"spadscan: error: {empty} is empty (an unset shell variable?): give the file", file=sys.stderr)
        return 1
    empty = _empty_positional(parser, args)
    if empty:
        print(f"spadscan: error: {empty} is empty (an unset shell variable?)", file=sys.stderr)
        return 1
    return run_command(module.run, args)


FOLDER_OPTIONS = ("--out", "--root", "--queue", "--lcspc")
"""Options that name a folder: given empty (`--out "$OUT"` with OUT unset) they would mean the current folder, where
a command writes its result among the user's files."""


FILE_OPTIONS = ("--config", "--gt")
"""Options that name a file: given empty they named the current folder, and the error said `.: cannot read` or `.: is
a folder, not a mesh file`."""


def _empty_option(argv: list[str], options: tuple[str, ...]) -> str | None:
    """The first of `options` given an empty value in `argv` (`--out ""` or `--out=`), or None."""
    for i, token in enumerate(argv):
        name, eq, value = token.partition("=")
        if name in options and ((eq and not value) or (not eq and i + 1 < len(argv) and argv[i + 1] == "")):
            return name
    return None


def _empty_positional(parser: argparse.ArgumentParser, args: argparse.Namespace) -> str | None:
    """The name of the first positional argument given empty (`"$CAPTURE"` with CAPTURE unset), or None: to the file
    system an empty path is the current folder, and the error then named '.' instead of the argument."""
    for action in parser._actions:  # argparse keeps no public list of a parser's arguments
        if action.option_strings:
            continue
        value = getattr(args, action.dest, None)
        if value == "":
            return action.metavar or action.dest
        if isinstance(action.choices, dict) and isinstance(action.choices.get(value), argparse.ArgumentParser):
            found = _empty_positional(action.choices[value], args)  # a sub-command's own (calibrate hand-eye)
            if found:
                return found
    return None


_UNSIGNED = r"(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?"
NEGATIVE_LIST = re.compile(rf"-{_UNSIGNED}(,[-+]?{_UNSIGNED})+")
"""A comma-separated list of numbers whose first is negative (`--target -0.1,0,0.1`)."""


def _negative_lists_attached(argv: list[str]) -> list[str]:
    """`--flag -0.1,0,0.1` -> `--flag=-0.1,0,0.1`: argparse takes a value that starts with '-' for an option and
    refuses it, and base-frame coordinates are often negative. A list of numbers is never an option."""
    out: list[str] = []
    for arg in argv:
        flag = out[-1] if out else ""
        if NEGATIVE_LIST.fullmatch(arg) and flag.startswith("--") and flag != "--" and "=" not in flag:
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def run_command(func, args) -> int:
    """Run a command; turn the project's errors into one-line messages and exit code 1, Ctrl-C into 130."""
    from spadscan.protocol.errors import SpadscanError

    try:
        code = int(func(args) or 0)
        sys.stdout.flush()  # here, so that a reader that went away is handled below and not at interpreter exit
        return code
    except SpadscanError as exc:
        print(f"spadscan: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("spadscan: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        if isinstance(exc, BrokenPipeError) and _stdout_gone():
            return _quiet_exit_on_closed_stdout()
        # A file the user named is missing, a disk is full, a socket is gone: one line, not a traceback.
        print(f"spadscan: error: {describe_os_error(exc)}", file=sys.stderr)
        return 1


def add_progress_options(parser: argparse.ArgumentParser, no_progress_help: str, default_help: str,
                         bars: bool = False) -> None:
    """--progress and --no-progress (one or the other) for a command that draws a progress bar on stderr (`bars`:
    several, one after another); `default_help` says what it shows when given neither and stderr is not a
    terminal."""
    bar = "bars" if bars else "bar"
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--progress", action="store_true",
                       help=f"draw the progress {bar} even when standard error is not a terminal (default: the {bar} "
                            f"on a terminal only; in a file or a pipe, {default_help})")
    group.add_argument("--no-progress", action="store_true", help=no_progress_help)


def progress_bar_wanted(args: argparse.Namespace, stream=None) -> bool:
    """Whether a command draws its progress bar: always with --progress, never with --no-progress, else only when
    `stream` (default: standard error) is a terminal. A bar redraws itself with carriage returns, which a log file
    (`2>run.log`, cron, systemd) keeps every one of: kilobytes of frames on one line."""
    if getattr(args, "no_progress", False):
        return False
    if getattr(args, "progress", False):
        return True
    return is_terminal(sys.stderr if stream is None else stream)


def is_terminal(stream) -> bool:
    """Whether `stream` is a terminal (False for one that is closed or has no file behind it)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError, OSError):
        return False


SIGPIPE_EXIT = 128 + 13
"""Exit status of a command whose reader closed its output (`spadscan ctl status | head -1`), as a shell reports a
program ended by SIGPIPE."""


def _stdout_gone() -> bool:
    """True when stdout is a pipe whose reading end is closed (poll reports an error on the write end)."""
    import select

    try:
        fd = sys.stdout.fileno()
        poller = select.poll()
        poller.register(fd, 0)
        return any(ev & (select.POLLERR | select.POLLHUP) for _, ev in poller.poll(0))
    except (AttributeError, OSError, ValueError):  # no real stdout (captured in tests): not a closed pipe
        return False


def _quiet_exit_on_closed_stdout() -> int:
    """End quietly: the reader has what it wanted. Point stdout at /dev/null so that Python's final flush of the
    unwritten rest does not complain at exit."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    finally:
        os.close(devnull)
    return SIGPIPE_EXIT


def describe_os_error(exc: OSError) -> str:
    """One line for an OSError: what went wrong and with which path, with a hint where the fix is clear."""
    import errno
    import os

    path = exc.filename
    if is_disk_full(exc):
        where = f"{path}: " if path else ""
        return f"{where}the disk is full (no space left on the device); free some space or write elsewhere"
    if isinstance(exc, FileExistsError) and path and not os.path.isdir(path):
        return f"{path}: exists and is not a folder"
    if isinstance(exc, NotADirectoryError) and path:
        blocker = file_in_the_way(path)
        if blocker is not None:
            return f"{blocker}: is a file, not a folder (needed for {path})"
        return f"{path}: is not a folder"
    if exc.errno == errno.EACCES and path:
        return f"{path}: permission denied"
    where = f" ({path})" if path else ""
    return f"{exc.strerror or exc}{where}"


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
