"""A resume counts what the capture holds on disk and whether the disk can take the next pose: one on a disk still
too full for a chunk is refused at once, the arm not moved (reopening the capture alone may fit: the half-written
chunk it drops frees a little room); a chunk moved out of a scan paused in the daemon's hands is taken again. A file
that outgrows the daemon's file-size limit (`ulimit -f`) is not called a full disk, and a disk that cannot be written
for another reason is not given a full disk's remedy."""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import subprocess
import sys
import textwrap

import pytest

import spadscan.daemon.room_check as room_check
from spadscan.protocol.errors import ConfigError

from test_abort_durable import disk  # noqa: F401  (a fixture)
from test_runner import check_capture, daemon_runner, make_cfg, paused_after, until
from test_runner import sphere  # noqa: F401  (a fixture)

PAGE = 4096  # tmpfs allocates files' data in pages


@contextlib.contextmanager
def tiny_disk(path, size: str):
    """A tmpfs of `size` mounted at `path` for the block (needs root: the test is skipped without it); unmounted on
    the way out, lazily if something still holds it."""
    path.mkdir(parents=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs", str(path)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here (needs root): {r.stderr.strip()}")
    try:
        yield path
    finally:
        if subprocess.run(["umount", str(path)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(path)], capture_output=True)


def fill_leaving(folder, room: int) -> None:
    """Fill the filesystem holding `folder` with a file, then free `room` bytes of it (whole pages)."""
    filler = folder / "filler"
    with open(filler, "wb", buffering=0) as f:
        for block in (1 << 16, PAGE):
            try:
                while f.write(b"\0" * block):
                    pass
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc
    os.truncate(filler, filler.stat().st_size // PAGE * PAGE - room)


def test_a_resume_on_a_disk_with_room_for_the_manifest_but_not_a_chunk_is_refused_at_once(arun, tmp_path,
                                                                                          sphere):  # noqa: F811
    """The captures on a 512 KiB tmpfs, filled while the scan is paused but for two pages: the capture reopens
    (its manifest fits), a pose's chunk (hists.npy alone is three pages) does not. The resume is refused with the
    cause and what to do, the arm stays where it is; once room is made, the scan completes, every pose once."""
    cfg = make_cfg(tmp_path, views=6)
    folder = tmp_path / "caps" / "tight"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "tight", runner.pause, poses=2)
            fill_leaving(tmp_path / "caps", 2 * PAGE)
            moves = runner.arm.moves
            with pytest.raises(ConfigError) as refused:
                await runner.resume()
            still = runner.status(), runner.arm.moves
            (tmp_path / "caps" / "filler").unlink()  # the operator makes room
            await runner.resume()
            return str(refused.value), still, moves, await runner.wait("tight")

    with tiny_disk(tmp_path / "caps", "512k"):
        refused, (still, moved), moves, done = arun(scenario())
        check_capture(folder, 6, 2)
        assert not [p.name for p in folder.iterdir() if p.name.startswith(".tmp-")]
    assert refused.startswith("cannot resume scan 'tight': the captures' disk is still full (No space left on "
                              "device: no room for the next pose's chunk in "), refused
    assert refused.endswith("); make room on it, then `spadscan ctl resume`"), refused
    assert "\n" not in refused
    assert still["state"] == "paused" and still["reason"].startswith("the captures' disk is still full"), still
    assert still["last_error"] == still["reason"], still
    assert moved == moves  # the arm stayed where it was
    assert done == {"name": "tight", "state": "complete"}


