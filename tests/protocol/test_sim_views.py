"""Which views a simulation can render: views that see nothing of the mesh (with and without a table), and sensors
placed where no sensor can stand (inside the object, on or under the table top)."""

import argparse
import json

import numpy as np
import pytest
import trimesh

from spadscan.cli import main
from spadscan.commands import simulate
from spadscan.protocol.errors import SimulationError
from spadscan.protocol.scenes import builtin_scene
from spadscan.protocol.schedules import look_at
from spadscan.protocol.sensor_presets import sensor_preset
from spadscan.protocol.sim_table import SimTable
from spadscan.protocol.simulator import Simulator, blind_views_note, simulate_capture

# 16 views around a point 0.8 m beside the built-in sphere: 14 of them look past it (and, with a table, at the table).
ASIDE = ["builtin:sphere", "--sensor", "tmf8820", "--views", "16", "--target", "0.8", "0", "0", "--radius", "0.3",
         "--no-progress"]


def warnings_of(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("warning:")]


def test_the_blind_views_note_counts_the_views_that_see_nothing():
    ball = trimesh.creation.icosphere(radius=0.05)
    some = blind_views_note(np.array([0.0, 0.5, 5.0, 10.0]), ball)
    assert some.startswith("warning: 2 of 4 views see nothing of the mesh (under 1 signal photon expected)")
    assert blind_views_note(np.zeros(4), ball).startswith("warning: none of the 4 views see the mesh (")
    assert blind_views_note(np.full(4, 3.0), ball) is None


def test_a_table_does_not_hide_the_views_that_miss_the_mesh(tmp_path, capsys):
    """The table's returns used to count as seeing the mesh: with --table the warning never came."""
    assert main(["simulate", *ASIDE, "--out", str(tmp_path / "bare")]) == 0
    bare = warnings_of(capsys.readouterr().err)
    assert main(["simulate", *ASIDE, "--table", "--min-elevation", "0", "--out", str(tmp_path / "table")]) == 0
    on_table = warnings_of(capsys.readouterr().err)
    assert len(bare) == 1 and bare[0].startswith("warning: 14 of 16 views see nothing of the mesh (")
    assert on_table == bare


@pytest.mark.parametrize("how", [["--target", "0", "0", "0.1", "--radius", "0.1005"], ["--ambient", "1"]])
@pytest.mark.parametrize("sensor, bins", [("lcspc-sim", 4), ("tmf8820", 14)])
def test_a_capture_flooded_by_pile_up_is_said_when_it_is_written(tmp_path, capsys, how, sensor, bins):
    """Views half a millimetre from the ball, or ambient light that fills the first bins of every cycle: every
    histogram holds its detections in its first bins, which reconstruct refuses later; simulate says so at once. The
    TMF8820's zero range lies at bin 12.4: a surface touching it returns there (its pulse peaks at bin 9), and the
    capture was written without a word when only bins 0-3 were looked at."""
    out = str(tmp_path / "c")
    assert main(["simulate", "builtin:sphere", "--views", "16", "--no-progress", "--sensor", sensor, *how,
                 "--out", out]) == 0
    said = warnings_of(capsys.readouterr().err)
    assert len(said) == 1 and said[0].startswith("warning: 16 of 16 views hold "), said
    assert f"in their first {bins} bins (pile-up" in said[0]


def test_a_saturated_capture_is_said_when_it_is_written(tmp_path, capsys):
    """At 100 times the laser power every return stops nearly every cycle: nothing is flooded (the returns are far
    from the first bins), but no histogram holds anything behind its first surface."""
    out = str(tmp_path / "c")
    assert main(["simulate", "builtin:sphere", "--views", "16", "--no-progress", "--power", "100", "--out", out]) == 0
    said = warnings_of(capsys.readouterr().err)
    assert len(said) == 1 and said[0].startswith("warning: 16 of 16 histograms are saturated (pile-up"), said
    assert "lower --power or --ambient, or move the views back" in said[0]


@pytest.mark.parametrize("sensor", ["lcspc-sim", "tmf8820"])
def test_a_plain_capture_is_not_said_to_be_flooded(tmp_path, capsys, sensor):
    assert main(["simulate", "builtin:sphere", "--views", "16", "--no-progress", "--sensor", sensor,
                 "--out", str(tmp_path / "c")]) == 0
    assert warnings_of(capsys.readouterr().err) == []


