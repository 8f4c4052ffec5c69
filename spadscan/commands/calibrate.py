"""Calibrate the rig from a capture.

    spadscan calibrate hand-eye CAPTURE --plane X,Y,Z,NX,NY,NZ     the flange-to-sensor transform from views of a plane
    spadscan calibrate hand-eye CAPTURE --sphere X,Y,Z,R            ... or of a sphere

`hand-eye` fits the rig config's [arm] hand_eye (X: sensor pose = TCP pose x X) to a capture of a target whose place
in the arm's base frame you know (metres): the table (a point on it and its normal, e.g. `--plane 0,0,0.02,0,0,1`)
or a sphere (centre and radius). It starts from the X the capture was taken with (and from it turned 90, 180 and
270 deg about the sensor's axis, going on from the turn that explains the returns best), moves it until every zone's
return lies where the sensor model puts it, and prints the fitted X as the line to put in the config, with its
uncertainty (one standard deviation, from the residuals' scatter; a pose's frames count as one view, as they share
its error). A one-zone sensor sees the same at every turn about its axis: that turn is kept as the capture's X has
it and printed as not determined. A zone counts as a return on the target only
where the predicted return lies within 2 bins of the observed one; the residual RMS is given over those returns at
the fitted X and at the capture's X (saying how many of them the capture's X puts farther off). Take the capture
with views that tilt the tool in different directions (rings at several elevations with --jitter, see
firmware_notes/hand_eye.md): a plane seen from one orientation fixes X only along its normal, and views that differ
only by a turn about one axis (one ring, rings without jitter) leave part of X undetermined: such a capture is
refused, naming the part. A start centimetres off along the sensor's axis (the default identity, a bracket left out)
is first moved along that axis to the returns' median range. A fit that tilts the sensor's axis more than 10 deg,
moves it more than 20 mm across it or along it (100 mm from a start without a translation, the default identity),
leaves more than 10 mm RMS or more than a fifth of the returns off a plane is printed with a warning naming the
likely cause: a wrong target or something standing on the plane is likelier than such a bracket, and a plane given
at the wrong height (measured with the wrong TCP active) moves X along the sensor's axis and shows nowhere else.
With --fit-zero-bin the printed X is right only together with the fitted zero-bin shift, which no config key
applies (the daemon and the worker use the capture's sensor preset): a warning says so, with the shift.
"""

from __future__ import annotations

import sys

import numpy as np


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="what", required=True, metavar="WHAT")
    he = sub.add_parser("hand-eye", help="fit [arm] hand_eye from a capture of a known plane or sphere",
                        description=__doc__, formatter_class=parser.formatter_class)
    he.add_argument("capture", metavar="CAPTURE", help="the capture folder (holds scan.json)")
    he.add_argument("--plane", metavar="X,Y,Z,NX,NY,NZ",
                    help="the target is a plane through point X,Y,Z with normal NX,NY,NZ (base frame, metres)")
    he.add_argument("--sphere", metavar="X,Y,Z,R", help="the target is a sphere of centre X,Y,Z and radius R (m)")
    he.add_argument("--fit-zero-bin", action="store_true",
                    help="also fit a shift of the sensor model's zero bin (weakly separable from X's offset along "
                         "the boresight: use views at several distances); the printed hand_eye is then right only "
                         "with that shift, which no config key applies (without the flag X takes it along the "
                         "sensor's axis)")


