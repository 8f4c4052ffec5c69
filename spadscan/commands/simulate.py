"""Render a simulated capture of a mesh: poses from a schedule, ray-cast transients, pulse, background, pile-up and
photon counts, written as a complete capture folder.

MESH is a mesh file (OBJ, PLY, STL, OFF, ...; metres: one of those four formats over 5 m across is read as
millimetres, and said so) or `builtin:NAME` for a built-in scene (listed below, with the split each belongs to).
The sensor circles TARGET at RADIUS metres on a Fibonacci spiral (like LCSPCData: 256 views, 0.5 m, from 86 degrees
down to the horizon) or on elevation rings (in a band of zero width, --min-elevation = --max-elevation, at most 2
rings: the second is offset by half a step, a third would repeat the first's poses), always looking at TARGET;
--jitter-deg turns each view by a random rotation about the sensor, like the dataset's `_random` captures. --table
puts the object on a horizontal table (black by default), which real captures see in every histogram; the
reconstruction then finds its height, as it does for a real capture. Views that would put the sensor inside the
mesh or on or under the table top are refused (no sensor can stand there); on a table the spiral starts 10 degrees
up unless --min-elevation says otherwise; views less than 1 cm above the table top (the spiral's lowest from 0
degrees, 1 mm above it at 256 views, whose histograms the table floods) and views that see nothing of the mesh are
warned about, and so is a capture whose views hold most of their detections in their first bins (pile-up: a surface
touching the sensor, or --ambient or --power so high that nothing behind the first bins is seen) or most of whose
histograms are saturated (pile-up again: the first return stops nearly every laser cycle, as at --power 100).

--out must be a new or empty folder that can be written into. Ctrl-C (or SIGTERM) stops a simulation, exit status 130:
the chunks written so far stay in --out as a partial capture marked aborted, which cannot be resumed; the command
says how many views it holds and how to go on (remove it and run again, or give --out a new folder).

Examples:
  spadscan simulate bunny.obj --out captures/bunny-sim --sensor lcspc-sim --views 256
  spadscan simulate builtin:head-on-can --out captures/head-on-can --sensor tmf8820 --table \\
      --views 120 --schedule rings --rings 8 --min-elevation 36 --max-elevation 83 --radius 0.45 --target 0 0 0.25
"""

from __future__ import annotations

import argparse
import math
import shlex
from pathlib import Path

from spadscan.cli import add_progress_options, progress_bar_wanted
from spadscan.protocol.scenes import scene_listing
from spadscan.protocol.schedules import MAX_VIEWS_PER_RING, RINGS_BAND_DEG
from spadscan.protocol.sim_table import DEFAULT_ALBEDO as DEFAULT_TABLE_ALBEDO

