"""The scan runner: drives the arm through a scan plan, captures K frames per pose, publishes every pose durably.

Per pose: move (TCP pose = sensor pose @ inv(hand-eye)), settle, drop frames that began before the arm stopped and
settled, capture K frames, read the arm's *actual* TCP pose and joints, store each frame as its own measurement
(sensor pose = actual TCP @ hand-eye), publish the pose as one chunk. Publishing runs on one writer thread and
overlaps the next pose's move, settle and frames; pose i+1 is handed to the writer only once pose i's chunk has
landed. So at any moment at most one *finished* pose is unpublished (a kill -9 loses it and the frames of the pose
being captured, nothing else), and a pose counts only once its chunk is published.

Faults pause the scan with the reason in `status`: a silent sensor (SensorSilent; not when the daemon itself was not
running meanwhile, `stall.py`: that wait begins again), frames that all began too early (FramesTooEarly), a safety
stop or lost link (ArmFault, LinkLost, any DeviceError), a full disk or other write error (OSError, CaptureError); the
reason says, on one line, what the operator does before `ctl resume` (`_advice`). The writer is then dropped; every
resume reopens the capture (counting what it holds on disk: a chunk moved out meanwhile is taken again) and writes
a pose's worth of files to check for room (`no_room`) before it replies, and continues at the first unpublished
pose (`CaptureWriter.next_pose_index`); a takeover checks for room the same way (a full disk's pause could not be
recorded on it). A safety stop that comes while the arm stands at a pose is named in the
reason (emergency, protective or safeguard stop, `arm/stops.py`), with what clears it, and when it was found: as
the move ended or the arm settled, or while the pose was captured. A move's limit, move_timeout_s, counts motion
time at the pace of the arm's speed slider (`MoveClock`). Before the first move after a
resume the arm is readied: after LinkLost, or whenever its link is found down then, whatever paused the scan, it
reconnects (`Arm.reconnect`: fresh interfaces); after ArmFault `Arm.clear_fault` runs (the sim arm clears its
safety stop; a real UR arm's stop is cleared by the operator before `ctl resume`, and the arm uploads its control
script again if the fault stopped it). A new scan whose arm link went down while no scan ran reconnects it the same
way before it plans. The first move of every run starts wherever the arm
stands: it is checked like the planned moves (`workspace.first_move_problem`), and after a pause the arm's controller
is asked again about the poses still to come (`Arm.check_poses`).

An abort is recorded in the capture's manifest alone (no chunk is read). One the disk cannot take (full, read-only)
is never undone by a restart: the reply says it is not recorded yet, `abort-pending.json` in the scan folder keeps it
where an empty file still fits (no daemon takes such a scan over), and the daemon writes it again every
ABORT_RETRY_S, at each control request and at shutdown (`abort_book.py`). A scan found interrupted that cannot be
taken over (a chunk torn by a power cut) is named in `status` with what to do: `ctl resume NAME` tries the takeover
again (after its damaged chunk is moved out of the folder: the poses it held are taken again first, `_retake`), `ctl
abort NAME` ends it as aborted, every chunk kept; `ctl wait NAME` says which of these it waits for; it stays named
until that scan itself is taken over or aborted. The two are done one at a time (the later one is refused, to be
tried again), so an acknowledged abort is never undone by a takeover, nor by a shutdown (SIGTERM) while `ctl abort`
waits for the arm to stop: the scan's wind-down runs to its end whoever is cancelled.
"""

from __future__ import annotations

import asyncio
import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from spadscan import __version__
from spadscan.protocol.capture_format import MANIFEST, Measurement, one_line, read_json
from spadscan.protocol.capture_writer import CaptureWriter, mark_paused, writer_lock_held
from spadscan.protocol.errors import CaptureError, ConfigError, DeviceError, SpadscanError

from .abort_book import FOLDER_GONE, AbortBook
from .config import DaemonConfig, scan_request
from .arm.stops import clear_advice, stop_name
from .describe import describe, write_advice
from .devices import (Arm, ArmFault, ArmState, Frame, FramesTooEarly, LinkLost, Sensor, SensorSilent,
                      wait_counted)
from .move_clock import MoveClock
from .room_check import no_room
from .root_lock import RootLock
from .scan_capture import (close_writer, count_as_held, counted_on_disk, end_early, finish_capture, folder_gone,
                           gone_or_ended, lost_chunks, pause_kind, pause_said, paused_reason, paused_record,
                           pose_measurements, remove_partial, reopen_fix, reopen_problem)
from .scan_job import (ABORT_PENDING, DEFAULT_ABORT_REASON, RIG_VERSION, WRITER, ScanJob, abort_pending,
                       check_scan_name, clear_abort_pending, default_scan_name, find_abort_pending, find_interrupted,
                       interrupted_at, interrupted_scan, load_job, name_taken, pause_before_block, takeover_note,
                       way_out)
from .adaptive import ViewChooser, live_converged
from .scan_end import ScanEnd, recorded_end
from .scan_path import back_on_path, check_left, check_way
from .scan_plan import build_plan, tcp_from_sensor
from .speed_slider import slider_status, speed_slider
from .stall import StallWatch
from .workspace import first_move_problem

log = logging.getLogger("spadscan.daemon")
STATE_TIMEOUT_S = 5.0  # how long arm.state() may take
STOP_TIMEOUT_S = 5.0  # how long arm.stop() may take
FRAME_GRACE_S = 2.0  # extra time a sensor gets beyond its own timeout before the runner gives up on it
PUBLISH_TIMEOUT_S = 60.0  # how long publishing one pose (fsyncs, rename) may take
READY_TIMEOUT_S = 60.0  # how long readying the arm after a fault (reconnecting) may take
ARM_FIXES = {"reconnect": "reconnecting", "clear": "clearing its fault"}  # what readying the arm does, said
ARM_LINK_CHECK = "check the network to the arm's controller and that the controller is on"  # for a lost arm link
CONTROLLER_TRIES = 3  # ranked views an adaptive scan offers the arm's controller for one pose before its fallback
STALL_NOTE_S = 30.0  # a pause this soon after the daemon itself stood still says so (a watchdog, a timeout may follow)
TAKING_FRAMES = ("scanning", "pausing")  # the states in which a scan takes frames ("pausing": the pose in flight)
RATE_UNIT = "frames/s"  # what status's rate_hz counts (each pose takes frames_per_pose of them), said beside it
SLIDER_READ_S = 1.0  # how long a status waits for the arm's speed slider read afresh (a UR arm answers in ms)
ARM_IDLE = ("paused", "idle")  # the states in which no scan reads the arm: status reads its speed slider itself
USER_PAUSE = "paused by user"  # the reason of the operator's pause (`ctl pause`)
SENSOR_LINK_WAIT = "`spadscan ctl resume` once the sensor's link is back (the scan does not go on by itself)"
SENSOR_LINK_BACK = "the sensor's link is back now: `spadscan ctl resume`"
"""What a pause for the sensor's lost link tells the operator to do while it is down, and once it is back."""


class _Fault(SpadscanError):
    """A fault that pauses the scan; its message is the pause reason."""


class _SensorLinkLost(LinkLost):
    """The sensor's link is down (LinkLost from the sensor): told apart from the arm's, which calls for other
    advice."""


KEPT_ENDS = 100
"""How many ended scans' records (`ScanRunner.ends`, a status each, 1-2 kB) a daemon keeps, the newest: a `wait` for
an older one reads how it ended from its folder, as for a scan that ended before the daemon started."""