def run(args) -> int:
    from spadscan.daemon.hand_eye import (PLAUSIBLE_ACROSS_MM, PLAUSIBLE_TILT_DEG, UNCERTAIN_DEG, UNCERTAIN_MM,
                                          WINDOW_BINS, fit_hand_eye, hand_eye_toml, parse_target)

    target = parse_target(args.plane, args.sphere)
    fit = fit_hand_eye(args.capture, target, fit_zero_bin=args.fit_zero_bin)
    moved = (fit.hand_eye[:3, 3] - fit.start[:3, 3]) * 1e3
    odd = fit.implausible()
    off = f" ({fit.lost} more off it at the fitted hand_eye, left out)" if fit.lost else ""
    # A view is a pose (as a reconstruction sums its frames into one); every frame is fitted on its own, so the
    # returns (and those left off) count a zone once per frame: said so when a view has several.
    several = fit.frames > fit.views
    frames = f" ({fit.frames} frames)" if several else ""
    counted = f" in those {fit.frames} frames" if several else ""
    print(f"{args.capture}: {fit.views} views{frames}, {fit.returns} zone returns on the {target.kind}{counted}{off}")
    print(f"residual RMS {_start_rms(fit, WINDOW_BINS)}, {fit.rms_mm:.2f} mm fitted ({fit.iterations} iterations)")
    if fit.turn_deg:
        print(f"the fit went on from the capture's hand_eye turned {fit.turn_deg:g} deg about the sensor's axis (that "
              f"start explained the returns best{'' if odd else ': a connector turned from the drawing?'})")
    print(f"change: {fit.change_mm:.1f} mm ({', '.join(f'{v:+.1f}' for v in moved)} mm), {fit.change_deg:.2f} deg")
    rotation = ', '.join(f'{v:.2f}' for v in fit.std_deg)
    if fit.turn_determined:
        rotation += " deg about the flange's x, y, z"
    else:
        rotation += (" deg tilt of the sensor's axis about its own x, y; the turn about the sensor's axis: not "
                     "determined (one zone sees the same at every turn: the capture's hand_eye's is kept)")
    print(f"uncertainty (one standard deviation): {', '.join(f'{v:.2f}' for v in fit.std_mm)} mm along the flange's "
          f"x, y, z; {rotation}")
    if fit.uncertain:
        print(f"spadscan: warning: the hand_eye below is uncertain by more than {UNCERTAIN_MM:g} mm or "
              f"{UNCERTAIN_DEG:g} deg: add views that tilt the tool further about several axes", file=sys.stderr)
    if odd:
        # A tight uncertainty says only that the returns fix this X, not that it is the bracket: a wrong target
        # fits as tightly.
        print(f"spadscan: warning: implausible fit: it {', '.join(odd)} (a bracket's drawing is rarely off by more "
              f"than {PLAUSIBLE_TILT_DEG:g} deg or {PLAUSIBLE_ACROSS_MM:g} mm, and the right target leaves a few mm "
              f"RMS): {fit.likely_causes()}; check before using the hand_eye below", file=sys.stderr)
    if args.fit_zero_bin:
        # No config key sets the zero bin: the daemon stores its preset's in every capture and the worker reads
        # ranges with that, so this X alone leaves every range off by the shift.
        shift_mm = fit.zero_bin_shift * fit.bin_width_mm
        print(f"spadscan: warning: the hand_eye below is right only with the sensor's zero bin moved "
              f"{fit.zero_bin_shift:+.3f} bins ({shift_mm:+.1f} mm of range) from the capture's sensor model, and no "
              f"config key sets the zero bin: the daemon and the worker do not apply the shift, so with this hand_eye "
              f"every range stays {abs(shift_mm):.1f} mm off; fit without --fit-zero-bin for a hand_eye that takes "
              f"the shift along the sensor's axis", file=sys.stderr)
    print("for the rig config's [arm] table:")
    if not fit.turn_determined:
        print("# the turn about the sensor's axis is the capture's hand_eye's, not fitted (a one-zone sensor)")
    print(hand_eye_toml(np.asarray(fit.hand_eye)))
    return 0


def _start_rms(fit, window_bins: int) -> str:
    """The start's residual RMS over the fitted returns, saying which of them it covers: a zone whose return the
    start predicts outside its window has no residual there (a miss is not scored as a match)."""
    if fit.lost_start == 0:
        return f"{fit.rms_start_mm:.2f} mm with the capture's hand_eye"
    far = f"more than {window_bins} bins = {window_bins * fit.bin_width_mm:.0f} mm off"
    if fit.lost_start == fit.returns:
        return f"not defined with the capture's hand_eye (it puts all {fit.returns} of these returns {far})"
    return (f"{fit.rms_start_mm:.2f} mm with the capture's hand_eye (over the {fit.returns - fit.lost_start} of these "
            f"returns it puts on the {fit.kind}; the other {fit.lost_start} {far})")