SCHEDULES = ("fibonacci", "rings")
DEFAULT_RINGS = 4
SPIRAL_BAND = (0.0, 90.0)  # degrees: the dataset's spiral, from 86.4 down to 0.1 deg at 256 views
TABLE_SPIRAL_LOW_DEG = 10.0
"""The spiral's lowest elevation by default on a table (degrees): from 0 its lowest views stood 1-9 mm above the
top, which floods their histograms (a torus on edge came out 4.61 mm so, 2.08 from 10 degrees up); the rings' band
starts there too."""
RINGS_BAND = RINGS_BAND_DEG  # degrees: the rings' own band (rings stand at both ends)
MIN_CYCLES = 100
"""The fewest laser cycles per histogram simulate takes: a sensor counts at most one photon a cycle, so fewer leave a
histogram of hundreds of bins a few counts, mostly none (the sphere at 100 cycles: ~4 counts at its peak, 57 in all;
at 1 cycle half the histograms were empty, and reconstruct refused the capture)."""
NEAR_TABLE_M = 0.01
"""A sensor less than this (metres) above the table top sees the top at a grazing angle from next to no distance:
its histograms may be flooded by the table (pile-up). Warned about, not refused: a real sensor may sit that low."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mesh", metavar="MESH",
                        help="mesh file in metres (millimetres detected), or builtin:NAME for a built-in scene")
    parser.add_argument("--out", required=True, metavar="CAPTURE", help="capture folder to create (holds scan.json)")
    parser.add_argument("--sensor", default="lcspc-sim", choices=("tmf8820", "lcspc-sim"),
                        help="sensor model preset (default: lcspc-sim)")
    parser.add_argument("--views", type=int, default=256, help="number of views (default: 256)")
    parser.add_argument("--schedule", default="fibonacci", choices=SCHEDULES,
                        help="fibonacci: equal-area spiral (default); rings: --rings elevation rings of views/rings")
    parser.add_argument("--rings", type=int, default=None,
                        help=f"number of elevation rings for --schedule rings (default: {DEFAULT_RINGS})")
    parser.add_argument("--min-elevation", type=float, default=None, metavar="DEG",
                        help="lowest elevation of the schedule band in degrees (default: 0 for the spiral, "
                             f"{TABLE_SPIRAL_LOW_DEG:g} on a --table, where lower views stand on its top; "
                             f"{RINGS_BAND[0]:g} for rings)")
    parser.add_argument("--max-elevation", type=float, default=None, metavar="DEG",
                        help="highest elevation of the schedule band in degrees (default: 90 for the spiral, which "
                             "puts its top view at 86.4 deg for 256 views, as in LCSPCData; "
                             f"{RINGS_BAND[1]:g} for rings, whose top ring stands at it: a ring at 90 would be one "
                             "viewpoint)")
    parser.add_argument("--radius", type=float, default=0.5, metavar="M",
                        help="distance from the sensor to the target in metres (default: 0.5)")
    parser.add_argument("--target", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                        help="point every view looks at, metres (default: 0 0 0)")
    parser.add_argument("--jitter-deg", type=float, default=0.0, metavar="D",
                        help="turn each view by a random rotation of up to D degrees (default: 0)")
    parser.add_argument("--ambient", type=float, default=None, metavar="PHOTONS_PER_BIN_PER_CYCLE",
                        help="background photons per bin per cycle (default: the sensor preset's)")
    parser.add_argument("--power", type=float, default=1.0, metavar="P",
                        help="laser power relative to the sensor preset (default: 1)")
    parser.add_argument("--cycles", type=int, default=None, metavar="N",
                        help=f"laser cycles per histogram, at least {MIN_CYCLES} (default: the sensor preset's)")
    parser.add_argument("--albedo", type=float, default=1.0, help="Lambertian albedo of the mesh (default: 1)")
    parser.add_argument("--rays-per-zone", type=int, default=None, metavar="R",
                        help="rays cast per zone per view (default: 4096 per view shared by the zones, at least "
                             "about 512 each: a rectangular zone rounds them to its grid of rays, 504 on the "
                             "TMF8820's)")
    table = parser.add_argument_group("table")
    table.add_argument("--table", action="store_true",
                       help="stand the object on a horizontal table (a 2 m square at --table-height)")
    table.add_argument("--table-albedo", type=float, default=None, metavar="A",
                       help=f"Lambertian albedo of the table, relative to the sensor preset like --albedo (default: "
                            f"{DEFAULT_TABLE_ALBEDO:g}, a black table)")
    table.add_argument("--table-height", type=float, default=None, metavar="M",
                       help="height of the table top in metres (default: 0, where built-in scenes stand); refused "
                            "more than 3 mm above the mesh's lowest point, warned about more than 10 mm below it")
    parser.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default: 0)")
    parser.add_argument("--chunk-size", type=int, default=64, metavar="K", help="measurements per chunk (default: 64)")
    add_progress_options(parser, "do not show a progress bar", "none: the last line says what was written")
    parser.epilog = scene_listing()


def check_options(args) -> None:
    """One-line errors for options that make no physical sense, before the mesh is loaded or anything written."""
    import math

    from spadscan.protocol.errors import SimulationError

    if args.views < 1:
        raise SimulationError(f"--views {args.views} must be at least 1")
    if not (args.radius > 0 and math.isfinite(args.radius)):
        raise SimulationError(f"--radius {args.radius} m must be a finite distance > 0")
    if args.seed < 0:  # numpy's SeedSequence takes only non-negative integers
        raise SimulationError(f"--seed {args.seed} must be an integer >= 0")
    # The upper limits (jitter 180 degrees, power 1e9) are the simulator's own checks; these are the lower ones it
    # lets through: a negative jitter would be ignored, and power 0 (the laser off, kept in the library for dark
    # frames) makes a capture of background alone that nothing downstream can use.
    if not (args.jitter_deg >= 0):
        raise SimulationError(f"--jitter-deg {args.jitter_deg:g} must be >= 0 degrees (0: every view looks at the "
                              f"target)")
    if args.cycles is not None and args.cycles < MIN_CYCLES:
        raise SimulationError(f"--cycles {args.cycles} is too few: at least {MIN_CYCLES} laser cycles per histogram "
                              f"(a sensor counts at most one photon a cycle; fewer leave the histograms nearly empty)")
    if not (args.power > 0):
        raise SimulationError(f"--power {args.power:g} must be > 0 (relative to the sensor preset; 0 is the laser "
                              f"switched off)")
    for option, value in (("--table-albedo", args.table_albedo), ("--table-height", args.table_height)):
        if value is not None and not args.table:
            raise SimulationError(f"{option} {value:g} is for a table: add --table")


def make_table(args):
    """The table the options ask for (a SimTable), or None."""
    from spadscan.protocol.sim_table import SimTable

    if not args.table:
        return None
    return SimTable(height_m=0.0 if args.table_height is None else args.table_height,
                    albedo=DEFAULT_TABLE_ALBEDO if args.table_albedo is None else args.table_albedo).check()


def check_table_under(table, mesh, given: bool):
    """None, or a warning, for a table (SimTable or None) under the mesh (metres); a one-line SimulationError when
    the table top lies above the mesh's lowest point (it would cut the object, or hang above it: a height typed in
    millimetres, say). given: whether --table-height set the height (else it is the default, z = 0)."""
    from spadscan.protocol.errors import SimulationError
    from spadscan.protocol.sim_table import CUT_TOLERANCE_M, FLOAT_WARN_M

    if table is None:
        return None
    lowest = float(mesh.bounds[0][2])
    gap = table.gap_below(lowest)
    where = f"--table-height {table.height_m:g}" if given else "the default --table-height 0"
    if gap < -CUT_TOLERANCE_M:
        raise SimulationError(f"{where} puts the table top {_length(-gap)} above the object's lowest point (z = "
                              f"{lowest:.4g} m): it would cut the object or hang above it; stand the object on it "
                              f"with --table-height {lowest:.4g} (metres)")
    if gap > FLOAT_WARN_M:
        return (f"the object's lowest point (z = {lowest:.4g} m) floats {_length(gap)} above the table ({where}): "
                f"it does not stand on it (--table-height {lowest:.4g} puts it there, metres)")
    return None


def near_table_note(poses, table) -> str | None:
    """A warning naming the views whose sensor lies less than NEAR_TABLE_M above the table top (over it), or None.
    Views on or under the top are `misplaced_views_note`'s (refused)."""
    import numpy as np

    if table is None:
        return None
    eyes = np.asarray(poses, np.float64)[:, :3, 3]
    near = table.below_top(eyes - [0.0, 0.0, NEAR_TABLE_M]) & ~table.below_top(eyes)
    if not near.any():
        return None
    idx = np.flatnonzero(near)
    listed = ", ".join(str(i) for i in idx[:8]) + (", ..." if len(idx) > 8 else "")
    lowest = float(eyes[near, 2].min()) - table.height_m
    return (f"warning: {len(idx)} of {len(eyes)} views ({listed}) put the sensor within {NEAR_TABLE_M * 100:g} cm "
            f"above the table top (the lowest {lowest * 1e3:.2f} mm above it): their histograms may be flooded by "
            f"the table; a higher --min-elevation (degrees) lifts them")