class ScanRunner:
    """Owns the current scan. All methods run on the daemon's event loop; writer I/O runs on one thread."""

    def __init__(self, arm: Arm, sensor: Sensor, cfg: DaemonConfig, *, rig: dict | None = None,
                 scene: dict | None = None, root_lock: RootLock | None = None):
        self.arm, self.sensor, self.cfg = arm, sensor, cfg
        self.root = cfg.captures
        self.root_lock = root_lock
        """The captures root's lock this daemon holds (None: not checked), taken again by a new scan where the root
        was moved or its lock file removed meanwhile (`RootLock.keep`)."""
        self.rig, self.scene = rig or {}, scene or {}
        self.job: ScanJob | None = None
        self.state = "idle"
        self.last_error: str | None = None
        self.ends: dict[str, ScanEnd] = {}
        """The end of each scan this daemon ended (its state, reason and the status as it ended), the last one last:
        what `wait`, `status`'s last_scan and a refused resume say of it, whatever its folder says since."""
        self._task: asyncio.Task | None = None
        self._resume = asyncio.Event()
        self._pause_requested = False
        self._starting = False
        self._resume_checks = 0  # resumes whose checks (`_check_resumable`) are under way
        self._interrupted_op: str | None = None
        """What is being done to an interrupted scan the daemon does not hold ("taken over": `ctl resume NAME`;
        "aborted": `ctl abort NAME`), or None. One at a time: a takeover that read the scan while an abort was being
        written would rewrite scan.json to 'running' after it, undoing an abort already acknowledged. No scan may
        start meanwhile either."""
        self._end: tuple[str, str] | None = None  # (state, reason) the scan ends in when its task is cancelled
        self._ending: asyncio.Future | None = None  # the scan task's cancellation and wind-down, once begun
        self._changed = asyncio.Event()
        self._io_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="capture-writer")
        self.stalls = StallWatch()
        self.frame_waits_retried = 0
        """Frame waits begun again because the daemon itself had not run (see `stall.py`), not the sensor."""
        self.aborts = AbortBook(self._io, self._replace_error, cfg.auto_resume)
        """The aborts their capture could not record yet, written again until they land."""
        self.also_interrupted: list[str] = []
        """The interrupted scans found at start-up besides the one taken over (an older one that could not be, and a
        newer scan started, then a crash), newest first: named in `status` until taken over or aborted by name."""
        self.stuck: dict | None = None
        """The interrupted scan found at start-up that could not be taken over: {"scan", "cause", "error" (the
        last_error, with what the operator can do)}; None when there is none."""

    # ---- requests --------------------------------------------------------------------------------------------------
    async def start(self, name: str | None = None, overrides: dict | None = None) -> dict:
        """Plan and start a scan named `name` (default: scan-<time>) with [scan] keys overridden."""
        if self.job is not None:
            # A pause's reason says what a resume needs, or that only an abort will do (its folder gone).
            why = f" ({self.job.reason})" if self.state == "paused" and self.job.reason else ""
            raise ConfigError(f"scan {self.job.name!r} is {self.state} at pose {self._progress()}{why}: "
                              f"{'resume or abort it' if self.state == 'paused' else 'wait for it or abort it'} first")
        if self._starting:
            raise ConfigError("another scan is being planned; try again in a moment")
        if self._interrupted_op is not None:
            raise ConfigError(f"an interrupted scan is being {self._interrupted_op}; try again in a moment")
        self._starting = True
        try:
            return await self._start(name, overrides)
        finally:
            self._starting = False

    async def _start(self, name: str | None, overrides: dict | None) -> dict:
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CaptureError(f"cannot start a scan: {describe(exc, 'creating the captures root')}") from None
        if self.root_lock is not None:
            try:
                relocked = await asyncio.to_thread(self.root_lock.keep)
            except ConfigError as exc:
                raise ConfigError(f"cannot start a scan: {exc}") from None
            except OSError as exc:  # the new lock file's pid could not be written (a full disk)
                raise CaptureError(f"cannot start a scan: {describe(exc, 'locking the captures root')}") from None
            if relocked:
                log.warning("captures root %s was moved or removed, or its lock file deleted, while the daemon ran: "
                            "locked again", self.root)
        name = check_scan_name(name, self.root) if name is not None else default_scan_name(self.root)
        path = self.root / name
        if os.path.lexists(path):
            raise ConfigError(name_taken(name, self.root))
        scan = scan_request(self.cfg.scan, overrides or {})
        try:
            start = (await self._arm_state()).tcp_pose
        except LinkLost as exc:
            # The link went down while no scan ran (a controller rebooted, a cable re-plugged): a new scan reconnects
            # first, as a resumed one does, rather than being refused until the daemon restarts.
            log.info("scan %s: %s: the link is down (%s); reconnecting", name, self.arm.name, exc)
            try:
                await self._reconnect_arm("reconnect")
                start = (await self._arm_state()).tcp_pose
            except LinkLost as still:
                raise LinkLost(f"cannot start scan {name!r}: {one_line(still)}; {ARM_LINK_CHECK}, then start the "
                               f"scan again") from None
        plan = await asyncio.to_thread(build_plan, scan, self.cfg.arm, start_tcp=start, where=f"scan {name!r}")
        try:
            await self.arm.check_poses(plan.tcp_poses)  # the controller's own limits, before anything is created
        except ArmFault as exc:
            raise ConfigError(f"scan {name!r}: {exc}") from None
        hand_eye = self.cfg.arm.hand_eye
        chooser = None
        if scan.schedule == "adaptive":
            chooser = await asyncio.to_thread(ViewChooser, scan, self.cfg.arm, hand_eye, path)
        try:
            # Made here, exclusively: planning took a while, and a folder that appeared meanwhile (another program
            # writing there) is not ours to fill, nor to remove if the start fails.
            await self._io(path.mkdir)
        except FileExistsError:
            raise ConfigError(name_taken(name, self.root)) from None
        except OSError as exc:
            self.last_error = f"cannot start scan {name!r}: {describe(exc, 'creating the scan folder')}"
            log.warning("%s", self.last_error)
            raise CaptureError(self.last_error) from None
        try:
            writer = await self._io(CaptureWriter.create, path, self.sensor.model, scan_id=name,
                                    rig={**self.rig, "writer": WRITER, RIG_VERSION: __version__},
                                    hand_eye=hand_eye, schedule=plan.description, planned_poses=plan.sensor_poses,
                                    chunk_size=scan.chunk_size, scene=self.scene,
                                    frames_per_pose=scan.frames_per_pose)
        except (OSError, CaptureError) as exc:
            # The folder was made above, by this call: whatever create left of it is ours to remove, so that the
            # name is free again once the disk has room.
            await self._io(remove_partial, path)
            what = describe(exc, "creating the scan folder") if isinstance(exc, OSError) else str(exc)
            self.last_error = f"cannot start scan {name!r}: {what}"
            log.warning("%s", self.last_error)
            raise CaptureError(self.last_error) from None
        self.job = ScanJob(name=name, path=path, scan=scan, sensor_poses=plan.sensor_poses,
                           tcp_poses=plan.tcp_poses, hand_eye=hand_eye, writer=writer, chunk_book=writer.book,
                           controller_checked=True, chooser=chooser)
        self.job.count_from(writer.manifest.get("created_utc"))
        self._forget_earlier_error()
        self._launch("scanning")
        log.info("scan %s: %d poses x %d frames -> %s", name, len(plan), scan.frames_per_pose, path)
        return self.status()

    async def recover(self) -> None:
        """At start-up: record the aborts a disk could not take before (`abort-pending.json`), then take over a scan a
        crash or stop left 'running', paused (or resumed when auto_resume)."""
        await self._settle_pending_aborts()
        found = await asyncio.to_thread(find_interrupted, self.root)
        if not found:
            return
        self.also_interrupted = [p.name for p in found[1:]]
        if self.also_interrupted:
            log.warning("also left 'running' by an earlier daemon, not taken over: %s; `spadscan ctl resume NAME` "
                        "takes one over once no scan is held, `spadscan ctl abort NAME` ends it as it stands",
                        ", ".join(self.also_interrupted))
        await self._take_over(found[0], self.cfg.auto_resume)

    async def _take_over(self, path: Path, auto_resume: bool) -> bool:
        """Take the interrupted scan at `path` over, paused (resumed when auto_resume allows); False when it cannot
        be (`stuck`, and last_error with the reason and what the operator can do). A capture that cannot be reopened,
        or whose disk has no room for the next pose's chunk (`no_room`, as a resume checks it: the pause that a full
        disk made could not be recorded on it), is taken over paused with that cause in its reason: after the pause it
        had (the operator's, a fault's: `ScanJob.paused_for`, which the capture goes on recording alone)."""
        in_the_way = None  # why the capture cannot take the scan on (its disk), with what to do; None when it can
        try:
            job = await asyncio.to_thread(load_job, path, self.cfg.arm.hand_eye, sensor_now=self.sensor.model,
                                          rig_now=self.rig, scene_now=self.scene)
            # A block an earlier daemon recorded is checked afresh (load_job), not taken for a pause of the scan's.
            record = await asyncio.to_thread(paused_record, path)
            recorded = pause_before_block(paused_reason(record), path.name)
            try:
                job.writer = await self._io(job.reopen)
                job.record_progress(job.writer)
            except OSError as exc:  # a full disk: take the scan over all the same, paused until room is made
                in_the_way = f"{describe(exc, 'reopening the capture')}; {reopen_fix(exc)}"
                await asyncio.to_thread(job.count_published)
            else:
                if job.blocked is None:
                    in_the_way = await self._io(no_room, job, self.sensor.model)
            if job.blocked is None:
                # In a thread: thousands of poses take seconds, and the event loop must keep kicking the arm's
                # watchdog meanwhile (a 4,000-view plan blocked it 1.4 s, and the controller stopped the script).
                await asyncio.to_thread(check_left, job, self.cfg.arm)
            if job.scan.schedule == "adaptive":
                job.chooser = await asyncio.to_thread(ViewChooser, job.scan, self.cfg.arm, job.hand_eye, path)
                await asyncio.to_thread(job.count_choices)
        except (CaptureError, ConfigError, OSError) as exc:
            await self._cannot_take_over(path, exc)
            return False
        self._forget_stuck(path.name)
        job.taken_over = True
        self.job = job
        owed = _owed(job)
        # A scan that was paused when the daemon stopped (by the operator, or by a fault) stays paused: auto_resume
        # continues a scan that was interrupted, not one someone or something had stopped. An earlier takeover's own
        # note that it found the scan interrupted (recorded while it waited for `ctl resume`) is no such pause.
        paused = None if record is not None and takeover_note(record) else recorded
        auto = auto_resume and job.blocked is None and in_the_way is None and paused is None
        # What this takeover says of the scan it found interrupted while it waits for `ctl resume`: also after an
        # auto_resume refused (the sensor's link down), when "auto_resume continues it" no longer holds.
        waiting = self._takeover_note("`spadscan ctl resume` continues", owed)
        if job.blocked:
            # Said after the pause the scan had, as the capture records it (`pause_said`) for the dashboard:
            # `ctl status` and the dashboard say the same.
            job.reason = f"{paused}; {job.blocked}" if paused else job.blocked
        elif paused:
            # The pause the scan had, said as the capture records it: `ctl status` and the dashboard say the same.
            job.reason = paused
        else:
            # An earlier takeover's record (kind INTERRUPTED) is not repeated: its words may be a refused resume's
            # cause, long gone, or a pose since passed. This takeover says its own note, as the scan stands now.
            job.reason = self._takeover_note("auto_resume continues it", owed) if auto else waiting
        # Why the scan waits stays said first when a resume is refused (`_refuse_resume`), and is what the capture
        # records (`pause_said`): not the refusal's cause, which the next daemon checks afresh. A blocked scan
        # keeps the pause it had alone (the block is no pause of its own, and `pause_said` records it with that).
        job.paused_for = paused if job.blocked else paused or waiting
        job.interrupted = paused is None
        if in_the_way and not job.blocked:
            # The pause the scan had (the operator's, a fault's) stays said first: the full disk is one more thing
            # to see to, not why it was paused. The capture records that alone (or that the scan was interrupted):
            # the next daemon checks the disk again itself.
            interrupted = interrupted_at(self._progress())
            taken = f"{paused}; taken over at pose {self._progress()} (daemon restarted)" if paused else interrupted
            job.paused_for = paused or interrupted
            job.reason = self.last_error = (f"{taken}, and {in_the_way}" +
                                            (f", which takes pose(s) {owed} again first (missing from the capture)"
                                             if owed else ""))
        if job.preset_note:
            log.warning("scan %s: %s", job.name, job.preset_note)
        log.info("took over interrupted scan %s at pose %s (%s)", job.name, self._progress(),
                 "blocked: " + job.blocked if job.blocked else
                 "paused, as it was when the daemon stopped: " + job.reason if paused else
                 "paused: " + job.reason if in_the_way else
                 "resuming by itself: auto_resume" if auto else "paused until `ctl resume`")
        self._launch("paused")
        if auto:
            try:
                await self.resume()
            except ConfigError as exc:  # a cause known to persist (the sensor's link down): it stays paused
                log.warning("scan %s: auto_resume did not continue it: %s", job.name, exc)
        return True

    def _takeover_note(self, going_on: str, owed: list[int]) -> str:
        """A takeover's note of the scan it found interrupted, at the pose it stands at now: how it goes on
        (`going_on`), and the poses it takes again first (`owed`: missing from the capture)."""
        return (f"{interrupted_at(self._progress())}; {going_on}" +
                (f", taking pose(s) {owed} again first (missing from the capture)" if owed else ""))

    async def _cannot_take_over(self, path: Path, exc: BaseException) -> None:
        """Say why scan `path` cannot be taken over and what the operator can do (a damaged chunk named): the scan
        stays 'running' on disk, untouched, until `ctl resume NAME` or `ctl abort NAME`."""
        way = await asyncio.to_thread(way_out, path)
        said = f"cannot take over interrupted scan {path.name!r}: {exc}; {way}"
        log.error("%s", said)
        before = self.stuck["scan"] if self.stuck is not None else None
        if before not in (None, path.name, *self.also_interrupted):
            self.also_interrupted.append(before)  # still 'running' on disk: still named
        if path.name in self.also_interrupted:
            self.also_interrupted.remove(path.name)  # named as the one that cannot be taken over
        self.stuck = {"scan": path.name, "cause": str(exc), "error": said}
        self.last_error = said

    def _forget_earlier_error(self) -> None:
        """A scan starts, or `ctl resume NAME` takes another one over: last_error no longer shows an earlier scan's
        fault (that scan's outcome stays in `last_scan`), which beside this scan's name and progress would read as
        its own. What still stands stays, or comes back where a later fault had replaced it: an abort not recorded
        yet, a scan that could not be taken over (each names its scan, and is still current)."""
        standing = [self.aborts.said(name) for name in self.aborts.unrecorded]
        if self.stuck is not None:
            standing.append(self.stuck["error"])
        if self.last_error not in standing:
            self.last_error = standing[-1] if standing else None

    async def _interrupted(self, name: str) -> Path:
        """`interrupted_scan`; a scan that is no longer one (moved out of the root by hand, ended) is no longer named
        as one that could not be taken over or was left interrupted."""
        try:
            return await asyncio.to_thread(interrupted_scan, self.root, name)
        except ConfigError:
            # Only a scan status names is looked up (a folder's name): the error of a name that cannot be a scan's
            # (too long, a NUL, a lone surrogate) was lost to the lookup's own ("internal error: OSError: ...").
            if name in self.also_interrupted or (self.stuck is not None and self.stuck["scan"] == name):
                if await asyncio.to_thread(gone_or_ended, self.root / name):
                    self._forget_stuck(name)
            raise

    def _forget_stuck(self, name: str) -> None:
        """Scan `name` is taken over or aborted: if it is the one that could not be taken over, or one of the others
        found interrupted at start-up, status stops naming it. Another scan's takeover leaves it named: it is still
        'running' on disk, and plain `ctl resume` and `ctl abort` still point at it."""
        if name in self.also_interrupted:
            self.also_interrupted.remove(name)
        if self.stuck is None or self.stuck["scan"] != name:
            return
        if self.last_error == self.stuck["error"]:
            self.last_error = None
        self.stuck = None

    async def _settle_pending_aborts(self) -> None:
        """Record in scan.json each abort an earlier daemon could keep only in `abort-pending.json` (a full disk);
        one that still does not fit stays pending (and its scan is never taken over)."""
        for path in await asyncio.to_thread(find_abort_pending, self.root):
            reason = await asyncio.to_thread(abort_pending, path)
            try:
                state = (await asyncio.to_thread(read_json, path / MANIFEST)).get("state")
            except CaptureError as exc:
                log.warning("scan %s: %s holds an abort, but: %s", path.name, ABORT_PENDING, exc)
                continue
            if state != "running":  # recorded already; only removing the file had failed
                await asyncio.to_thread(clear_abort_pending, path)
                continue
            await self.aborts.record(path.name, path, reason, None)
            if path.name not in self.aborts.unrecorded:
                log.info("scan %s: recorded its abort (%s), which %s had kept", path.name, reason, ABORT_PENDING)

    async def pause(self) -> dict:
        """Pause after the pose in flight is published. A scan that waits only because a takeover found it
        interrupted (`ScanJob.interrupted`) is paused by the operator from now on (`_hold_taken_over`)."""
        if self.state == "scanning":
            self._pause_requested = True
            self._set_state("pausing")
            log.info("scan %s: pause requested at pose %s; pausing at pose %s, once the poses under way are published",
                     self.job.name, self._progress(), self._pause_at())
        elif self.state == "paused" and self.job is not None and self.job.interrupted and not self._aborting():
            await self._hold_taken_over(self.job)
        elif self.state not in ("pausing", "paused"):
            raise ConfigError(f"nothing to pause (daemon is {self.state})")
        return self.status()

    async def _hold_taken_over(self, job: ScanJob) -> None:
        """`ctl pause` on a scan that a takeover holds waiting, found interrupted: the wait becomes the operator's
        pause, recorded as one (kind PAUSE), so that no later daemon goes on by itself, auto_resume or not (a
        takeover's note of kind INTERRUPTED lets it). Its reason says so first; what stands in the way besides (a
        block, a full disk, a refused resume's cause) stays said after it. A resume being checked decides first."""
        if self._resume_checks:
            raise ConfigError(f"scan {job.name!r} is being resumed: pause it (`spadscan ctl pause`) once it scans")
        was, note = job.reason or "", job.paused_for or ""
        rest = (f"; {job.blocked}" if job.blocked else
                was[len(note):] if note and was.startswith(note) else "")
        job.reason, job.paused_for, job.interrupted = f"{USER_PAUSE}{rest}", USER_PAUSE, False
        if self.last_error == was:
            self.last_error = job.reason
        log.info("scan %s %s at pose %s (it waited after a takeover): it stays paused, auto_resume or not, until "
                 "`spadscan ctl resume`", job.name, USER_PAUSE, self._progress())
        self._notify()
        await self._record_pause(job)

    async def resume(self, name: str | None = None) -> dict:
        """Continue a paused scan at its first unpublished pose. `name`: a scan the daemon does not hold (found
        interrupted but not taken over, its damaged chunk moved out since): taken over first, then continued. With
        no scan held, the one that could not be taken over is tried again."""
        job = self.job
        if name is not None and (job is None or job.name != name):
            return await self._resume_interrupted(name)
        if job is None and self.stuck is not None and not self._starting:
            return await self._resume_interrupted(self.stuck["scan"])
        if self._aborting():  # (nothing to check or withdraw: the scan ends)
            raise ConfigError(self._nothing_to_resume())
        if self.state == "pausing":
            self._pause_requested = False
            self._set_state("scanning")
            log.info("scan %s: pause withdrawn, scanning on at pose %s", job.name, self._progress())
        elif self.state == "paused" and job is not None:
            if job.blocked:
                raise ConfigError(f"cannot resume scan {job.name!r}: {job.blocked}")
            self._resume_checks += 1
            try:
                await self._check_resumable(job)
                await self._read_arm()
            finally:
                # A scan task waiting for the outcome (`_wait_resume`) runs after this call's next await at the
                # earliest: by then a resume that goes on has set `_resume`, and one refused has not.
                self._resume_checks -= 1
                self._notify()
            if self.job is not job or self.state != "paused" or self._aborting():  # an abort or a resume meanwhile
                return await self.resume(name)
            self._sensor_link_back(job)
            log.info("scan %s: resumed at pose %s%s", job.name, self._progress(),
                     f" (was paused: {job.reason})" if job.reason else "")
            self._resume.set()
            job.reason = job.paused_for = None
            job.interrupted = False
            self._set_state("scanning")
        else:
            raise ConfigError(self._nothing_to_resume())
        return self.status()

    def _nothing_to_resume(self) -> str:
        """Why a resume finds no scan to continue. An abort is named, with its reason, when it is under way or ended
        the daemon's last scan (none held since): a resume raced by an abort says that the abort came first, not that
        the daemon had nothing."""
        job, said = self.job, f"nothing to resume (daemon is {self.state})"
        if job is not None:
            return said if not self._aborting() else \
                f"nothing to resume: scan {job.name!r} is being aborted ({self._end[1]})"
        last = next(reversed(self.ends), None)
        if last is None or self.ends[last].state != "aborted":
            return said
        reason = self.ends[last].reason
        return f"nothing to resume: scan {last!r} was aborted{f' ({reason})' if reason else ''}; the daemon is " \
               f"{self.state}"

    def _aborting(self) -> bool:
        """Whether an abort of the scan held is under way (its task cancelled, its wind-down not ended)."""
        return self.job is not None and self._end is not None and self._end[0] == "aborted"

    async def _check_resumable(self, job: ScanJob) -> None:
        """Before a paused scan goes on: a cause the daemon knows cheaply to persist refuses the resume at once, the
        scan left paused with that cause as its reason (a reply of 'scanning' that a pause follows a moment later
        would be untrue), and the arm is not moved: the sensor's link down (it reconnects by itself), a capture that
        cannot be reopened (a full disk, its folder removed), a disk with no room for the next pose's chunk
        (`no_room`: reopening alone may fit, as the half-written chunk it drops frees a little). The capture is
        reopened whether or not the daemon still holds it: what it holds on disk is counted again, so that a chunk
        moved out of it while the scan was paused (damaged) is taken again first (`CaptureWriter.retakes`); only the
        chunks that changed since this daemon read or published them are read again (`ScanJob.reopen`). The
        writer reopened here is the one the scan goes on with. What the resumed run fixes by itself (the arm's link:
        it reconnects) is left to it."""
        link = self.sensor.counters().get("link")
        if link == "down":
            self._refuse_resume(job, f"the link to {self.sensor.name} is down (it reconnects by itself); resume once "
                                     f"`spadscan ctl status` shows its link up")
        try:
            writer = await self._io(job.reopen)
        except (OSError, CaptureError) as exc:
            self._refuse_resume(job, reopen_problem(job, exc))
        if self.job is not job or self.state != "paused" or self._aborting():  # an abort or a resume meanwhile
            return
        job.writer = writer
        job.record_progress(writer)
        full = await self._io(no_room, job, self.sensor.model)
        if full is not None:
            self._refuse_resume(job, full)

    async def _read_arm(self) -> None:
        """Read the arm once before a resume's reply: a paused arm is not read, and the reply's speed slider
        (`status`) would be the one read before the pause. A link found down is left to the resumed run, which
        reconnects it."""
        try:
            await self._arm_state()
        except DeviceError:
            pass

    def _refuse_resume(self, job: ScanJob, cause: str) -> None:
        """Refuse to resume `job` for `cause`, which becomes its pause's reason (status tells it as it stands now)."""
        first = f"{job.paused_for}; " if job.paused_for else ""  # (why it was paused stays said)
        job.reason = self.last_error = f"{first}{cause} (pose {self._progress()})"
        log.warning("scan %s: not resumed: %s", job.name, cause)
        self._notify()
        raise ConfigError(f"cannot resume scan {job.name!r}: {cause}")

    async def _resume_interrupted(self, name: str) -> dict:
        """Take over the daemon's interrupted scan `name` (one it could not take over at start-up, or another), then
        continue it; a ConfigError says why not."""
        if self.job is not None:
            raise ConfigError(f"scan {self.job.name!r} is {self.state}: wait for it or abort it before taking over "
                              f"scan {name!r}")
        if self._starting or self._interrupted_op is not None:
            doing = "another scan is being planned" if self._starting else \
                f"an interrupted scan is being {self._interrupted_op}"
            raise ConfigError(f"{doing}; try again in a moment")
        self._interrupted_op = "taken over"
        try:
            path = await self._interrupted(name)
            if ((name in self.ends and self.ends[name].state == "aborted") or name in self.aborts.unrecorded
                    or await asyncio.to_thread(abort_pending, path) is not None):
                raise ConfigError(f"scan {name!r} was aborted (its {MANIFEST} does not say so yet: the disk could not "
                                  f"take it); it cannot be resumed")
            log.info("scan %s: taking it over (`ctl resume`)", name)
            if not await self._take_over(path, auto_resume=False):
                raise ConfigError(self.last_error)
            self._forget_earlier_error()
        finally:
            self._interrupted_op = None
        return await self.resume()

    async def abort(self, reason: str = DEFAULT_ABORT_REASON, name: str | None = None) -> dict:
        """Stop the arm, mark the scan aborted (what was published stays). `name`: a scan the daemon does not hold
        (found interrupted but not taken over, or another of its interrupted scans): marked aborted on disk, every
        chunk kept. The reply's abort_recorded says whether the capture records the abort (False: the disk could
        not take it yet; last_error says what keeps it)."""
        if name is not None and (self.job is None or self.job.name != name):
            return await self._abort_interrupted(name, reason)
        if self.job is None or self._task is None:
            stuck = self.stuck["scan"] if self.stuck is not None else None
            raise ConfigError(f"nothing to abort (daemon is {self.state})" + (
                f"; scan {stuck!r} could not be taken over: `spadscan ctl abort {stuck}` ends it" if stuck else ""))
        job = self.job
        await self._cancel(("aborted", reason))
        await asyncio.to_thread(count_as_held, job)  # the pose it stopped at, as its capture holds it
        return self._aborted_reply(job.name, job)

    async def _abort_interrupted(self, name: str, reason: str) -> dict:
        """End the daemon's interrupted scan `name`, which it does not hold, as aborted: the manifest alone is
        written (a damaged chunk does not stand in the way), nothing is removed. Set before its first await and
        held to its end, `_interrupted_op` keeps a `ctl resume NAME` from taking the scan over meanwhile."""
        if self._interrupted_op is not None:
            raise ConfigError(f"an interrupted scan is being {self._interrupted_op}; try again in a moment")
        self._interrupted_op = "aborted"
        try:
            path = await self._interrupted(name)
            if await asyncio.to_thread(writer_lock_held, path):  # its writer is open in another process
                raise ConfigError(f"scan {name!r} not aborted: another process is writing it (another daemon on this "
                                  f"captures root?); abort it there, or stop that process first")
            stuck = self.stuck if self.stuck is not None and self.stuck["scan"] == name else None
            if stuck is not None:
                reason = f"{reason}; it could not be taken over: {stuck['cause']}"
            await self.aborts.record(name, path, reason, None)
            self._forget_stuck(name)
            self._record_end(name, "aborted", reason)
        finally:
            self._interrupted_op = None
        log.info("scan %s aborted, as it stood on disk: %s", name, reason)
        self._notify()
        return self._aborted_reply(name)

    def _aborted_reply(self, name: str, job: ScanJob | None = None) -> dict:
        """The abort's reply: the status, `aborted` (the scan it ended), `abort_recorded`; for the scan the daemon
        held (`job`), the pose it stopped at as `status` and the pause reply give it (pose, poses, progress), unless
        the daemon holds another scan by now (the status's keys are that scan's)."""
        reply = {**self.status(), "aborted": name, "abort_recorded": name not in self.aborts.unrecorded}
        if job is not None and reply["scan"] is None:
            reply.update(pose=job.next_pose, poses=job.n_poses, progress=_progress_of(job))
        if name in self.aborts.folder_gone:  # removed by hand: the abort is done, with nothing to record
            reply["abort_note"] = FOLDER_GONE
        return reply

    def _replace_error(self, old: str | None, new: str | None) -> bool:
        """last_error becomes `new` if `old` is None or last_error still says `old` (it tells of nothing newer)."""
        if old is not None and self.last_error != old:
            return False
        self.last_error = new
        return True

    async def wait(self, name: str) -> dict:
        """Block until scan `name` is complete or aborted; returns {'name', 'state'}."""
        return {"name": name, "state": (await self.wait_end(name)).state}

    async def wait_end(self, name: str) -> ScanEnd:
        """Block until scan `name` is complete or aborted; returns how it ended: this daemon's record of it (`ends`),
        or for a scan this daemon never ended, what its manifest records (no status then)."""
        check_scan_name(name, self.root)
        while self.job is not None and self.job.name == name:
            changed = self._changed
            await changed.wait()
        if name in self.ends:
            return self.ends[name]
        m = self.root / name / MANIFEST
        manifest = await asyncio.to_thread(read_json, m) if m.is_file() else {}
        end = recorded_end(manifest)
        if end is None:
            raise ConfigError(await self._not_held(name, manifest.get("state")))
        return end

    async def _not_held(self, name: str, state: str | None) -> str:
        """Why `wait NAME` cannot wait for scan `name`, which this daemon does not hold and whose capture has not
        ended: it does not exist, its abort is not recorded yet, or it is interrupted (not taken over, or could not
        be), with the ways out."""
        if state is None:
            return f"no scan named {name!r} is running or finished in {self.root}"
        if name in self.aborts.unrecorded:
            return self.aborts.said(name)
        if await asyncio.to_thread(abort_pending, self.root / name) is not None:
            return (f"scan {name!r} is aborted, but its {MANIFEST} does not say so yet ({ABORT_PENDING} keeps it: no "
                    f"daemon takes it over, and the next one records it)")
        held = f"scan {name!r} is interrupted and not held by this daemon, so it neither ends nor goes on by itself"
        if self.stuck is not None and self.stuck["scan"] == name:
            return f"{held}: {self.stuck['error']}"
        try:
            await asyncio.to_thread(interrupted_scan, self.root, name)
        except ConfigError as exc:  # not the daemon's (another tool's capture left 'running')
            return f"not waiting for scan {name!r}: {exc}"
        return (f"{held}: `spadscan ctl resume {name}` takes it over and continues it; or `spadscan ctl abort "
                f"{name}` ends it as aborted, keeping every chunk")

    async def shutdown(self) -> None:
        """Stop the scan in flight (leaving its capture 'running', resumable) and the writer thread; then say where
        the scan was left (`_left_note`), once the writer thread has ended: a publish still landing as the scan was
        stopped is counted (the scan task, cancelled while it waited for it, never counted it)."""
        left = None
        if self._task is not None:
            job, paused, error = self.job, self.state in ("paused", "pausing"), self.last_error
            await self._cancel(("running", "daemon stopped; a restarted daemon resumes at the first unpublished pose"))
            if job is not None and self.job is job:  # (an abort under way ended it: not left)
                left = (job, paused, self.last_error if self.last_error != error else None)
        await self.aborts.close()
        self._io_pool.shutdown(wait=True)
        if left is not None:
            log.info("%s", self._left_note(*left))
        if self.job is not None and self.job.writer is not None:
            # Its writer lock goes now, not when the writer is collected: a daemon started next in this process's
            # place (or beside it, in a test) may take the scan over at once.
            self.job.writer.close()

    def _left_note(self, job: ScanJob, paused: bool, unrecorded: str | None) -> str:
        """Where a scan the daemon stops with stands, and how it goes on: the last line an operator who stopped the
        daemon (Ctrl-C, SIGTERM) reads. `unrecorded`: why its state could not be recorded on stopping. Called once
        the writer thread has ended. The pose is the one the next daemon takes the scan over at (`count_as_held`)."""
        count_as_held(job)
        self._sensor_link_back(job)
        at = f"scan {job.name} left {'paused ' if paused else ''}at pose {self._progress()}"
        why = job.paused_for if job.blocked else job.reason  # (a block is said once, below)
        if paused and why:
            at += f" ({why})"
        if job.blocked:
            return f"{at}; not resumable as the rig stands: {job.blocked}"
        if unrecorded is not None:
            return f"{at}; {unrecorded}"
        on = "it goes on by itself (auto_resume)" if self.cfg.auto_resume and not paused else \
            "then `spadscan ctl resume`"
        return f"{at}, resumable: start the daemon again, {on}"

    async def status_now(self) -> dict:
        """`status` for a request (`ctl status`): while no scan reads the arm (paused, idle), its speed slider is read
        afresh first, within SLIDER_READ_S (the reading from before a pause must not stand for the slider now; one
        that cannot be renewed is shown with its age)."""
        if self.state in ARM_IDLE:
            try:
                async with asyncio.timeout(SLIDER_READ_S):
                    await self.arm.read_speed_slider()
            except (TimeoutError, DeviceError):
                pass  # (a link down is the resume's to handle: status says what it last read, and when)
        await self._count_owed()
        return self.status()

    async def _count_owed(self) -> None:
        """While a scan is paused, its progress as its resume will find it, counted afresh from its folder
        (`ScanJob.stock_on_disk`): a chunk the operator moved out during the pause shows at once, not only after
        `ctl resume`: one before the newest under poses_to_take_again, the newest ones as a lower pose and frame
        count (the resume goes on from the first pose they held). Where only the resume can count (a chunk changed
        since the daemon read it), the progress stays as last counted and `owed_note` says why."""
        job = self.job
        if job is None or self.state != "paused" or job.blocked or self._resume_checks:
            return
        stock, note = await asyncio.to_thread(counted_on_disk, job)
        # (a resume or an abort meanwhile counts on its own: the resume reopens the capture)
        if self.job is job and self.state == "paused" and not self._resume_checks:
            if stock is not None:
                job.record_stock(stock)
            job.owed_note = note

    def status(self) -> dict:
        job = self.job
        if self.state == "paused":
            self._sensor_link_back(job)
        out = {"state": self.state, "scan": None, "last_error": self.last_error, "arm": self.arm.name,
               "sensor": {"name": self.sensor.name, **self.sensor.counters()}}
        out.update(slider_status(self.arm))
        if job is not None:
            now = time.monotonic()  # read once: elapsed_s and scan_elapsed_s differ by the time before the takeover
            out.update(scan=job.name, path=str(job.path), pose=job.next_pose, poses=job.n_poses,
                       progress=self._progress(), frames=job.frames, frames_per_pose=job.scan.frames_per_pose,
                       dropped_frames=job.dropped, rate_hz=self._rate_hz(job), rate_unit=RATE_UNIT,
                       eta_s=scan_eta_s(job) if self.state == "scanning" else None, reason=job.reason,
                       elapsed_s=round(now - job.started, 3), started_utc=job.started_utc,
                       scan_elapsed_s=_rounded(job.scan_elapsed_s(now), 3), schedule=job.scan.schedule)
            if job.chooser is not None:
                out["views_chosen"] = dict(sorted(job.view_counts.items()))
            unsure = job.owed_note if self.state == "paused" else None  # why the resume may owe more (_count_owed)
            if job.owed or unsure:  # (kept on the job: a fault's pause drops the writer)
                out["poses_to_take_again"] = list(job.owed)
            if unsure:
                out["poses_to_take_again_note"] = unsure
            if job.preset_note:  # (the preset the scan was planned with differs, and the scan goes on all the same)
                out["preset_note"] = job.preset_note
            if self.state == "pausing":
                out["pausing_at"] = self._pause_at()
        if self.ends:
            name = next(reversed(self.ends))
            out["last_scan"] = {"name": name, "state": self.ends[name].state}
        if self.aborts.unrecorded:
            out["unrecorded_aborts"] = self.aborts.status()
        if self.stuck is not None:
            out["cannot_take_over"] = {"scan": self.stuck["scan"], "error": self.stuck["error"]}
        if self.also_interrupted:
            out["also_interrupted"] = list(self.also_interrupted)
        out["daemon_stalls"] = {**self.stalls.counters(), "frame_waits_retried": self.frame_waits_retried}
        return out

    def _rate_hz(self, job: ScanJob) -> float | None:
        """Frames published per second over the last 10 s; None while the scan takes no frames (paused): a rate
        then would say a paused scan, or one stopped by a silent sensor, is measuring (the dashboard shows none
        either)."""
        return round(job.rate_hz(), 2) if self.state in TAKING_FRAMES else None

    # ---- the scan task ---------------------------------------------------------------------------------------------
    def _launch(self, state: str) -> None:
        self._pause_requested = False
        self._resume.clear()
        self._end, self._ending = None, None
        self._set_state(state)
        self._task = asyncio.create_task(self._run(self.job, paused=(state == "paused")), name=f"scan {self.job.name}")

    async def _run(self, job: ScanJob, paused: bool) -> None:
        watch = asyncio.ensure_future(self.stalls.run())
        try:
            await self._run_scan(job, paused)
        finally:
            watch.cancel()
            await asyncio.gather(watch, return_exceptions=True)

    async def _run_scan(self, job: ScanJob, paused: bool) -> None:
        try:
            if paused:
                await self._wait_resume(job)
            while True:
                self._check_end()
                if job.writer is None:
                    try:
                        job.writer = await self._io(job.reopen)
                        job.record_progress(job.writer)
                        if "paused" in job.writer.manifest:  # reopened to go on after a fault's pause
                            await self._io(job.writer.set_state, "running")
                    except (OSError, CaptureError) as exc:
                        await self._fault(job, reopen_problem(job, exc))
                        continue
                if self._pause_requested:
                    job.reason = USER_PAUSE
                    log.info("scan %s %s at pose %s", job.name, USER_PAUSE, self._progress())
                    await self._wait_resume(job)
                    continue
                try:
                    await self._ready_arm(job)
                    await self._retake(job)
                    await self._poses(job)
                    if job.ended_early is not None:
                        if await self._io(lost_chunks, job):
                            continue  # taken again (`_retake`), then ended where the scan stands
                        await self._io(end_early, job)
                        break
                    if not self._pause_requested:
                        if job.next_pose >= job.n_poses:
                            if await self._io(lost_chunks, job):
                                continue  # taken again (`_retake`), then complete
                            await self._io(finish_capture, job)
                            break
                        # A pause withdrawn (resume) while the pose in flight was being published: the loop stopped
                        # for the pause all the same, and finishing here marked a partial capture complete. Go on
                        # from the first pose not taken.
                        continue
                except (DeviceError, OSError, CaptureError, ConfigError, _Fault) as exc:
                    # (ConfigError: a pose the workspace refuses now, its config tightened since the scan began: a
                    # pause with the reason, not an "internal error".) What the arm needs before it moves again, once
                    # the user resumes.
                    job.arm_fix = ("reconnect" if isinstance(exc, LinkLost) else
                                   "clear" if isinstance(exc, ArmFault) else job.arm_fix)
                    at, job.way_at = self._fault_at(job), None
                    await self._fault(job, self._fault_reason(exc, at))
                except asyncio.CancelledError:
                    raise
                except Exception as exc:  # a bug must pause the scan, never kill the daemon
                    log.exception("scan %s: unexpected error", job.name)
                    await self._fault(job, f"internal error: {type(exc).__name__}: {exc}")
            self._finish(job, "complete", job.ended_early)
        except asyncio.CancelledError:
            await self._wind_down_whole(job)
            raise

    async def _ready_arm(self, job: ScanJob) -> None:
        """Before the first move of a run: reconnect after a lost link, clear a fault (see the module docstring). The
        link is checked whatever paused the scan: it may have dropped and come back meanwhile (a controller rebooted,
        a cable re-plugged), and the first resume must reconnect it, not pause again for it. A failure raises like
        any fault (and the fix is tried again at the next resume)."""
        fix = job.arm_fix
        if fix != "reconnect" and not await self._link_up(job):
            fix = "reconnect"
        if fix is None:
            return
        log.info("scan %s: %s: %s before pose %s", job.name, self.arm.name, ARM_FIXES[fix], self._progress())
        await self._reconnect_arm(fix)
        job.arm_fix = None

    async def _link_up(self, job: ScanJob) -> bool:
        """Whether the arm's link answers (a state read); False, logged, on LinkLost."""
        try:
            await self._arm_state()
        except LinkLost as exc:
            log.info("scan %s: %s: the link is down (%s)", job.name, self.arm.name, exc)
            return False
        return True

    async def _reconnect_arm(self, fix: str) -> None:
        """Reconnect the arm (fix "reconnect") and clear its fault, within READY_TIMEOUT_S."""
        try:
            async with asyncio.timeout(READY_TIMEOUT_S):
                if fix == "reconnect":
                    await self.arm.reconnect()
                await self.arm.clear_fault()
        except TimeoutError:
            raise LinkLost(f"{self.arm.name}: {ARM_FIXES[fix]} did not finish within {READY_TIMEOUT_S:g} s") from None

    async def _poses(self, job: ScanJob) -> None:
        """Run poses from job.next_pose until the plan ends or a pause is requested; raises on a fault. An adaptive
        scan chooses each pose first (`_choose`), and ends here when the live reconstruction has converged."""
        pending = None  # the previous pose's publish, overlapping this pose's move, settle and frames
        replan = None  # an adaptive scan's schedule.npy being rewritten for this pose, overlapping its move
        ahead = None  # an adaptive scan's choice of the next pose, made while this pose's frames are taken
        try:
            for i in range(job.next_pose, job.n_poses):
                self._check_end()
                if self._pause_requested:
                    break
                if job.chooser is not None:
                    if await self._converged(job, i):
                        break
                    replan, ahead = await self._choose(job, i, ahead), None
                if i == job.next_pose:
                    await self._check_first_move(job, i)
                job.in_flight = i
                t_stop = await self._move(job, i)
                if job.chooser is not None and i + 1 < job.n_poses:
                    ahead = asyncio.ensure_future(asyncio.to_thread(job.chooser.choose, job.sensor_poses, i + 1))
                await self._settle(job, i)
                await self.sensor.begin_exposure()  # a sensor that can starts a fresh exposure now
                frames = await self._frames(job, i, t_stop + job.scan.settle_s)
                arm = await self._check_stop(i, f"while capturing pose {i}")
                if pending is not None:  # pose i-1 lands before pose i is handed over: one finished pose unpublished
                    p, pending = pending, None
                    await self._landed(p, i - 1)
                    job.record_progress(job.writer)
                    self._count_choice(job, i - 1)
                    self._notify()
                if replan is not None:  # row i names this pose on disk before its chunk is published
                    r, replan = replan, None
                    await self._landed(r, i)
                pending = asyncio.ensure_future(self._io(self._publish, job.writer,
                                                         pose_measurements(job, i, frames, arm, job.choices.get(i))))
        finally:
            try:
                if replan is not None or ahead is not None:  # a rewrite of schedule.npy lands before the writer is
                    # reopened; a choice made ahead is dropped (the next run chooses afresh)
                    await asyncio.gather(*(f for f in (replan, ahead) if f is not None), return_exceptions=True)
                if pending is not None:  # let the publish land before anything else touches the writer
                    try:
                        await asyncio.shield(pending)
                    finally:
                        if pending.done() and not pending.cancelled() and pending.exception() is None:
                            job.record_progress(job.writer)
                            self._count_choice(job, job.next_pose - 1)
                            self._notify()
            finally:
                job.in_flight = None

    async def _retake(self, job: ScanJob) -> None:
        """Take again what the capture lacks before its first unpublished pose (`CaptureWriter.retakes`: a damaged
        chunk the operator moved out) before the scan goes on. Moves are straight lines (moveL), and one from the
        scan's end back to an early pose would cross the object: so the arm goes to the published pose nearest to it,
        back along the scan's own path to the first pose owed, and forward along it again to the last published
        pose, capturing each owed pose's missing frames as it first passes it (published under the chunk numbers
        that keep the capture in pose order). Nothing overlaps: it is rare, and a pause or a fault finds nothing in
        flight; the next run starts the way again from where the arm then is. That holds once every owed pose is
        taken, too: the way forward still unfinished (`job.way_on`), the next run walks it on, instead of moving
        straight from an early pose to the scan's next one. A daemon restarted meanwhile knows nothing of the way:
        it walks it on when the arm stands on the scan's path before its last published pose (`back_on_path`).
        Before the arm goes, every pose and move of the way is checked against the current [arm] limits
        (`check_way`): a refusal pauses the scan with the reason, the arm not moved."""
        if self._pause_requested:
            return
        owed = {r.pose: r for r in job.writer.retakes}
        last = job.next_pose - 1
        if not (owed or job.way_on or job.taken_over) or last < 0:
            return
        now = np.asarray((await self._arm_state()).tcp_pose, dtype=np.float64)
        start = int(np.argmin(np.linalg.norm(job.tcp_poses[:last + 1, :3, 3] - now[:3, 3], axis=1)))
        if job.taken_over and not owed and start < last and back_on_path(job, now[:3, 3]):
            job.way_on = True
            log.info("scan %s: %s stands on the scan's path near pose %d, before its last published pose %d "
                     "(taken over during the retake's way forward?)", job.name, self.arm.name, start, last)
        job.taken_over = False
        if not owed and (not job.way_on or start >= last or job.next_pose >= job.n_poses):  # (no move follows)
            job.way_on = False
            return
        low = min(owed) if owed else start
        way = list(range(start, low, -1)) + list(range(low, last + 1)) if start > low else \
            list(range(start, last + 1))
        turn = start - low + 1 if start > low else 0  # way[:turn] goes back along the path (to `low`), the rest on
        if owed:
            log.info("scan %s: taking pose(s) %s again (missing from the capture), by way of poses %s", job.name,
                     ", ".join(map(str, sorted(owed))), f"{start}..{low}..{last}" if start > low else
                     f"{start}..{last}")
        else:
            log.info("scan %s: walking on along the scan's path from pose %d to pose %d before pose %d", job.name,
                     start, last, job.next_pose)
        first = min(start, low)
        # The takeover checked the poses from the first owed or unpublished one against the current [arm] limits;
        # the way may begin before it (the arm nearer an earlier pose, or walking on after a restart). A config
        # tightened since the scan began must stop the scan here, before the arm goes, not once it stands there.
        await asyncio.to_thread(check_way, job, first, last, self.cfg.arm)
        if not job.controller_checked:  # the way back passes poses before `start`: the controller is asked from there
            await self.arm.check_poses(job.tcp_poses[first:], first_index=first)
            job.controller_checked = True
        await self._check_first_move(job, start)
        job.way_on = True
        for k, i in enumerate(way):
            self._check_end()
            if self._pause_requested:
                job.way_at = None
                return
            direction = "back" if k < turn else "forward"
            job.way_at = (i, "moving to", direction)
            retake = owed.pop(i, None)
            if retake is None:
                await self._move(job, i)
                continue
            job.in_flight = i
            try:
                await self._retake_pose(job, retake)
            finally:
                job.in_flight = None
        job.way_on, job.way_at = False, None

    async def _retake_pose(self, job: ScanJob, retake) -> None:
        """Move to pose `retake.pose`, capture its missing frames and publish them (see `_retake`)."""
        i = retake.pose
        t_stop = await self._move(job, i)
        if job.way_at is not None:
            job.way_at = (i, "at", job.way_at[2])
        await self._settle(job, i)
        await self.sensor.begin_exposure()
        frames = await self._frames(job, i, t_stop + job.scan.settle_s, len(retake.frames))
        arm = await self._check_stop(i, f"while capturing pose {i}")
        whole = len(retake.frames) == job.scan.frames_per_pose
        choice = None if job.chooser is None else {
            "why": "retaken", "detail": "taken again after its chunk was moved out of the capture (damaged)"}
        measurements = pose_measurements(job, i, frames, arm, choice, numbers=retake.frames)
        await self._landed(asyncio.ensure_future(self._io(job.writer.publish_retake, retake, measurements)), i)
        job.record_progress(job.writer)
        if choice is not None and whole:  # a pose some of whose frames stayed is counted by why it was first taken
            job.view_counts["retaken"] += 1
        log.info("scan %s: pose %d taken again (%d frame(s))", job.name, i, len(frames))
        self._notify()

    async def _choose(self, job: ScanJob, i: int, ahead: asyncio.Future | None = None) -> asyncio.Future | None:
        """Choose pose i of an adaptive scan (`adaptive.ViewChooser`; `ahead`: that choice, begun while the pose
        before was captured, so that reading next_views.json costs the scan no time); returns the rewrite of
        schedule.npy it needs (None when row i stays), which runs beside the move. A ranked view the arm's controller
        refuses is passed over (CONTROLLER_TRIES at most, then the fallback plan)."""
        plan = job.sensor_poses
        for _ in range(CONTROLLER_TRIES):
            if ahead is not None:
                (choice, rows), ahead = await ahead, None
            else:
                choice, rows = await asyncio.to_thread(job.chooser.choose, plan, i)
            if choice.why != "adaptive":
                break
            try:
                await self.arm.check_poses(tcp_from_sensor(rows[i:i + 1], job.hand_eye), first_index=i)
                break
            except ArmFault as exc:
                log.info("scan %s: ranked view %s for pose %d refused by the controller: %s", job.name,
                         choice.record.get("rank"), i, exc)
                job.chooser.refuse(choice.candidate)
        else:
            choice, rows = await asyncio.to_thread(job.chooser.fallback, plan, i,
                                                   f"{CONTROLLER_TRIES} ranked views refused by the controller")
        job.choices[i] = choice.record
        if rows is plan or np.array_equal(rows, plan):
            return None
        job.sensor_poses, job.tcp_poses = rows, tcp_from_sensor(rows, job.hand_eye)
        return asyncio.ensure_future(self._io_side(job.writer.replace_schedule, rows.copy()))

    async def _converged(self, job: ScanJob, i: int) -> bool:
        """Whether an adaptive scan with stop_when_converged ends before pose i (sets job.ended_early)."""
        scan = job.scan
        if not scan.stop_when_converged or i < scan.initial_views:
            return False
        why = await asyncio.to_thread(live_converged, job.path, scan.initial_views)
        if why is None:
            return False
        job.ended_early = f"ended at {i} of {job.n_poses} poses: {why} (stop_when_converged)"
        log.info("scan %s %s", job.name, job.ended_early)
        return True

    @staticmethod
    def _count_choice(job: ScanJob, i: int) -> None:
        record = job.choices.pop(i, None)
        if record is not None:
            job.view_counts[record["why"]] += 1

    async def _check_first_move(self, job: ScanJob, i: int) -> None:
        """The first move of a run starts wherever the arm is now (after a pause it may have been jogged anywhere):
        check it as every planned move was checked, and refuse it with the reason. After a pause or a restart the
        arm's controller is asked again about the poses still to come (its limits may have changed meanwhile)."""
        if not job.controller_checked:
            await self.arm.check_poses(job.tcp_poses[i:], first_index=i)
            job.controller_checked = True
        now = np.asarray((await self._arm_state()).tcp_pose, dtype=np.float64)
        problem = first_move_problem(now, job.tcp_poses[i], self.cfg.arm)
        if problem:
            at = ", ".join(f"{v:.3f}" for v in now[:3, 3])
            raise _Fault(f"{self.arm.name} at [{at}] m is not moved to pose {i}: {problem} ([arm] limits); jog it "
                         f"back into the workspace near pose {i}, then `spadscan ctl resume`")

    def _check_end(self) -> None:
        """Honour an abort or shutdown even if its cancellation was absorbed by a device call that finished at the
        same moment: the request is also recorded in self._end."""
        if self._end is not None:
            raise asyncio.CancelledError()

    @staticmethod
    async def _landed(publish: asyncio.Future, i: int) -> None:
        """Wait for pose i's publish; a disk that stalls past PUBLISH_TIMEOUT_S pauses the scan (the write may still
        land later: the writer thread finishes it before the capture is reopened)."""
        try:
            async with asyncio.timeout(PUBLISH_TIMEOUT_S):
                await asyncio.shield(publish)
        except TimeoutError:
            publish.add_done_callback(lambda f: f.cancelled() or f.exception())  # retrieved: no "never retrieved"
            raise _Fault(f"capture writer: publishing pose {i} did not finish within {PUBLISH_TIMEOUT_S:g} s "
                         f"(disk stalled?)") from None

    async def _move(self, job: ScanJob, i: int) -> float:
        """Move to pose i; returns the monotonic time the arm stopped. Its limit, move_timeout_s, counts motion time
        (`MoveClock`): a move the pendant's speed slider slows is not taken for a stuck one."""
        clock = MoveClock(self.cfg.arm.move_timeout_s, lambda: speed_slider(self.arm))
        try:
            async with asyncio.timeout_at(clock.deadline()) as limit:
                follow = asyncio.ensure_future(clock.follow(limit))
                try:
                    await self.arm.move_to(job.tcp_poses[i], self.cfg.arm.speed, self.cfg.arm.acceleration)
                finally:
                    follow.cancel()
                    await asyncio.gather(follow, return_exceptions=True)
        except TimeoutError:
            raise ArmFault(clock.timed_out(self.arm.name, i)) from None
        return time.monotonic()

    async def _check_stop(self, i: int, when: str) -> ArmState:
        """The arm's state at pose i; ArmFault naming the safety stop that holds it, if one does, and `when` it was
        found (the operator clears each stop in its own way at the rig)."""
        arm = await self._arm_state()
        self._check_end()
        stop = stop_name(arm)
        if stop is not None:
            raise ArmFault(f"{stop} on {self.arm.name} {when}; {clear_advice(stop)}")
        return arm

    async def _settle(self, job: ScanJob, i: int) -> None:
        """Let the arm settle at pose i (settle_s), then check that no safety stop holds it: one that came as the
        move ended, or while the arm settled, is named so, not as one while the pose was captured (the operator
        looks for its cause where the arm was then)."""
        if job.scan.settle_s > 0:
            await asyncio.sleep(job.scan.settle_s)
        await self._check_stop(i, f"at pose {i}, as the move there ended or the arm settled (before its frames)")

    async def _frames(self, job: ScanJob, i: int, ready_t: float, count: int | None = None) -> list[Frame]:
        """K frames (`count`, else frames_per_pose) that began at or after ready_t; earlier ones (exposed while moving
        or settling) are dropped.
        Each wait counts frame_timeout_s on the sensor's `wait_clock` (a simulated sensor's stands still while this
        process renders a frame that is due). A wait the daemon itself slept through (stopped, suspended:
        `stall.py`), or one that ran out while the sensor started again on its own (`Sensor.starting_left`), is
        begun again, not blamed on the sensor."""
        timeout = self.cfg.sensor.frame_timeout_s
        model = self.sensor.model
        clock = self.sensor.wait_clock
        frames: list[Frame] = []
        since, slept_since = clock(), time.monotonic()  # (the stall watch counts on the monotonic clock)
        deadline, dropped = since + timeout, job.dropped
        last_arrival = since  # when the sensor last delivered a frame, dropped or kept
        while len(frames) < (job.scan.frames_per_pose if count is None else count):
            left = deadline - clock()
            if left <= 0:
                extra = self._wait_again(job, i, slept_since)
                if extra is not None:
                    since, slept_since = clock(), time.monotonic()
                    deadline, dropped = since + timeout + extra, job.dropped
                    continue
                raise self._too_late(job, i, dropped) or SensorSilent(
                    f"{self.sensor.name}: no frame that began after the arm settled within {timeout:g} s at pose {i}")
            try:
                f = await wait_counted(self.sensor.next_frame(left), left + FRAME_GRACE_S, clock)
            except LinkLost as exc:
                raise _SensorLinkLost(str(exc)) from None
            except (TimeoutError, SensorSilent) as exc:
                extra = self._wait_again(job, i, slept_since)
                if extra is not None:
                    since, slept_since = clock(), time.monotonic()
                    deadline, dropped = since + timeout + extra, job.dropped
                    continue
                # Frames kept coming until just now (a backlog of early ones): not silence.
                too_late = self._too_late(job, i, dropped)
                if too_late is not None and clock() - last_arrival < timeout / 2:
                    raise too_late from None
                if isinstance(exc, TimeoutError):
                    raise SensorSilent(f"{self.sensor.name}: next_frame did not return within "
                                       f"{left + FRAME_GRACE_S:.1f} s at pose {i}") from None
                # The sensor names the rest of the timeout it was given (0.953291 s); the operator set the whole.
                # Why the sensor went silent (e.g. the error its bridge reported), where it knows, stays in the reason.
                detail = exc.detail
                raise SensorSilent(f"{self.sensor.name}: no complete frame within {timeout:g} s (frame_timeout_s) "
                                   f"at pose {i}" + (f"; {detail}" if detail else "")) from None
            last_arrival = clock()
            if f.t_start < ready_t:
                job.dropped += 1
                continue
            if np.shape(f.hists) != (model.n_zones, model.n_bins):
                raise DeviceError(f"{self.sensor.name}: frame of shape {np.shape(f.hists)}, expected "
                                  f"({model.n_zones}, {model.n_bins})")
            frames.append(f)
            since, slept_since = clock(), time.monotonic()
            deadline, dropped = since + timeout, job.dropped  # each kept frame starts a wait of its own
        return frames

    def _too_late(self, job: ScanJob, i: int, dropped_before: int) -> FramesTooEarly | None:
        """The fault when every frame of a wait came but began too early (the count is status' dropped_frames)."""
        if job.dropped <= dropped_before:
            return None
        return FramesTooEarly(f"{self.sensor.name}: {job.dropped - dropped_before} frames in "
                            f"{self.cfg.sensor.frame_timeout_s:g} s (frame_timeout_s) at pose {i}, none begun after "
                            f"the arm settled")

    def _wait_again(self, job: ScanJob, i: int, slept_since: float) -> float | None:
        """Whether a frame wait that ran out is begun again, and with how many seconds on top of its frame_timeout_s:
        0 when the daemon itself stood still meanwhile (`_slept_through`), the rest of the sensor's own start when
        one is under way (`_sensor_starting`); None when neither: the sensor is silent."""
        if self._slept_through(job, i, slept_since):
            return 0.0
        starting = self._sensor_starting(job, i)
        return starting if starting > 0 else None

    def _sensor_starting(self, job: ScanJob, i: int) -> float:
        """Seconds the sensor says its own start may still take (`Sensor.starting_left`: a bridge that reset and
        set its sensor up again, after a replug that powered it off), logged; 0 when none is under way. A frame wait
        that runs out meanwhile is begun again, to run its frame_timeout_s from the start's end."""
        starting = self.sensor.starting_left()
        if starting <= 0:
            return 0.0
        log.warning("scan %s: the sensor is starting again (its bridge set it up afresh) at pose %d; waiting up to "
                    "%.0f s more for its first frame", job.name, i, starting + self.cfg.sensor.frame_timeout_s)
        return starting

    def _slept_through(self, job: ScanJob, i: int, since: float) -> bool:
        """Whether the daemon itself stood still while it waited for a frame since `since` (then the wait is begun
        again and counted in status' daemon_stalls)."""
        stalled = self.stalls.stalled_between(since, time.monotonic())
        if stalled <= 0:
            return False
        self.frame_waits_retried += 1
        log.warning("scan %s: the daemon itself did not run for %.1f s while it waited for a frame at pose %d "
                    "(stopped or suspended); waiting for the frame again", job.name, stalled, i)
        return True

    @staticmethod
    def _publish(writer: CaptureWriter, measurements: list[Measurement]) -> None:
        for m in measurements:
            writer.append(m)
        writer.flush()

    async def _arm_state(self):
        try:
            async with asyncio.timeout(STATE_TIMEOUT_S):
                return await self.arm.state()
        except TimeoutError:
            raise LinkLost(f"{self.arm.name}: no state within {STATE_TIMEOUT_S:g} s") from None

    async def _stop_arm(self) -> None:
        try:
            async with asyncio.timeout(STOP_TIMEOUT_S):
                await self.arm.stop()
        except TimeoutError:
            self.last_error = f"{self.arm.name}: stop did not return within {STOP_TIMEOUT_S:g} s"
        except DeviceError as exc:
            self.last_error = str(exc)

    # ---- pausing, ending -------------------------------------------------------------------------------------------
    async def _fault(self, job: ScanJob, reason: str) -> None:
        """Pause on a fault: stop the arm, drop the writer (reopened on resume), wait for `ctl resume`."""
        reason += self._stall_note()
        log.warning("scan %s paused: %s", job.name, reason)
        await self._stop_arm()
        close_writer(job)
        job.reason = self.last_error = reason
        await self._wait_resume(job)

    async def _record_pause(self, job: ScanJob, paused: bool = True) -> None:
        """Say in scan.json that the scan is paused and why (or, `paused` False, that it goes on: through the open
        writer's next state): a daemon restarted meanwhile (a crash, `systemctl restart`) takes a paused scan over
        paused, even with auto_resume, instead of moving the arm again by itself. A capture that cannot be written (a
        full disk) keeps the pause in memory only."""
        try:
            if paused:
                await self._io(mark_paused, job.path, pause_said(job) or "paused", pause_kind(job))
            else:
                await self._io(job.writer.set_state, "running")
        except (OSError, CaptureError) as exc:
            log.warning("scan %s: the pause could not be recorded in its capture: %s", job.name, describe(exc))

    def _stall_note(self) -> str:
        """What to add to a pause's reason when the daemon itself stood still just before (the UR watchdog stops the
        arm then, a device's timeout may fire): the fault may be the stall's, not the device's."""
        last = self.stalls.last_stall()
        if last is None or time.monotonic() - last[1] > STALL_NOTE_S:
            return ""
        return f"; the daemon itself had not run for {last[1] - last[0]:.1f} s just before (stopped or suspended)"

    async def _wait_resume(self, job: ScanJob) -> None:
        # The event is cleared after each resume and only set while the state is 'paused', so a resume that lands
        # between 'paused' being announced and this wait starting is not lost.
        self._pause_requested = False
        job.controller_checked = False
        # A scan launched paused and resumed before its task first ran (a takeover's auto_resume, `ctl resume
        # NAME`): the reply said 'scanning', and announcing (and recording) a pause now would be untrue. So would
        # one announced while that resume is still being checked (`_check_resumable`): its outcome decides.
        while self._resume_checks and not self._resume.is_set():
            await self._changed.wait()
        if not self._resume.is_set():
            self._set_state("paused")
            await self._record_pause(job)
            await self._resume.wait()
        self._resume.clear()
        job.reason = job.paused_for = None
        job.interrupted = False
        if job.writer is not None:  # (without one, the writer reopened on the way on clears the record)
            await self._record_pause(job, paused=False)
        self._set_state("scanning")

    async def _cancel(self, end: tuple[str, str]) -> None:
        """End the scan task in `end` (its wind-down records it). An abort already under way stays an abort: a
        shutdown that follows (SIGTERM) waits for it instead of turning it back into 'running'. The wind-down is
        shielded: a cancelled caller (ControlServer.close cancels the `ctl abort` handler on SIGTERM) leaves it
        running to its end; cancelled with the caller, it would cut the arm's stop short and leave the abort
        unrecorded."""
        if self._end is None or self._end[0] != "aborted":
            self._end = end
        if self._ending is None:
            self._ending = asyncio.ensure_future(self._end_task(self._task, self.job))
        await asyncio.shield(self._ending)

    @staticmethod
    async def _end_task(task: asyncio.Task, job: ScanJob) -> None:
        # A task cancelled before its first step never runs its body, which records the scan's end in its capture
        # (an abort right after a takeover's resume left it 'running'): one turn of the loop runs that step first.
        await asyncio.sleep(0)
        # A task that woke in the same turn as the request (a publish landed, an arm reply came) has met `_check_end`
        # and begun its wind-down by itself: cancelled now, the wind-down would be cut short (the abort acknowledged
        # but never recorded, the daemon left 'scanning' with no task).
        if job.winding_down is None:
            task.cancel()
        try:
            await task
        except asyncio.CancelledError:
            pass

    async def _wind_down_whole(self, job: ScanJob) -> None:
        """Run the scan's wind-down to its end whoever cancels the scan task meanwhile: it runs as a future of its own,
        waited for again after each cancellation (the task ends cancelled all the same once it is done)."""
        job.winding_down = winding = asyncio.ensure_future(self._wind_down(job))
        while not winding.done():
            try:
                await asyncio.shield(winding)
            except asyncio.CancelledError:
                continue
        winding.result()

    async def _wind_down(self, job: ScanJob) -> None:
        """The scan task was cancelled (abort or shutdown): stop the arm, record the end state in the manifest."""
        state, reason = self._end or ("running", "scan task cancelled")
        await self._stop_arm()
        if state == "aborted":
            await self.aborts.record(job.name, job.path, reason, job.writer)
            self._finish(job, "aborted", reason)
            return
        try:
            if job.writer is None:
                job.writer = await self._io(job.reopen)
            if self.state in ("paused", "pausing"):  # stopped while paused: the next daemon takes it over paused
                await self._io(mark_paused, job.path, pause_said(job) or USER_PAUSE, pause_kind(job))
            else:
                await self._io(job.writer.set_state, "running", reason)
        except (OSError, CaptureError) as exc:
            self.last_error = f"scan {job.name!r}: could not record '{state}': {describe(exc, 'recording it')}"

    def _finish(self, job: ScanJob, state: str, reason: str | None = None) -> None:
        close_writer(job)
        self.job, self._task = None, None
        self._set_state("idle")
        self._record_end(job.name, state, reason)  # (a `wait` woken above runs once this call has returned)
        log.info("scan %s %s: %d frames", job.name, state, job.frames)

    def _record_end(self, name: str, state: str, reason: str | None) -> None:
        """Record how scan `name` ended, with the status as it ended (what `ctl wait --json` prints: read later, the
        status may be the next scan's). The last scan to end comes last, even under a name that ended before (its
        folder deleted by hand, the name taken again)."""
        self.ends.pop(name, None)
        self.ends[name] = ScanEnd(state, reason or None)  # first: the status names it as the last scan
        self.ends[name] = ScanEnd(state, reason or None, self.status(), time.monotonic())
        while len(self.ends) > KEPT_ENDS:  # the oldest first: its folder still says how it ended
            del self.ends[next(iter(self.ends))]

    def _set_state(self, state: str) -> None:
        if state == "scanning" and self.state not in TAKING_FRAMES and self.job is not None:
            self.job.mark_scanning()  # started or resumed: the frame rate is counted from here
        self.state = state
        self._notify()

    def _notify(self) -> None:
        changed, self._changed = self._changed, asyncio.Event()
        changed.set()

    def _progress(self) -> str:
        return _progress_of(self.job) if self.job else "-"

    @staticmethod
    def _fault_at(job: ScanJob) -> str:
        """Where a fault stopped the scan, for its reason: on the retake's way, the pose of the scan's path the arm
        was moving to or at (an operator at the pendant looks for it there), else the scan's next pose."""
        going = f"pose {job.next_pose}/{job.n_poses}"
        if job.way_at is None:
            return f" ({going})"
        i, phase, direction = job.way_at
        if job.owed:
            why = f"to take pose(s) {', '.join(map(str, job.owed))} again"
        else:
            why = f"to pose {job.next_pose - 1}, the last published"
        return (f" (the arm was {phase} pose {i}, on its way {direction} along the scan's path {why}; the scan "
                f"goes on at {going})")

    def _fault_reason(self, exc: BaseException, at: str) -> str:
        """The pause reason for fault `exc` (`at`: where it stopped the scan): what happened and, where its own
        message does not say (`_advice`), what the operator does before `spadscan ctl resume`. A pause for the
        sensor's lost link says to resume once the link is back: it reconnects by itself, the scan does not go on by
        itself (and once the link is back, the reason says so: `_sensor_link_back`)."""
        if isinstance(exc, _SensorLinkLost) or (isinstance(exc, SensorSilent)
                                                and self.sensor.counters().get("link") == "down"):
            return f"{describe(exc)}; {SENSOR_LINK_WAIT}{at}"
        job = self.job
        if isinstance(exc, (OSError, CaptureError)) and job is not None and folder_gone(job.path):
            # Not the disk's fault: its advice (the kernel log, a failing disk) would send the operator astray. (The
            # manifest, which nothing but the operator removes: a folder deleted while a chunk was being written
            # may be left holding that chunk's remains.)
            return (f"{describe(exc)}; the scan's folder {job.path} is gone (moved or deleted while the scan ran): "
                    f"move it back, then `spadscan ctl resume`, or `spadscan ctl abort` ends the scan{at}")
        advice = _advice(exc)
        return f"{describe(exc)}{'; ' + advice if advice else ''}{at}"

    def _sensor_link_back(self, job: ScanJob | None) -> None:
        """A paused scan whose reason waits for the sensor's link (SENSOR_LINK_WAIT): once the sensor reports its
        link up, the reason (and last_error, where it says the same) says that it is back, instead of going on
        telling the operator to wait for it."""
        if job is None or SENSOR_LINK_WAIT not in (job.reason or "") or self.sensor.counters().get("link") != "up":
            return
        was = job.reason
        job.reason = was.replace(SENSOR_LINK_WAIT, SENSOR_LINK_BACK)
        if self.last_error == was:
            self.last_error = job.reason

    def _pause_at(self) -> str:
        """The progress a requested pause stops at: a pose already in flight is finished and published first, so
        the count can be one or two ahead of the published poses (one waiting to be written, one being captured)."""
        job = self.job
        at = job.next_pose if job.in_flight is None else max(job.next_pose, job.in_flight + 1)
        return f"{at}/{job.n_poses}"

    async def _io(self, fn, *args, **kwargs):
        """Run capture I/O on the writer thread (one thread: writes never interleave)."""
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._io_pool, lambda: fn(*args, **kwargs))

    @staticmethod
    async def _io_side(fn, *args):
        """Capture I/O that may run beside the writer thread's (it touches no file the writer does: an adaptive
        scan's schedule.npy), so that it never waits behind a publish."""
        return await asyncio.to_thread(fn, *args)


