"""Convert a file of the public LCSPCData dataset into a capture folder.

FILE.json is a JSON list of measurements. The kind is read from the data: 1024-bin single histograms are the
dataset's simulated scenes (sensor preset lcspc-sim); 9 x 128 histograms with a reference histogram are its real
TMF8820 captures (preset tmf8820), whose joint angles, on-chip depths, confidences, temperature and tick are kept in
each measurement's metadata. Poses stored with a last row of [0, 0, 0, 0] (some real captures) are read as the
rigid transforms they are, with one warning line, when their rotation is valid. The capture's scene record names the
source file, its SHA-256, the kind and, when a ground-truth mesh lies beside the file (<scene>.obj, or the folder's
only .stl for real scenes), its path.

Examples:
  spadscan import-lcspc LCSPCData/simulated/bunny/bunny.json --out captures/bunny
  spadscan import-lcspc LCSPCData/real/pyramid/pyramid.json --out captures/pyramid
"""

from __future__ import annotations

import argparse

from spadscan.cli import add_progress_options, progress_bar_wanted


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("file", metavar="FILE.json", help="an LCSPCData scene file")
    parser.add_argument("--out", required=True, metavar="CAPTURE", help="capture folder to create (holds scan.json)")
    parser.add_argument("--chunk-size", type=int, default=64, metavar="K", help="measurements per chunk (default: 64)")
    parser.add_argument("--scan-id", default=None, help="scan id in the manifest (default: the folder's name)")
    add_progress_options(parser, "do not show progress bars", "none: the last lines say what was imported")


def check_scan_id(scan_id: str, out) -> None:
    """A scan id is a plain name, by the daemon's own rule for scan names (it names folders and jobs)."""
    from pathlib import Path

    from spadscan.daemon.scan_job import check_scan_name
    from spadscan.protocol.errors import ConfigError

    try:
        check_scan_name(scan_id, Path(out).parent)
    except ConfigError as exc:
        raise ConfigError(f"--scan-id: {exc}") from None


def run(args: argparse.Namespace) -> int:
    import sys

    from tqdm import tqdm

    from spadscan.protocol.capture_format import check_new_capture_out
    from spadscan.protocol.folders import check_folder_option
    from spadscan.protocol.lcspc import import_lcspc
    from spadscan.signals import terminate_as_interrupt

    if args.scan_id is not None:
        check_scan_id(args.scan_id, args.out)
    check_folder_option(args.out, "--out")  # a folder that already holds a capture the import refuses, saying so
    check_new_capture_out(args.out)

    bars: dict[str, tqdm] = {}
    show = progress_bar_wanted(args)

    def progress(stage: str, done: int, total: int) -> None:
        if not show:
            return
        if stage not in bars:
            unit, scale = ("B", True) if stage == "read" else ("meas", False)
            bars[stage] = tqdm(total=total, desc=stage, unit=unit, unit_scale=scale, file=sys.stderr,
                               leave=False)
        bar = bars[stage]
        bar.update(done - bar.n)

    try:
        with terminate_as_interrupt():
            s = import_lcspc(args.file, args.out, chunk_size=args.chunk_size, scan_id=args.scan_id,
                             progress=progress)
    finally:
        for bar in bars.values():
            bar.close()
    for warning in s.warnings:
        print(f"spadscan: warning: {warning}", file=sys.stderr)
    for note in s.notes:
        print(f"spadscan: note: {note}", file=sys.stderr)
    shape = " x ".join(str(v) for v in s.hists_shape[1:])
    ref = "" if s.reference_shape is None else ", reference histograms"
    print(f"imported {s.measurements} measurements ({s.kind}, sensor {s.sensor}, histograms {shape}{ref}) "
          f"into {s.out} in {s.chunks} chunk{'s' if s.chunks != 1 else ''}")
    print(f"ground truth: {s.ground_truth if s.ground_truth else 'none found beside the file'}")
    return 0