def _length(m: float) -> str:
    """A length for a message: millimetres under a metre, metres from there (a height typed in millimetres)."""
    return f"{m * 1e3:.0f} mm" if m < 1.0 else f"{m:.4g} m"


def repeated_poses(args) -> str | None:
    """Why the schedule would put two views on one pose (one line naming this command's flags), or None. The same
    rules as `protocol.schedules`, whose own refusals name no flags (the daemon's config names its keys)."""
    from spadscan.protocol import schedules

    lo, hi = args.min_elevation, args.max_elevation
    band = "widen the band (--min-elevation below --max-elevation, degrees)"
    if args.schedule == "fibonacci":
        pole = schedules.spiral_at_pole_deg(args.views, lo, hi)
        return None if pole is None else (
            f"--views {args.views} in a spiral band of zero width at {pole:+g} deg elevation stand at one viewpoint "
            f"(straight {'above' if pole > 0 else 'below'} the target); {band}")
    per_ring = args.views // args.rings
    pole = schedules.ring_at_pole_deg(args.rings, per_ring, lo, hi)
    if pole is not None:
        flag = "--max-elevation" if pole > 0 else "--min-elevation"
        return (f"a ring at {pole:+g} deg elevation puts its {per_ring} views at one viewpoint (straight "
                f"{'above' if pole > 0 else 'below'} the target); keep {flag} strictly between -90 and 90 (degrees)")
    repeat = schedules.rings_repeat_note(args.rings, lo, hi)
    return None if repeat is None else f"--rings {args.rings}: {repeat}; {band}, or use --rings 1"