def test_frames_keep_the_meshs_photons_apart_from_the_tables():
    ball = builtin_scene("sphere")
    sim = Simulator(ball, sensor_preset("tmf8820"), table=SimTable(0.0, 0.5))
    at_ball = look_at([0.4, 0.0, 0.3], [0.0, 0.0, 0.1])
    at_table = look_at([1.0, 0.0, 0.3], [1.0, 0.3, 0.0])  # looks down at the table, away from the ball
    fr = sim.frames(np.stack([at_ball, at_table]))
    assert fr.mesh_photons[0] > 1e3 and fr.signal_photons[0] > fr.mesh_photons[0]  # the table beside the ball
    assert fr.mesh_photons[1] == 0 and fr.signal_photons[1] > 1e3
    bare = Simulator(ball, sensor_preset("tmf8820")).frames(np.stack([at_ball, at_table]))
    np.testing.assert_array_equal(bare.mesh_photons, bare.signal_photons)


def test_a_sensor_inside_the_mesh_is_refused_naming_the_views(tmp_path, capsys):
    """At 0.08 m from a point inside the 0.2 m sphere every view stood inside it, and rendered its inner wall."""
    out = tmp_path / "inside"
    assert main(["simulate", "builtin:sphere", "--out", str(out), "--views", "32", "--radius", "0.08",
                 "--target", "0", "0", "0.1", "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert err == ("spadscan: error: 32 of 32 views (0, 1, 2, 3, 4, 5, 6, 7, ...) put the sensor inside the mesh: no "
                   "sensor can stand there; move the target or the radius (metres), or the elevations\n")
    assert not out.exists()


@pytest.mark.parametrize("band, line", [
    (["--min-elevation", "0"], "8 of 32 views (0, 1, 2, 3, 4, 5, 6, 7) put the sensor on or under the table top "
                               "(z = 0 m)"),
    (["--min-elevation", "-40", "--max-elevation", "-10"], "32 of 32 views (0, 1, 2, 3, 4, 5, 6, 7, ...) put the "
                                                           "sensor on or under the table top (z = 0 m)"),
], ids=["ring-on-the-table", "all-under-it"])
def test_a_sensor_on_or_under_the_table_top_is_refused(tmp_path, capsys, band, line):
    """The lowest ring at 0 deg stood on the table top, where the table vanished from its histograms; 0.05 deg
    higher the same table flooded them. Under the table, the views saw its underside alone."""
    args = ["builtin:sphere", "--sensor", "tmf8820", "--schedule", "rings", "--rings", "4", "--views", "32", *band,
            "--no-progress"]
    assert main(["simulate", *args, "--table", "--out", str(tmp_path / "t")]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"spadscan: error: {line}: no sensor can stand there") and err.count("\n") == 1, err
    assert not (tmp_path / "t").exists()
    if band == ["--min-elevation", "0"]:  # without a table the same ring stands beside the object: fine
        assert main(["simulate", *args, "--out", str(tmp_path / "bare")]) == 0


def test_the_library_renders_a_misplaced_view_but_says_so(tmp_path):
    """A library caller may render such a view on purpose (a table seen from below): it is logged, not refused."""
    from spadscan.protocol.simulator import misplaced_views_note

    ball = builtin_scene("sphere")
    poses = np.stack([look_at([0, 0, 0.1], [0.3, 0, 0.1]), look_at([0.5, 0, 0.1], [0, 0, 0.1]),
                      look_at([0.5, 0, -0.2], [0, 0, 0.1])])
    lines = []
    simulate_capture(ball, sensor_preset("tmf8820"), poses, tmp_path / "c", progress=False, log=lines.append,
                     table=SimTable(0.0))
    assert lines[0] == ("warning: 1 of 3 views (0) put the sensor inside the mesh and 1 of 3 views (2) put the "
                        "sensor on or under the table top (z = 0 m): no sensor can stand there; move the target or "
                        "the radius (metres), or the elevations")
    assert misplaced_views_note(poses[1:2], ball, SimTable(0.0)) is None
    # asked to refuse them (as `simulate` and a sweep's points do), it raises that line and writes nothing
    with pytest.raises(SimulationError, match=r"^1 of 3 views \(0\) put the sensor inside the mesh and"):
        simulate_capture(ball, sensor_preset("tmf8820"), poses, tmp_path / "r", progress=False, log=lines.append,
                         table=SimTable(0.0), refuse_misplaced=True)
    assert not (tmp_path / "r").exists() and len(lines) == 2  # the first capture's two lines alone
    # an open mesh has no inside: nothing is said of it
    closed = trimesh.creation.icosphere(radius=0.3)
    assert misplaced_views_note(poses[:1], closed) is not None
    assert misplaced_views_note(poses[:1], trimesh.Trimesh(closed.vertices, closed.faces[:-4])) is None


def test_a_ray_from_the_table_top_into_it_meets_it_at_range_0():
    table = SimTable(0.05, half_size_m=1.0)
    origins = np.array([[0.1, 0.0, 0.05], [0.1, 0.0, 0.05], [0.1, 0.0, 0.25], [0.1, 0.0, -0.15]])
    dirs = np.array([[0.0, 0.6, -0.8], [0.0, 0.6, 0.8], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    t, cos = table.hits(origins, dirs)
    assert t[0] == 0.0 and cos[0] == pytest.approx(0.8)  # on the top, heading down into the slab
    assert t[1] == np.inf  # on the top, heading up and away
    assert t[2] == pytest.approx(0.2) and t[3] == pytest.approx(0.2)  # from above, and the underside from below
    assert table.below_top(origins).tolist() == [True, True, False, True]
    assert not table.below_top(np.array([[1.5, 0.0, -0.3]])).any()  # beside the table, lower than its top: fine


ONE_BAND = ["builtin:sphere", "--schedule", "rings", "--min-elevation", "45", "--max-elevation", "45",
            "--rays-per-zone", "64", "--no-progress"]


def test_two_rings_in_a_band_of_zero_width_are_one_ring_of_twice_the_views(tmp_path):
    """The second ring is offset by half a step: 16 poses of their own, refused before as if they repeated."""
    from spadscan.protocol.capture_reader import CaptureReader

    assert main(["simulate", *ONE_BAND, "--rings", "2", "--views", "16", "--out", str(tmp_path / "c")]) == 0
    poses = np.asarray(CaptureReader(tmp_path / "c").load().poses)
    assert len(np.unique(np.round(poses.reshape(16, -1), 9), axis=0)) == 16
    # Ring by ring, as elevation_rings lays rings out: 0.5 m away at 45 deg, the second ring offset by half a step.
    e, a = np.radians(45.0), 2 * np.pi * (np.arange(16) % 8 + 0.5 * (np.arange(16) >= 8)) / 8
    want = 0.5 * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.full(16, np.sin(e))], axis=-1)
    np.testing.assert_allclose(poses[:, :3, 3], want, atol=1e-12)
    np.testing.assert_allclose(poses[:, :3, 2], -want / 0.5, atol=1e-12)  # each looks at the target
    record = json.loads((tmp_path / "c" / "scan.json").read_text())["schedule"]
    assert (record["rings"], record["per_ring"]) == (2, 8)


def test_two_rings_in_a_band_of_zero_width_hold_the_limit_per_ring_not_per_pair():
    """2 rings of 75,000 views each are within a ring's limit; they were refused as one ring of 150,000."""
    parser = argparse.ArgumentParser()
    simulate.add_arguments(parser)
    args = parser.parse_args([*ONE_BAND, "--rings", "2", "--views", "150000", "--out", "unused"])
    poses, record = simulate.make_poses(args)
    assert poses.shape == (150000, 4, 4) and (record["rings"], record["per_ring"]) == (2, 75000)
    # the second ring stands half a step further round than the first, ring by ring
    azim = np.arctan2(poses[:, 1, 3], poses[:, 0, 3]) % (2 * np.pi)
    step = 2 * np.pi / 75000
    np.testing.assert_allclose(azim[[0, 1, 75000, 75001]], [0.0, step, 0.5 * step, 1.5 * step], atol=1e-9)


@pytest.mark.parametrize("argv", [["--rings", "1", "--views", "150000"],
                                  ["--rings", "2", "--views", "250000"]],
                         ids=["one-ring", "two-rings-in-a-band-of-zero-width"])
def test_more_views_per_ring_than_a_ring_holds_is_refused_naming_the_flags(tmp_path, capsys, argv):
    per_ring = int(argv[3]) // int(argv[1])
    assert main(["simulate", *ONE_BAND, *argv, "--out", str(tmp_path / "c")]) == 1
    assert capsys.readouterr().err == (f"spadscan: error: --views {argv[3]} in --rings {argv[1]} is {per_ring} views "
                                       f"per ring; a ring holds at most 100000\n")
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("argv, line", [
    (["--rings", "3", "--views", "24"],
     "--rings 3: 3 rings in a band of zero width (45 deg) all stand at one elevation, every other ring on the same "
     "poses; widen the band (--min-elevation below --max-elevation, degrees), or use --rings 1"),
    (["--rings", "2", "--views", "2", "--min-elevation", "90", "--max-elevation", "90"],
     "--rings 2: 2 rings in a band of zero width at +90 deg elevation all stand at one viewpoint (straight above the "
     "target); widen the band (--min-elevation below --max-elevation, degrees), or use --rings 1"),
    (["--rings", "2", "--views", "16", "--min-elevation", "10", "--max-elevation", "90"],
     "a ring at +90 deg elevation puts its 8 views at one viewpoint (straight above the target); keep "
     "--max-elevation strictly between -90 and 90 (degrees)"),
    (["--schedule", "fibonacci", "--views", "4", "--min-elevation", "-90", "--max-elevation", "-90"],
     "--views 4 in a spiral band of zero width at -90 deg elevation stand at one viewpoint (straight below the "
     "target); widen the band (--min-elevation below --max-elevation, degrees)"),
], ids=["three-rings", "two-rings-at-the-top", "ring-at-the-top", "spiral-at-the-bottom"])
def test_a_schedule_that_repeats_a_pose_is_refused_naming_the_flags(tmp_path, capsys, argv, line):
    """The schedules' own refusals named min_elevation and max_elevation, which are no options of this command."""
    assert main(["simulate", *ONE_BAND, *argv, "--out", str(tmp_path / "c")]) == 1
    assert capsys.readouterr().err == f"spadscan: error: {line}\n"
    assert not (tmp_path / "c").exists()


def test_views_just_above_the_table_top_are_warned_about_and_rendered_as_they_were(tmp_path, capsys):
    """The spiral from 0 degrees puts its lowest views 1-9 mm above a table at z = 0 (the lowest at 0.11 deg
    elevation): the table floods their histograms, and nothing said so. Said now, in one line; the capture is the
    one the library renders for those poses, count for count."""
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.protocol.schedules import fibonacci_hemisphere
    from spadscan.protocol.simulator import SimSettings

    assert main(["simulate", "builtin:sphere", "--sensor", "tmf8820", "--table", "--no-progress",
                 "--min-elevation", "0", "--out", str(tmp_path / "cli")]) == 0
    err = capsys.readouterr().err
    near = [line for line in err.splitlines() if "within 1 cm above the table top" in line]
    assert near == ["warning: 5 of 256 views (251, 252, 253, 254, 255) put the sensor within 1 cm above the table top "
                    "(the lowest 0.98 mm above it): their histograms may be flooded by the table; a higher "
                    "--min-elevation (degrees) lifts them"], err
    poses = fibonacci_hemisphere(256, 0.5, min_elevation_deg=0, max_elevation_deg=90)
    simulate_capture(builtin_scene("sphere"), sensor_preset("tmf8820"), poses, tmp_path / "lib",
                     settings=SimSettings(), seed=0, progress=False, table=SimTable(0.0))
    cli, lib = CaptureReader(tmp_path / "cli").load(), CaptureReader(tmp_path / "lib").load()
    np.testing.assert_array_equal(cli.hists, lib.hists)
    np.testing.assert_array_equal(cli.poses, lib.poses)


def test_on_a_table_the_spiral_starts_ten_degrees_up_unless_told(tmp_path, capsys):
    """The default a new user gets on a table is a spiral whose views all stand clear of its top (from 0 degrees,
    its lowest stood on the table and flooded their histograms)."""
    from spadscan.protocol.capture_reader import CaptureReader

    assert main(["simulate", "builtin:sphere", "--sensor", "tmf8820", "--table", "--no-progress", "--views", "64",
                 "--rays-per-zone", "64", "--out", str(tmp_path / "c")]) == 0
    assert "table top" not in capsys.readouterr().err
    reader = CaptureReader(tmp_path / "c")
    assert reader.manifest["schedule"]["min_elevation_deg"] == 10.0
    heights = reader.load().poses[:, 2, 3]
    assert heights.min() > 0.5 * np.sin(np.radians(10.0)) - 1e-6


def test_a_spiral_band_below_the_tables_default_start_is_taken_as_asked(tmp_path, capsys):
    assert main(["simulate", "builtin:sphere", "--sensor", "tmf8820", "--table", "--no-progress", "--views", "16",
                 "--rays-per-zone", "64", "--max-elevation", "5", "--out", str(tmp_path / "c")]) == 0
    from spadscan.protocol.capture_reader import CaptureReader

    assert CaptureReader(tmp_path / "c").manifest["schedule"]["min_elevation_deg"] == 0.0


@pytest.mark.parametrize("argv", [
    ["--table", "--schedule", "rings"],  # the rings' lowest at 10 deg: 87 mm above the table
    ["--views", "16"],  # the same spiral without a table
    ["--table", "--min-elevation", "1.2"],  # the lowest view 11.4 mm above the table
], ids=["rings", "no-table", "spiral-lifted"])
def test_views_a_centimetre_or_more_above_the_table_are_not_warned_about(tmp_path, capsys, argv):
    assert main(["simulate", "builtin:sphere", "--sensor", "tmf8820", "--rays-per-zone", "64", "--no-progress",
                 *argv, "--out", str(tmp_path / "c")]) == 0
    assert "table top" not in capsys.readouterr().err