def scan_eta_s(job: ScanJob) -> float | None:
    """Seconds left of a scan taking frames, at its measured pace: the poses still to take (those planned past the
    last published one, and any owed again) at the pose rate of the last 10 s (`ScanJob.rate_hz` frames per second,
    `frames_per_pose` a pose). None before a rate is measured (the scan has just started or resumed). The caller
    leaves it out (null) while the scan is paused or pausing: it is not going to end at any pace then."""
    rate = job.rate_hz()
    if rate <= 0:
        return None
    left = max(0, job.n_poses - job.next_pose) + len(job.owed)
    return round(left * job.scan.frames_per_pose / rate, 1)


def _progress_of(job: ScanJob) -> str:
    """A scan's pose i/n, as `status` gives it (`progress`): its next pose of its poses."""
    return f"{job.next_pose}/{job.n_poses}"


def _owed(job: ScanJob) -> str:
    """The poses the capture lacks before its first unpublished one (to be taken again), said; '' when none."""
    return ", ".join(map(str, job.owed))


def _advice(exc: BaseException) -> str:
    """What the operator does about fault `exc` before `spadscan ctl resume`, where its message does not say it
    already (an arm's safety stop names what clears it; a move's timeout, the runner's own faults word theirs); ''
    when there is nothing to add."""
    if isinstance(exc, OSError):
        return write_advice(exc)
    if isinstance(exc, SensorSilent):  # with its link up: the sensor itself, or its bridge, stopped measuring
        return ("check the sensor, its cable, its power and its bridge (or raise [sensor] frame_timeout_s), then "
                "`spadscan ctl resume`")
    if isinstance(exc, LinkLost):  # the arm's (the sensor's is `_SensorLinkLost`, told in `_fault_reason`)
        return f"{ARM_LINK_CHECK}, then `spadscan ctl resume` (it reconnects)"
    return ""


def _rounded(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