def make_poses(args):
    """(poses (n, 4, 4), schedule record) from the command-line options."""
    import numpy as np

    from spadscan.protocol import schedules
    from spadscan.protocol.errors import SimulationError

    band = SPIRAL_BAND if args.schedule == "fibonacci" else RINGS_BAND
    lifted = args.table and (args.max_elevation is None or args.max_elevation >= TABLE_SPIRAL_LOW_DEG)
    low = max(band[0], TABLE_SPIRAL_LOW_DEG) if lifted else band[0]  # (a band asked for below it: as before)
    args.min_elevation = low if args.min_elevation is None else args.min_elevation
    args.max_elevation = band[1] if args.max_elevation is None else args.max_elevation
    common = dict(radius_m=args.radius, target=tuple(args.target), min_elevation_deg=args.min_elevation,
                  max_elevation_deg=args.max_elevation)
    record = {"kind": args.schedule, "views": args.views, "radius_m": args.radius, "target_m": list(args.target),
              "min_elevation_deg": args.min_elevation, "max_elevation_deg": args.max_elevation,
              "jitter_deg": args.jitter_deg, "seed": args.seed}
    if args.schedule == "fibonacci":
        if args.rings is not None:
            raise SimulationError(f"--rings {args.rings} is for --schedule rings (the fibonacci spiral has none)")
    else:
        args.rings = DEFAULT_RINGS if args.rings is None else args.rings
        if not (1 <= args.rings <= args.views):
            raise SimulationError(f"--rings {args.rings} must lie in [1, views = {args.views}]")
        if args.views % args.rings:
            raise SimulationError(f"--views {args.views} is not a multiple of --rings {args.rings}")
        if args.views // args.rings > MAX_VIEWS_PER_RING:
            raise SimulationError(f"--views {args.views} in --rings {args.rings} is {args.views // args.rings} views "
                                  f"per ring; a ring holds at most {MAX_VIEWS_PER_RING}")
    # A band outside [-90, 90] degrees, or upside down, is the schedules' own refusal; poses repeated in a band that
    # is fine otherwise are refused here, naming this command's flags.
    repeated = repeated_poses(args) if -90.0 <= args.min_elevation <= args.max_elevation <= 90.0 else None
    if repeated:
        raise SimulationError(repeated)
    if args.schedule == "fibonacci":
        poses = schedules.fibonacci_hemisphere(args.views, **common)
    elif args.rings > 1 and args.min_elevation == args.max_elevation:
        # Rings in a band of zero width that repeat no pose (2 rings, repeated_poses said): one ring of twice the
        # views, the second ring the first turned by half a step. elevation_rings refuses any rings in such a band,
        # by the rule of the daemon's config, which allows it for one ring only; the limit on views per ring holds.
        per_ring = args.views // args.rings
        ring = schedules.elevation_rings(1, per_ring, **common)
        poses = np.concatenate([ring, schedules.turned_about_vertical(ring, math.pi / per_ring, args.target)])
    else:
        poses = schedules.elevation_rings(args.rings, args.views // args.rings, **common)
    if args.schedule == "rings":
        record.update(rings=args.rings, per_ring=args.views // args.rings)
    if args.jitter_deg > 0:
        rng = np.random.default_rng(np.random.SeedSequence([args.seed, 1]))
        poses = schedules.jitter_orientations(poses, args.jitter_deg, rng)
    return poses, record


def left_behind(out, planned: int) -> str | None:
    """What an interrupted simulation left in `out` and how to go on, or None when it left no capture there (stopped
    before it began writing). The capture is marked aborted (a simulation cannot be resumed), and a new one is only
    made in a new or empty folder."""
    from spadscan.protocol.capture_format import MANIFEST, read_json
    from spadscan.protocol.errors import CaptureError
    from spadscan.worker.outputs import chunk_views

    try:
        state = read_json(Path(out) / MANIFEST).get("state")
        views = len(set().union(*chunk_views(out).values()))
    except (CaptureError, OSError):
        return None
    return (f"interrupted after {views} of {planned} views; the partial capture {out} is marked {state}: remove it "
            f"(rm -r {shlex.quote(str(out))}) and run again, or give --out a new folder")


def run(args) -> int:
    import sys
    import time

    from spadscan.protocol.capture_format import MANIFEST, check_new_capture_out
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.protocol.folders import check_folder_option
    from spadscan.protocol.mesh_io import MM_EXTENT_THRESHOLD_M, load_mesh_spec
    from spadscan.protocol.sensor_presets import sensor_preset
    from spadscan.protocol.simulator import SimSettings, flooded_note, saturated_note, simulate_capture
    from spadscan.signals import terminate_as_interrupt

    check_options(args)
    check_folder_option(args.out, "--out")  # named, before the mesh is loaded; not a bare OS error at the writer's
    check_new_capture_out(args.out)
    had_capture = (Path(args.out) / MANIFEST).exists()  # a capture there before this run is none of its own
    table = make_table(args)
    mesh, scene = load_mesh_spec(args.mesh)
    if scene.get("mesh_units") == "mm":
        print(f"{args.mesh}: read as millimetres (over {MM_EXTENT_THRESHOLD_M:g} m across as metres)", file=sys.stderr)
    floating = check_table_under(table, mesh, given=args.table_height is not None)
    if floating:
        print(f"spadscan: warning: {floating}", file=sys.stderr)
    poses, schedule = make_poses(args)
    near = near_table_note(poses, table)  # said only: the views are rendered as they are
    if near:
        print(near, file=sys.stderr)
    sensor = sensor_preset(args.sensor)
    settings = SimSettings(power=args.power, ambient=args.ambient, cycles=args.cycles, albedo=args.albedo,
                           **({} if args.rays_per_zone is None else {"rays_per_zone": args.rays_per_zone}))
    start = time.monotonic()
    try:
        with terminate_as_interrupt():
            path = simulate_capture(mesh, sensor, poses, args.out, settings=settings, seed=args.seed,
                                    chunk_size=args.chunk_size, scene=scene, schedule=schedule,
                                    progress=progress_bar_wanted(args), log=lambda line: print(line, file=sys.stderr),
                                    table=table, refuse_misplaced=True)
    except KeyboardInterrupt:
        left = None if had_capture else left_behind(args.out, len(poses))
        if left:  # (the bar, drawn with leave=False, has cleared its line)
            print(f"spadscan simulate: {left}", file=sys.stderr)
        raise  # the command line says it was interrupted, exit status 130
    hists = CaptureReader(path).load().hists
    for note in (flooded_note(hists, sensor), saturated_note(hists)):
        if note:
            print(note, file=sys.stderr)
    on_table = "" if table is None else f" on a table at z = {table.height_m:g} m (albedo {table.albedo:g})"
    print(f"wrote {len(poses)} views of {len(mesh.faces)} faces{on_table} with sensor {sensor.name} to {path} "
          f"in {time.monotonic() - start:.1f} s", file=sys.stderr)
    return 0