def test_a_refused_resume_for_a_disk_still_full_does_not_move_the_arm(arun, tmp_path, sphere,
                                                                      monkeypatch):  # noqa: F811
    """A disk that takes a manifest but not a chunk, as a filesystem that fills up does (its chunk writes and the
    resume's check of room fail with ENOSPC): the fault's pause, then a resume refused with the arm where it was,
    as often as it is tried; once room is made the scan completes."""
    import spadscan.protocol.capture_writer as cw

    cfg = make_cfg(tmp_path, views=8)
    full = {"on": False}

    def failing(real):
        def write(path, data):
            if full["on"]:
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
            real(path, data)
        return write

    monkeypatch.setattr(cw, "save_npy_durable", failing(cw.save_npy_durable))
    monkeypatch.setattr(room_check, "write_durable", failing(room_check.write_durable))

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("room")
            await until(lambda: runner.job.next_pose >= 2, "two poses")
            full["on"] = True
            await until(lambda: runner.state == "paused", "the pause for the full disk")
            paused = runner.status()
            moves, refusals = runner.arm.moves, []
            for _ in range(2):
                with pytest.raises(ConfigError) as refused:
                    await runner.resume()
                refusals.append(str(refused.value))
            after = runner.status(), runner.arm.moves
            full["on"] = False
            await runner.resume()
            return paused, moves, refusals, after, await runner.wait("room")

    paused, moves, refusals, (still, moved), done = arun(scenario())
    assert paused["reason"].startswith("disk full while publishing: No space left on device ("), paused
    assert "; make room on the captures' disk, then `spadscan ctl resume` (pose " in paused["reason"], paused
    for refused in refusals:
        assert refused.startswith("cannot resume scan 'room': the captures' disk is still full"), refused
    assert still["state"] == "paused" and moved == moves, (still, moved, moves)
    assert not list((tmp_path / "caps" / "room").glob(".tmp-*"))
    assert done == {"name": "room", "state": "complete"}
    check_capture(tmp_path / "caps" / "room", 8, 2)


def test_a_chunk_moved_out_of_a_scan_paused_in_the_daemons_hands_is_taken_again(arun, tmp_path, sphere,  # noqa: F811
                                                                                reads):
    """The operator pauses the scan and moves pose 1's chunk out of the capture (damaged): the resume counts what
    the capture holds, says pose 1 is owed, and takes it again, reading none of the chunks it published (its chunk
    book); the capture ends complete with every pose."""
    cfg = make_cfg(tmp_path, views=8)
    folder = tmp_path / "caps" / "held"

    async def scenario():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await paused_after(runner, "held", runner.pause, poses=4)
            shutil.move(folder / "chunk-000001", tmp_path / "chunk-000001")
            reply = await runner.resume()
            return reply, await runner.wait("held")

    reply, done = arun(scenario())
    assert reply["state"] == "scanning" and reply["poses_to_take_again"] == [1], reply
    assert done == {"name": "held", "state": "complete"}
    assert reads == [], reads
    check_capture(folder, 8, 2)


WRITE_OVER_THE_LIMIT = textwrap.dedent("""
    import errno, resource, sys
    import numpy as np
    from spadscan.daemon.describe import describe, write_advice
    from spadscan.protocol.capture_format import Measurement
    from spadscan.protocol.capture_reader import CaptureReader
    from spadscan.protocol.capture_writer import CaptureWriter
    from spadscan.protocol.sensor_presets import sensor_preset

    out, which, limit, poses = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
    writer = CaptureWriter.create(out, sensor_preset("tmf8820"), chunk_size=64)
    hard = resource.getrlimit(resource.RLIMIT_FSIZE)[1] if which == "soft" else limit
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    for k in range(poses):  # hists.npy: a 128-byte header and poses x 9 x 128 x 4 bytes
        writer.append(Measurement(np.ones((9, 128), np.uint32), np.eye(4), 0, k, None, {}))
    try:
        writer.flush()
    except OSError as exc:
        print(errno.errorcode.get(exc.errno), exc.filename)
        print(describe(exc))
        print(write_advice(exc))
    print(len(CaptureReader(out).chunk_names()))
""")


def write_over_the_limit(out, which: str, limit: int, poses: int) -> list[str]:
    """`WRITE_OVER_THE_LIMIT` run in a process of its own (its file-size limit is that process's): its lines."""
    r = subprocess.run([sys.executable, "-c", WRITE_OVER_THE_LIMIT, str(out), which, str(limit), str(poses)],
                       cwd=out.parent, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r.stdout.splitlines()


@pytest.mark.parametrize("limit", ["soft", "hard"])
def test_a_chunk_over_the_daemons_file_size_limit_is_not_called_a_full_disk(tmp_path, limit):
    """Under `ulimit -f` numpy's write of a chunk's counts stops short (no errno): at the process's file-size limit
    that is EFBIG, said as such with its own advice, not a full disk to make room on: `prlimit` on the running
    daemon where its hard limit allows more, else a daemon started with a higher limit (`ulimit -f` sets both)."""
    failed, said, advice, published = write_over_the_limit(tmp_path / "cap", limit, 16384, 8)
    assert failed.split()[0] == "EFBIG" and published == "0", failed
    assert said.startswith("file too large while publishing: File too large ("), said
    assert said.endswith("hists.npy); the daemon may write files of at most 16384 bytes (ulimit -f)"), said
    assert "disk full" not in said and "No space" not in said, said
    if limit == "soft":
        assert re.fullmatch(r"raise the daemon's file-size limit \(`prlimit --pid \d+ --fsize=\w+`\), then "
                            r"`spadscan ctl resume`", advice), advice
    else:
        assert advice == ("start the daemon again with a higher file-size limit (`ulimit -f` where it is started, "
                          "systemd's LimitFSIZE=), then `spadscan ctl resume`"), advice


def test_a_takeover_on_a_read_only_disk_says_to_make_it_writable_not_to_make_room(arun, tmp_path, sphere,
                                                                                   disk):  # noqa: F811
    """The daemon restarts on a disk remounted read-only: the scan is taken over paused, and the reason says what
    stands in the way of this error (the folder must be made writable), not a full disk's remedy."""
    cfg = make_cfg(tmp_path, views=6)

    async def first_daemon():
        async with daemon_runner(cfg, sphere, motion_time_s=0.01) as runner:
            await runner.start("ro")
            await until(lambda: runner.job.next_pose >= 2, "two poses")

    async def second_daemon():
        async with daemon_runner(cfg, sphere) as runner:
            await runner.recover()
            return runner.status()

    arun(first_daemon())
    disk["error"] = errno.EROFS
    status = arun(second_daemon())
    assert status["state"] == "paused" and status["scan"] == "ro", status
    assert re.fullmatch(r"interrupted at pose \d/6 \(daemon restarted\), and write error while reopening the "
                        r"capture: Read-only file system \([^()]+\); make the captures' folder writable, then "
                        r"`spadscan ctl resume`", status["reason"]), status["reason"]


WRITE_OUT_OF_FILES = textwrap.dedent("""
    import errno, os, resource, sys
    import numpy as np
    from spadscan.daemon.describe import describe, write_advice
    from spadscan.protocol.capture_format import Measurement
    from spadscan.protocol.capture_writer import CaptureWriter
    from spadscan.protocol.sensor_presets import sensor_preset

    writer = CaptureWriter.create(sys.argv[1], sensor_preset("tmf8820"), chunk_size=64)
    writer.append(Measurement(np.ones((9, 128), np.uint32), np.eye(4), 0, 0, None, {}))
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (64, hard))
    held = []
    try:
        while True:  # every descriptor this process may hold, as idle connections to a daemon would
            held.append(os.open(os.devnull, os.O_RDONLY))
    except OSError:
        pass
    try:
        writer.flush()
    except OSError as exc:
        print(errno.errorcode.get(exc.errno))
        print(describe(exc))
        print(write_advice(exc))
""")


def test_a_chunk_written_out_of_open_files_is_not_blamed_on_the_disk(tmp_path):
    """A daemon whose files were all held (a script's idle connections) paused its scan with "write error ...;
    check the captures' disk": it says now that it has too many files open, and how to free or raise them."""
    r = subprocess.run([sys.executable, "-c", WRITE_OUT_OF_FILES, str(tmp_path / "cap")], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    code, said, advice = r.stdout.splitlines()
    assert code == "EMFILE", r.stdout
    assert said.startswith("too many open files while publishing: Too many open files"), said
    assert said.endswith("; the daemon may hold 64 open at once (ulimit -n)"), said
    assert "disk" not in said + advice, advice
    assert advice.startswith("close what holds connections to the daemon open (a script's, a stuck program's) or "
                             ), advice
    assert advice.endswith(", then `spadscan ctl resume`"), advice


def test_a_chunk_whose_last_bytes_pass_the_file_size_limit_is_not_published(tmp_path):
    """numpy writes through C stdio and never raises a failure to flush the last partial buffer: a chunk whose
    hists.npy ended 128 bytes past the daemon's file-size limit was published short of its header's data, and the
    scan ended complete with every chunk unreadable. The write fails as one over the limit does, nothing published."""
    lines = write_over_the_limit(tmp_path / "cap", "soft", 9216, 2)  # the data's last 128 bytes over the limit
    code, name = lines[0].split(" ", 1)
    assert code == "EFBIG" and name.endswith("hists.npy"), lines
    assert lines[-1] == "0", lines
