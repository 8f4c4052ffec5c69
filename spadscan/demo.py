"""The whole loop on simulated devices: daemon -> capture folder -> worker -> mesh, each half in its own process.

By default the worker reconstructs live (`spadscan worker --live`): it starts on the scan's first chunk, its state
(recon/live/status.json) is shown while the scan runs, and once the scan is complete the final reconstruction
continues from the live fit. `live=False` runs today's offline job once the scan is complete.

The demo drives the same commands a lab operator uses (`spadscan daemon`, the control socket, `spadscan worker`), so
it proves the system end to end. Every process it starts it stops again, also on Ctrl-C or an error. A scan an
earlier run into the same folder left unfinished (stopped during its scan) is aborted through the daemon, its poses
kept, before the new scan starts. A scan an earlier run left complete but not reconstructed (stopped during its
reconstruction) is reconstructed first, said in one line and shown on a bar of its own, so that this run's
reconstruction, its times and its summary are its own scan's alone.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from spadscan.daemon.client import ControlError, call
from spadscan.parent_watch import child_env
from spadscan.daemon.root_lock import LOCK_NAME
from spadscan.protocol.capture_format import MANIFEST, enclosing_capture
from spadscan.protocol.child_command import module_command
from spadscan.protocol.errors import SpadscanError

# Unix socket paths longer than this fail to bind (sun_path is 108 bytes on Linux).
MAX_SOCKET_PATH = 100
MIN_VIEWS = 4
"""Fewest views the demo scans: fewer leave the reconstruction nothing to fit (the daemon itself accepts 1)."""
ARMS = ("sim", "ur-sim")
SENSORS = ("lcspc-sim", "tmf8820")
LOG_TAIL_BYTES = 64 * 1024  # how much of a child's log is searched for the line that says why it failed


class DemoError(SpadscanError):
    """A stage of the demo failed; the message says which and where its log is."""


@dataclass
class DemoOptions:
    """What `spadscan demo` runs."""

    out: Path
    """Folder for the rig config, captures, logs and the summary."""
    scene: str = "demo"
    """Built-in scene the simulated sensor renders (spadscan.protocol.scenes)."""
    views: int = 128
    """Sensor poses in the scan. 128: on the goblet, 64 views leave the fit short of data and its result depends on
    the seed (1.8-2.3 mm against 0.9-1.1 mm with 128; benchmarks/RESULTS.md); the scan itself takes seconds."""
    budget_s: float = 120.0
    """Wall-clock budget of the whole reconstruction job, from its start to its report (s); with `live`, of the final
    run that continues from the live fit once the scan is complete."""
    live: bool = True
    """Reconstruct while the scan runs (`spadscan worker --live`) and show the live state; False: reconstruct once
    the scan is complete (`spadscan worker --once`)."""
    arm: str = "sim"
    """'sim' (simulated arm) or 'ur-sim' (the real ur_rtde client against a simulated UR controller on loopback)."""
    sensor: str = "lcspc-sim"
    """Sensor preset the simulated sensor uses: 'lcspc-sim' or 'tmf8820'."""
    frames_per_pose: int = 1
    """Frames stored per pose."""
    stage_timeout_s: float = 600.0
    """Longest any one stage may take before the demo gives up (s)."""
    dashboard: bool = False
    """Serve the lab dashboard (`spadscan dashboard`) on the demo's captures while the demo runs."""
    dashboard_port: int = 8765
    """Port the dashboard listens on (127.0.0.1); a free one is taken when it is busy."""


@dataclass
class Processes:
    """The child processes of a demo run, stopped in reverse order."""

    procs: list[tuple[str, subprocess.Popen]] = field(default_factory=list)

    def start(self, name: str, argv: list[str], log: Path) -> subprocess.Popen:
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "ab") as f:
            # A new session: Ctrl-C in the terminal reaches only the demo, which then stops its children in order.
            # ... and each child stops by itself if the demo is killed before it can stop them (parent_watch.py).
            proc = subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True, env=child_env())
        self.procs.append((name, proc))
        return proc

    def stop_all(self, grace_s: float = 10.0) -> None:
        for name, proc in reversed(self.procs):
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for name, proc in reversed(self.procs):
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self.procs.clear()


def _spadscan(*args: str) -> list[str]:
    return module_command("spadscan.cli", *args)


def _free_loopback_host() -> str:
    """A 127.0.0.N address where the fixed UR ports (30004, 29999, 30003) are free."""
    for n in range(20, 250):
        host = f"127.0.0.{n}"
        try:
            for port in (30004, 29999, 30003):
                with socket.socket() as s:
                    s.bind((host, port))
            return host
        except OSError:
            continue
    raise DemoError("no loopback address has the UR ports 30004/29999/30003 free")


def _socket_path(out: Path) -> tuple[Path, Path | None]:
    """The control socket path, in a short temporary folder when `out` is too deep for a Unix socket."""
    path = out.resolve() / "daemon.sock"
    if len(str(path)) <= MAX_SOCKET_PATH:
        return path, None
    tmp = Path(tempfile.mkdtemp(prefix="spadscan-"))
    return tmp / "daemon.sock", tmp


RIG_CONFIG = "rig.toml"
"""The rig config the demo writes into OUT and starts its daemon with."""
RIG_HEADER = "# Written by `spadscan demo`"
"""The first line of every rig config the demo writes starts so: the mark of one it may write anew."""

DEMO_FRAME_TIME_S = 0.1
"""Seconds a simulated frame takes (a real TMF8820's histograms take longer still to read out over I2C): the default
scan then lasts about half a minute, long enough for the live job to start and show its fit while the scan goes on
(with instant frames it ended before the worker's first look)."""


def write_rig_config(opts: DemoOptions, captures: Path, sock: Path, ur_host: str | None) -> Path:
    """The demo's rig: simulated arm (or ur-sim), simulated sensor rendering a built-in scene."""
    # The ur backend needs a workspace box (metres, base frame): the scan's hemisphere of radius 0.5 m around the
    # origin with a margin.
    arm = (f'backend = "ur"\nhost = "{ur_host}"\nspeed = 0.5\nacceleration = 2.0\n'
           'workspace_min = [-0.7, -0.7, -0.1]\nworkspace_max = [0.7, 0.7, 0.7]\n' if ur_host else
           'backend = "sim"\nspeed = 0.5\nacceleration = 2.0\ntime_scale = 0.05\n')
    # Absolute: the daemon resolves a relative path against the config's own folder, not the demo's working folder.
    text = f"""{RIG_HEADER}: simulated devices only.
# Each demo run into this folder writes this file anew: copy it elsewhere to change it.
captures = "{captures.resolve()}"
socket = "{sock}"

[arm]
{arm}
[sensor]
backend = "sim"
preset = "{opts.sensor}"
mesh = "builtin:{opts.scene}"
frame_time_s = {DEMO_FRAME_TIME_S}

[scan]
views = {opts.views}
schedule = "fibonacci"
radius_m = 0.5
target = [0.0, 0.0, 0.0]
min_elevation_deg = 0.0
max_elevation_deg = 86.0
frames_per_pose = {opts.frames_per_pose}
settle_s = 0.0
"""
    path = opts.out / RIG_CONFIG
    refused = foreign_rig_config(opts.out)  # checked up front too (check_options); here as well, where it is written
    if refused:
        raise DemoError(refused)
    path.write_text(text)
    return path


def foreign_rig_config(out: Path) -> str | None:
    """Why the demo must not write its rig config into `out` (one line), or None: `out` holds a RIG_CONFIG that no
    demo run into `out` wrote, such as the user's own rig with their hand-eye and ports. The demo's own begins with
    RIG_HEADER and names `out`'s captures folder as its `captures` (every version has written both); a copy of it
    edited elsewhere keeps the header but names the folder it was copied from. Only the demo's own is replaced, so
    that a run into the folder of an earlier one goes on as before."""
    path = Path(out) / RIG_CONFIG
    if not os.path.lexists(path):
        return None
    try:
        text = path.read_bytes()
    except OSError as exc:  # a folder, a link to nothing, a file this user may not read: not known to be the demo's
        text, why = b"", f" ({exc.strerror or exc})"
    else:
        why = ""
    if text.startswith(RIG_HEADER.encode()) and _captures_named(text) == str((Path(out) / "captures").resolve()):
        return None
    return (f"{path} is not a rig config the demo wrote{why}: the demo would replace it with its own; give the demo "
            f"a new folder (--out DIR), or move {path} away")


def _captures_named(text: bytes) -> str | None:
    """The `captures` a rig config's TOML names, or None where it names none or cannot be read."""
    try:
        captures = tomllib.loads(text.decode()).get("captures")
    except (UnicodeDecodeError, tomllib.TOMLDecodeError):
        return None
    return captures if isinstance(captures, str) else None


def check_options(opts: DemoOptions) -> None:
    """Refuse, in one line each, the options the daemon or the worker would refuse, before anything starts (they
    would otherwise fail only after the daemon started or the whole scan ran). The limits are theirs, read from
    the daemon's config keys where they are declared."""
    from spadscan.daemon.config import ScanConfig, SensorConfig
    from spadscan.daemon.config_keys import key_spec
    from spadscan.protocol.scenes import BUILTIN_SCENES
    from spadscan.worker.jobs import DEFAULT_QUEUE, run_limits_problem

    if opts.scene not in BUILTIN_SCENES:
        raise DemoError(f"unknown scene {opts.scene!r} (built-in: {', '.join(BUILTIN_SCENES)})")
    if opts.arm not in ARMS:
        raise DemoError(f"--arm {opts.arm!r} must be one of {', '.join(ARMS)}")
    presets = key_spec(SensorConfig, "preset").choices
    if opts.sensor not in presets:
        raise DemoError(f"--sensor {opts.sensor!r} must be one of {', '.join(presets)}")
    most = int(key_spec(ScanConfig, "views").hi)
    if isinstance(opts.views, bool) or not isinstance(opts.views, int) or not MIN_VIEWS <= opts.views <= most:
        raise DemoError(f"--views {opts.views} must be an integer in [{MIN_VIEWS}, {most}]")
    # the worker's rule (`spadscan worker --budget-s`); the demo always names a budget
    problem = "a time budget is needed" if opts.budget_s is None else run_limits_problem(opts.budget_s, None, 0)
    if problem:
        raise DemoError(f"--budget-s: {problem}")
    if opts.out.exists() and not opts.out.is_dir():
        raise DemoError(f"{opts.out}: exists and is not a folder")
    capture = enclosing_capture(opts.out)
    if capture is not None:
        where = "is a capture" if capture == opts.out.resolve() else f"lies inside the capture {capture}"
        raise DemoError(f"--out {opts.out} {where} (it holds {MANIFEST}): the demo's captures, logs and rig config "
                        f"would be mixed into its measurements; give the demo a new folder (--out DIR)")
    held = [name for name in (LOCK_NAME, DEFAULT_QUEUE) if os.path.lexists(opts.out / name)]
    if held:
        raise DemoError(f"--out {opts.out} is a captures root (it holds {' and '.join(held)}): the demo's captures, "
                        f"logs and rig config would be mixed into its scans; give the demo a new folder (--out DIR)")
    foreign = foreign_rig_config(opts.out)
    if foreign:
        raise DemoError(foreign)
    port = opts.dashboard_port
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise DemoError(f"--dashboard-port {port} must be an integer in [0, 65535]")


def check_rig_config(config: Path) -> None:
    """Read the rig config as the daemon will at start-up, so that anything it would refuse fails here, in one
    line, before any process starts."""
    from spadscan.daemon.config import load_config

    load_config(config)


def last_log_line(log: Path) -> str | None:
    """The line of a child's log that says why it failed: its last `spadscan: error:` line (without the prefix),
    else its last line that is neither blank nor a progress bar; None for an empty or unreadable log."""
    try:
        with open(log, "rb") as f:
            f.seek(max(0, f.seek(0, os.SEEK_END) - LOG_TAIL_BYTES))
            text = f.read().decode("utf-8", "replace")
    except OSError:
        return None
    lines = [line.strip() for line in text.replace("\r", "\n").split("\n")]
    lines = [line for line in lines if line and not _is_progress_bar(line)]
    errors = [line for line in lines if line.startswith("spadscan: error:")]
    if errors:
        return errors[-1][len("spadscan: error:"):].strip()
    return lines[-1] if lines else None


def _is_progress_bar(line: str) -> bool:
    """tqdm's lines ("scan:  40%|####      | 4/10 [00:01<00:02, 3.1pose/s]") say nothing about a failure."""
    return "%|" in line and line.rstrip().endswith("]")


def _failed(what: str, log: Path) -> DemoError:
    """`what` failed: the error names the log and, when the log says why, repeats its last meaningful line."""
    why = last_log_line(log)
    return DemoError(f"{what}: {why} (log: {log})" if why else f"{what} (log: {log})")


def _wait_for_daemon(sock: Path, proc: subprocess.Popen, log: Path, timeout_s: float) -> None:
    """Wait until the daemon `proc` answers on `sock`. Only its own answer counts: another daemon may still serve the
    socket (one of a demo run killed a moment ago, not stopped yet, or of a demo still running into the same folder),
    and the demo would otherwise drive that daemon's scans (abort them, as an earlier run's)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise _failed(f"the daemon exited with code {proc.returncode} at start-up", log)
        try:
            status = call(sock, "status", timeout_s=2.0)
        except ControlError:
            status = {}
        if (status.get("daemon") or {}).get("pid") == proc.pid:
            return
        time.sleep(0.2)
    raise _failed(f"the daemon did not open its control socket within {timeout_s:.0f} s", log)


EARLIER_RUN_ABORTED = "an earlier demo run was interrupted"
"""The reason recorded in the capture of a scan the demo aborts because an earlier run of it was interrupted."""


STARTED = "demo-scans.txt"
"""OUT's record of the scans demo runs started there, one name a line, written before each scan begins: only those
does a later run abort (`_abort_earlier_scans`)."""


def started_scans(out: Path) -> set[str]:
    """The names of the scans demo runs into `out` started (`STARTED`; none when it is missing)."""
    try:
        return set((Path(out) / STARTED).read_text().split())
    except FileNotFoundError:
        return set()


def record_started(out: Path, name: str) -> None:
    """Add scan `name` to `out`'s record of the demo's scans, before the scan starts (a run killed during it leaves
    the name behind for the next run)."""
    with open(Path(out) / STARTED, "a") as f:
        f.write(name + "\n")


def _abort_earlier_scans(sock: Path, out: Path, captures: Path) -> list[str]:
    """Abort, through the daemon, the scans an earlier demo run into the same folder left unfinished (Ctrl-C or
    kill -9 during its scan), and return one line for each. The demo's daemon takes such a scan over, paused, at
    start-up, and would refuse the new scan until it is resumed or aborted; but no daemon is left to do either once
    the demo stops its own. One it cannot take over (a chunk a power cut tore) would stay unfinished for good. The
    abort keeps every pose the scan published: its capture stays, marked aborted, and the worker skips it. Only the
    demo's own scans (`started_scans`) are aborted: an interrupted scan of anyone else's in its captures folder is a
    DemoError that names it, the scan left as it was."""
    status = call(sock, "status", timeout_s=10.0)
    held = status.get("scan")  # a daemon just started holds no scan but one it took over
    stuck = (status.get("cannot_take_over") or {}).get("scan")
    own = started_scans(out)
    for name in (held, stuck):
        if name is not None and name not in own:
            raise DemoError(f"{captures} holds scan {name!r}, left unfinished, which no demo run started: resume or "
                            f"abort it with the rig that recorded it (`spadscan ctl resume {name}` or `spadscan ctl "
                            f"abort {name}`), or give the demo another --out")
    said = []
    if held is not None:
        _abort(sock, held)
        said.append(f"{EARLIER_RUN_ABORTED}: its scan {held} ({status.get('pose')} of {status.get('poses')} poses) "
                    f"is kept aborted; starting a new one")
    if stuck is not None:
        _abort(sock, stuck)
        said.append(f"{EARLIER_RUN_ABORTED}: its scan {stuck}, which the daemon could not take over (daemon.log "
                    f"says why), is kept aborted; starting a new one")
    return said


def _abort(sock: Path, name: str) -> None:
    """Abort scan `name` through the daemon (`spadscan ctl abort NAME`); a DemoError when the daemon refuses or its
    disk could not record the abort (the new scan would not be written either)."""
    try:
        reply = call(sock, "abort", name=name, reason=EARLIER_RUN_ABORTED)
    except ControlError as exc:
        raise DemoError(f"could not abort scan {name}, which an earlier demo run left unfinished: {exc}") from None
    if reply.get("abort_recorded") is False:
        raise DemoError(f"could not record the abort of scan {name}, which an earlier demo run left unfinished: "
                        f"{reply.get('last_error')}")


def _scan(sock: Path, name: str, opts: DemoOptions, progress, watch=None) -> dict:
    """Scan and wait for its end; `watch()` runs at every poll (the live state's display)."""
    call(sock, "scan", name=name, options={"views": opts.views})
    deadline = time.monotonic() + opts.stage_timeout_s
    last = 0
    while time.monotonic() < deadline:
        if watch is not None:
            watch()
        st = call(sock, "status", timeout_s=10.0)
        done = int(st.get("pose") or 0) if st.get("scan") == name else last
        progress.update(max(0, done - last))
        last = max(last, done)
        finished = (st.get("last_scan") or {})
        if finished.get("name") == name and st.get("scan") in (None, name) and st.get("state") == "idle":
            if finished.get("state") != "complete":
                raise DemoError(f"scan {name} ended {finished.get('state')}: {st.get('last_error')}")
            progress.update(max(0, opts.views - last))
            return st
        if st.get("state") == "paused":
            raise DemoError(f"scan {name} paused: {st.get('reason') or st.get('last_error')}")
        time.sleep(0.25)
    raise DemoError(f"scan {name} did not finish within {opts.stage_timeout_s:.0f} s")


@dataclass(frozen=True)
class JobRun:
    """One run of a job's process, as the queue shows it: each claim of a job runs a process of its own, with a log
    and a progress bar that start from nothing (a crashed job's retry is a new claim)."""

    job_id: str
    claim: str | None
    """The claim's token; None where it is not known (the run is then taken for the one last shown)."""
    attempt: int | None
    """Which attempt of the job the claim is (1-based), as its attempt record says; None where that cannot be read."""
    progress: object = None
    """Its bar (worker.job_progress.JobProgress), or None while its log shows none yet."""
    last_error: str | None = None
    """Why the job's last attempt before this one ended (for a claim past the first attempt), or None."""


def running_runs(captures: Path) -> dict[str, JobRun]:
    """Each job the worker is running on `captures` by id: its claim and its progress, read from its log in the
    queue and measured against its budget as `spadscan worker --status` measures it."""
    from spadscan.worker.job_progress import running_progress
    from spadscan.worker.queue import QUEUE_DIRNAME, SEP, Queue

    if not (captures / QUEUE_DIRNAME).is_dir():
        return {}
    queue = Queue.for_root(captures, create=False)
    paths = queue.job_paths()
    runs = {}
    for job_id, progress in sorted(running_progress(queue, captures).items()):
        state, path = paths.get(job_id, (None, None))
        token = path.stem.rpartition(SEP)[2] if state == "running" else None  # (None: its claim ended meanwhile)
        attempt = _attempt_of(queue.record(job_id, token) or {}) if token else None
        last_error = queue.last_error(job_id) if attempt is not None and attempt > 1 else None
        runs[job_id] = JobRun(job_id, token, attempt, progress, last_error)
    return runs


def running_job_run(captures: Path) -> JobRun | None:
    """The run of a job the worker is running on `captures` (the demo's worker runs one at a time), or None."""
    return next(iter(running_runs(captures).values()), None)


def running_job_progress(captures: Path):
    """The progress (worker.job_progress.JobProgress) of a job the worker is running on `captures`, read from
    its log in the queue; None while none runs or its log shows no progress yet."""
    run = running_job_run(captures)
    return None if run is None else run.progress


def finished_job_progress(scan_dir: Path):
    """The last progress (worker.job_progress.JobProgress) in the log of the scan's newest published result, or
    None."""
    from spadscan.worker.job_progress import read_progress

    try:
        report = _find_report(scan_dir)
    except DemoError:
        return None
    return read_progress(report.parent / "job.log")


def finished_job_run(captures: Path, scan: str) -> JobRun | None:
    """The run that published scan `scan`'s result, with the last progress in its log (`finished_job_progress`),
    or None when there is no result. Its claim is the one the job's 'done' record names (or the dead claim whose
    finished result that record's claim adopted); None where the records do not say."""
    from spadscan.worker.queue import Queue

    progress = finished_job_progress(captures / scan)
    if progress is None:
        return None
    job = _scan_job(captures, scan)
    if job is None or job[1] != "done":
        return JobRun(scan, None, None, progress)
    records = Queue.for_root(captures, create=False).records(job[0])
    done = [r for r in records if r.get("outcome") == "done"]
    token = (done[-1].get("adopted") or done[-1].get("token")) if done else None
    ran = next((r for r in records if token is not None and r.get("token") == token), {})
    return JobRun(job[0], token if isinstance(token, str) else None, _attempt_of(ran), progress)


def _attempt_of(record: dict) -> int | None:
    """The attempt number an attempt record gives its claim (1-based), or None where it gives none."""
    attempt = record.get("attempt")
    return attempt if isinstance(attempt, int) and not isinstance(attempt, bool) and attempt >= 1 else None


def _reconstruct(opts: DemoOptions, captures: Path, scan: str, procs: Processes, logs: Path, progress=None) -> None:
    """Run a worker over the captures until it has reconstructed them; `progress` receives the running job's run
    (`running_job_run`, or None) about twice a second. Scan `scan`'s job must be done; another job may fail (the
    worker then exits 1): an earlier live run's job of a scan the demo aborted ends failed, with the scan's reason."""
    tick = None if progress is None else (lambda: progress(running_job_run(captures)))
    code = _run_worker_once(opts, captures, procs, logs, tick, limit_s=opts.stage_timeout_s + opts.budget_s)
    if code != 0 and scan_job_state(captures, scan) != "done":
        raise _failed(f"the worker exited with code {code}", logs / "worker.log")


def _run_worker_once(opts: DemoOptions, captures: Path, procs: Processes, logs: Path, tick, limit_s: float) -> int:
    """Run `spadscan worker --once` over the captures and return its exit status; `tick()` (when given) runs about
    twice a second while it works."""
    log = logs / "worker.log"
    worker = procs.start("worker", _spadscan("worker", "--root", str(captures), "--once", "--processes", "1",
                                             "--budget-s", f"{opts.budget_s:g}", "--poll-s", "0.5"), log)
    deadline = time.monotonic() + limit_s
    while True:
        try:
            return worker.wait(timeout=0.5)
        except subprocess.TimeoutExpired:
            if time.monotonic() > deadline:
                raise _failed(f"the worker did not finish within {limit_s:.0f} s", log) from None
            if tick is not None:
                tick()


def unreconstructed_scans(captures: Path) -> list[str]:
    """The scans in `captures` an earlier run left complete but not reconstructed, oldest name first: their job is
    queued or running (the run was stopped during its reconstruction), or none is queued yet (stopped between its
    scan's end and the worker's first look) and no result is in place. A `spadscan worker --once` on the captures
    runs their jobs before a new scan's (the queue runs the oldest first)."""
    from spadscan.worker.watcher import scan_folders, scan_state

    found = []
    for folder in scan_folders(captures):
        try:
            complete = scan_state(folder) == "complete"
        except SpadscanError:
            complete = False
        if complete and scan_job_state(captures, folder.name) in (None, "queued", "running") \
                and _report_of(folder) is None:
            found.append(folder.name)
    return found


def _report_of(scan_dir: Path) -> Path | None:
    """The scan's newest report.json (`_find_report`), or None where it has none."""
    try:
        return _find_report(scan_dir)
    except DemoError:
        return None


EARLIER_RUN_UNRECONSTRUCTED = "left complete but not reconstructed"
"""What the demo says of the scans it reconstructs first (`unreconstructed_scans`): not "by an earlier run", since
a complete scan copied into the captures is one of them too."""


class EarlierBars:
    """A bar of its own for each earlier scan's job the worker runs, apart from this run's reconstruction bar (a
    job's next attempt starts its bar over: `ReconProgress.follow`)."""

    def __init__(self, captures: Path, progress_factory, total_s: float, say=None):
        self.captures, self.factory, self.total_s, self.say = captures, progress_factory, total_s, say
        self.job, self.bar, self.show = None, None, None

    def __call__(self) -> None:
        from spadscan.worker.queue import Queue

        for job_id, run in list(running_runs(self.captures).items())[:1]:  # the demo's worker runs one at a time
            if job_id != self.job:
                self.close()
                self.job = job_id
                scan = Queue.for_root(self.captures, create=False).registered_scan(job_id) or job_id
                self.bar = self.factory(self.total_s, f"earlier scan {scan} (training s)", "s")
                self.show = ReconProgress(self.bar, f"earlier scan {scan}: mesh, metrics, pictures, report",
                                          self.say)
            self.show.follow(run)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        self.job, self.bar, self.show = None, None, None


def _reconstruct_earlier(opts: DemoOptions, captures: Path, scans: list[str], procs: Processes, logs: Path,
                         progress_factory, say) -> list[dict]:
    """Reconstruct the scans an earlier run left unreconstructed (`unreconstructed_scans`) before this run's scan
    starts, with a line before and one for each after, and return what became of each (scan, state, report). Left
    in the queue, `spadscan worker --once` would run them first inside this run's reconstruction, its bar and its
    time. A Ctrl-C meanwhile leaves them for the next run or a worker (the worker gives a running job back; a scan
    not queued yet stays so)."""
    many = len(scans) > 1
    them = "them" if many else "it"
    say(f"scan{'s' if many else ''} {', '.join(scans)} {EARLIER_RUN_UNRECONSTRUCTED}: reconstructing {them} first, "
        f"on {'bars' if many else 'a bar'} of {'their' if many else 'its'} own and outside this run's times (Ctrl-C "
        f"leaves {them} for `spadscan worker --root {captures} --once`)")
    bars = EarlierBars(captures, progress_factory, opts.budget_s, say)
    limit_s = sum(opts.stage_timeout_s + _queued_budget_s(captures, scan, opts.budget_s) for scan in scans)
    try:
        _run_worker_once(opts, captures, procs, logs, bars, limit_s=limit_s)
    finally:
        bars.close()
    outcomes = [_earlier_outcome(captures, scan) for scan in scans]
    for outcome in outcomes:
        say(_earlier_line(outcome, captures))
    return outcomes


def _earlier_outcome(captures: Path, scan: str) -> dict:
    """What became of earlier scan `scan`'s reconstruction: its job's state, the report or the reason."""
    from spadscan.worker.queue import Queue

    job = _scan_job(captures, scan)
    state = job[1] if job else None
    report = _report_of(captures / scan) if state == "done" else None
    outcome = {"scan": scan, "state": state, "report": None if report is None else str(report.parent / "report.html"),
               "error": None}
    if report is None and job is not None:
        outcome["error"] = Queue.for_root(captures, create=False).last_error(job[0])
    return outcome


def _queued_budget_s(captures: Path, scan: str, budget_s: float) -> float:
    """The budget scan `scan`'s job runs under: the one it was queued with (an earlier run's --budget-s need not be
    this one's); `budget_s` (this run's) for a scan not queued yet (this run's worker queues it so) and for a job
    queued without one (it runs under its preset's default: looking that up would import torch into the demo, and
    the stage's own time limit covers the fast preset's 120 s)."""
    from spadscan.worker.jobs import Job

    job = _scan_job(captures, scan)
    try:
        queued = Job.from_dict(json.loads(job[2].read_text())).budget_s if job else None
    except (OSError, ValueError, SpadscanError):
        queued = None  # moved on meanwhile, or damaged (its claim fails it)
    return float(queued) if queued is not None and queued > 0 else budget_s


def _earlier_line(outcome: dict, captures: Path) -> str:
    scan = outcome["scan"]
    if outcome["report"] is not None:
        return f"earlier scan {scan} reconstructed: {outcome['report']}"
    why = f": {outcome['error']}" if outcome["error"] else ""
    return (f"earlier scan {scan} not reconstructed ({outcome['state'] or 'not queued'}{why}); "
            f"`spadscan worker --root {captures} --status` says more")


def _start_live_worker(opts: DemoOptions, captures: Path, procs: Processes, logs: Path) -> subprocess.Popen:
    """A worker that reconstructs scans while they are recorded; the final run gets the demo's budget."""
    return procs.start("worker", _spadscan("worker", "--root", str(captures), "--live", "--processes", "1",
                                           "--budget-s", f"{opts.budget_s:g}", "--poll-s", "0.5"),
                       logs / "worker.log")


class LiveWatch:
    """Shows a live reconstruction's state (recon/live/status.json) as the demo runs: one line through `say` each
    time its state changes, and its summary on the bar in front (`bar`, set by the demo stage by stage)."""

    def __init__(self, capture: Path, say):
        self.capture, self.say = capture, say
        self.bar = None
        self.state = None
        self.status = None

    def __call__(self):
        """The current status (LiveStatus), or None while there is none (or it cannot be read)."""
        from spadscan.protocol.live_status import read_status, status_path

        try:
            status = read_status(status_path(self.capture))
        except SpadscanError:
            return None
        self.status = status
        if status.state != self.state:
            self.say(status.summary())
            self.state = status.state
        if self.bar is not None and hasattr(self.bar, "set_postfix_str"):
            # the figures as the summary words them (a stopped attempt's never shown as the job's now)
            self.bar.set_postfix_str("live: " + ", ".join(status.figures()))
        return status


def scan_job_state(captures: Path, scan: str) -> str | None:
    """The queue's state of scan `scan`'s job (a scan has one job; 'queued', 'running', 'done' or 'failed'), or
    None while none is queued."""
    job = _scan_job(captures, scan)
    return job[1] if job else None


def _scan_job(captures: Path, scan: str) -> tuple[str, str, Path] | None:
    """(id, state, job file) of scan `scan`'s job, or None while none is queued. The job's own record says whose it
    is: its id need not start with the scan's name (`jobs.job_id_for` hashes long or odd names)."""
    from spadscan.worker.queue import QUEUE_DIRNAME, Queue

    if not (captures / QUEUE_DIRNAME).is_dir():
        return None
    queue = Queue.for_root(captures, create=False)
    for job_id, (state, path) in sorted(queue.job_paths().items()):
        if queue.registered_scan(job_id) == scan:
            return job_id, state, path
    return None


def _finish_live(opts: DemoOptions, captures: Path, scan: str, worker: subprocess.Popen, logs: Path,
                 watch: LiveWatch, progress=None) -> None:
    """Wait until the worker has published the scan's final result (the live status says `done`; the queue says so
    too, also for a scan so quick that its job ran as an ordinary one); `progress` receives the running job's run
    (`running_job_run`, or None) about twice a second."""
    log = logs / "worker.log"
    limit = opts.stage_timeout_s + opts.budget_s
    deadline = time.monotonic() + limit
    while True:
        status = watch()
        job = scan_job_state(captures, scan)
        if (status is not None and status.state == "done") or job == "done":
            watch()  # the result's own line, when the live status has it by now
            return
        if job == "failed":
            raise _failed("the reconstruction failed", log)
        if status is not None and status.state in ("aborted", "stopped"):
            raise _failed(f"the live reconstruction {status.state}: {status.note or 'no reason given'}", log)
        if worker.poll() is not None:
            raise _failed(f"the worker exited with code {worker.returncode}", log)
        if time.monotonic() > deadline:
            raise _failed(f"the live reconstruction did not finish within {limit:.0f} s", log)
        if progress is not None:
            progress(running_job_run(captures))
        time.sleep(0.5)


def _free_port(host: str, port: int) -> int:
    """`port` when it is free on `host`, else one the system has free."""
    for candidate in (port, 0):
        with socket.socket() as s:
            try:
                s.bind((host, candidate))
            except OSError:
                continue
            return s.getsockname()[1]
    raise DemoError(f"no free port on {host} for the dashboard")


def _start_dashboard(opts: DemoOptions, captures: Path, procs: Processes, logs: Path, timeout_s: float = 60.0,
                     sock: Path | None = None) -> str:
    """Serve the dashboard on the captures (a child process, stopped with the others), asking the demo's daemon on
    `sock` for its own state; returns its address once it answers."""
    import urllib.request

    host = "127.0.0.1"
    port = _free_port(host, opts.dashboard_port)
    log = logs / "dashboard.log"
    asked = ("--socket", str(sock)) if sock is not None else ()
    proc = procs.start("dashboard", _spadscan("dashboard", "--root", str(captures), "--host", host,
                                              "--port", str(port), *asked), log)
    url = f"http://{host}:{port}/"
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise _failed(f"the dashboard exited with code {proc.returncode} at start-up", log)
        try:
            with urllib.request.urlopen(url + "api/status", timeout=5):
                return url
        except OSError:
            time.sleep(0.2)
    raise _failed(f"the dashboard did not answer within {timeout_s:.0f} s", log)


class ReconProgress:
    """Shows a job's progress on a bar made by a progress_factory: seconds of the budget done, and the loss, step
    and Chamfer the job's own bar carries. Fed runs (`follow`), it starts the bar over when the worker runs the job
    again (a crashed job's next attempt trains from nothing), names the attempt in the bar's description and says
    why the last one ended in a line of its own (`say`)."""

    def __init__(self, bar, after: str | None = None, say=None):
        self.bar = bar
        self.shown = 0.0
        self.after = after or self.AFTER
        self.say = say
        self.desc = getattr(bar, "desc", "")
        """The bar's own description, before any attempt's name is added to it."""
        self.claim: str | None = None
        """The claim of the run the bar shows (`JobRun.claim`), once one was followed."""
        self.attempt: int | None = None
        self.label = ""
        """What the description says of the attempt (', attempt 2'), after its own words; '' for a first run."""

    AFTER = "reconstruction: mesh, metrics, pictures, report"
    """The bar's description once training is over: the job then extracts the mesh and writes its report."""

    def follow(self, run: JobRun | None) -> None:
        """Show run `run` of the job (None: none runs): a claim other than the one shown is a new run of the job's
        process, shown from its own start; a run whose claim is not known is taken for the one shown."""
        if run is None:
            return
        if run.claim is not None and run.claim != self.claim:
            if self.claim is not None or (run.attempt or 1) > 1:
                self._start_over(run)
            self.claim, self.attempt = run.claim, run.attempt
        self(run.progress)

    def _start_over(self, run: JobRun) -> None:
        """The bar back to nothing, its description naming the new attempt, and a line that says so."""
        if run.attempt is None:
            self.label = ", run again"
        else:  # the same number again: the claim before was given back (a full disk, say), not counted
            self.label = f", attempt {run.attempt}" + (", run again" if run.attempt == self.attempt else "")
        if hasattr(self.bar, "reset"):
            self.bar.reset()  # tqdm: the count and its clock from zero, the total kept until the new bar's comes
        else:
            self.bar.update(-self.shown)
        self.shown = 0.0
        if hasattr(self.bar, "set_postfix_str"):
            self.bar.set_postfix_str("")
        if hasattr(self.bar, "set_description_str"):
            self.bar.set_description_str(self.desc + self.label)
        if self.say is not None:
            why = f" (the last attempt: {run.last_error})" if run.last_error else ""
            self.say(f"reconstruction job {run.job_id}: the worker runs it again{self.label}{why}")

    def __call__(self, progress) -> None:
        """Show reading `progress` (worker.job_progress.JobProgress, or None) of the run shown."""
        if progress is None:
            return
        total = max(progress.total, self.shown)
        if progress.total > 0 and getattr(self.bar, "total", total) != total:
            # The job's own total: its training budget, which the set-up and the end leave less than the demo's.
            # Never below what the bar has counted (a reading of a run other than the one shown, that no claim
            # told apart): tqdm takes a count past its total for "no total", which `{total:.0f}` cannot format.
            self.bar.total = total
            if hasattr(self.bar, "refresh"):
                self.bar.refresh()
        fields = [f"step {progress.fields['step']}"] if "step" in progress.fields else []
        if "loss" in progress.fields:
            fields.append(f"loss {progress.fields['loss']}")
        if progress.chamfer_mm is not None:
            at = "" if progress.chamfer_step is None else f" (step {progress.chamfer_step})"  # a short run's is old
            fields.append(f"checkpoint Chamfer {progress.chamfer_mm:.2f} mm{at}")  # a coarse mesh's: not the result's
        # The fields before the count: a bar written as lines (ProgressLines) says a line with the count, and that
        # line carries this reading's fields, not the last one's.
        if fields and hasattr(self.bar, "set_postfix_str"):
            self.bar.set_postfix_str(", ".join(fields))
        done = min(progress.done, progress.total)
        self.bar.update(max(0.0, done - self.shown))
        self.shown = max(self.shown, done)
        # After the count: the end's stage once the training is over (its count at its total, or its bar's `ended`
        # field: a run that converged early), said at once as lines (ProgressLines), not only once the job has
        # finished (its mesh, metrics, pictures and report take a while).
        if progress.training_done and hasattr(self.bar, "set_description_str"):
            self.bar.set_description_str(self.after + self.label)


def _find_report(scan_dir: Path) -> Path:
    # Earlier results that a worker moved aside (`<job>.replaced-<time>`) are not this run's.
    reports = sorted((p for p in (scan_dir / "recon").glob("*/report.json") if ".replaced-" not in p.parent.name),
                     key=lambda p: p.stat().st_mtime)
    if not reports:
        raise DemoError(f"the worker wrote no report under {scan_dir / 'recon'}")
    return reports[-1]


def make_out(opts: DemoOptions) -> tuple[Path, Path]:
    """Make the demo's folders (OUT, its logs and captures) and return (logs, captures): the command makes them
    before it names the logs folder, so that an OUT it may not write is refused before any line promises it. An OUT
    that cannot be made, or that is there but cannot be written into, is refused in one line that names --out, as the
    other commands refuse theirs (not an OS error about its logs folder)."""
    from spadscan.protocol.folders import check_folder_option

    check_folder_option(opts.out, "--out")
    logs, captures = opts.out / "logs", opts.out / "captures"
    for folder in (opts.out, logs, captures):
        folder.mkdir(parents=True, exist_ok=True)
    return logs, captures


def run_demo(opts: DemoOptions, progress_factory, say=None) -> dict:
    """Run the loop and return the summary (also written to OUT/summary.json).

    progress_factory(total, desc, unit) -> an object with update(n) and close() (and set_postfix_str(text), where it
    has one), e.g. a tqdm bar: one for the scan's poses, one for the reconstruction's seconds (and, before the scan,
    one for each earlier run's scan left unreconstructed). `say(line)` receives what the user should know while the
    demo runs (the dashboard's address, the earlier scans reconstructed first). The summary's `seconds` are this
    run's own; `earlier_s` is the time its start took to reconstruct earlier scans, each in `earlier` (scan, state,
    report, error).
    """
    say = say or (lambda line: None)
    check_options(opts)
    out = opts.out
    logs, captures = make_out(opts)
    name = f"{opts.scene}-{time.strftime('%Y%m%d-%H%M%S')}"
    sock, sock_tmp = _socket_path(out)
    procs = Processes()
    dashboard = None
    stages: dict[str, float] = {}
    t0 = time.monotonic()
    try:
        ur_host = _free_loopback_host() if opts.arm == "ur-sim" else None
        config = write_rig_config(opts, captures, sock, ur_host)
        check_rig_config(config)
        if ur_host is not None:
            procs.start("ur-sim", module_command("spadscan.daemon.ursim", "--host", ur_host),
                        logs / "ursim.log")
        daemon = procs.start("daemon", _spadscan("daemon", "--config", str(config)), logs / "daemon.log")
        _wait_for_daemon(sock, daemon, logs / "daemon.log", timeout_s=60.0)
        for line in _abort_earlier_scans(sock, out, captures):  # before the worker starts: it then skips that scan
            say(line)
        if opts.dashboard:
            dashboard = _start_dashboard(opts, captures, procs, logs, sock=sock)
            say(f"dashboard: {dashboard} (open it in a browser; it stops with the demo)")
        t = time.monotonic()
        # Before this run's worker starts: it would run them first, inside this run's reconstruction and its time.
        scans = unreconstructed_scans(captures)
        earlier = _reconstruct_earlier(opts, captures, scans, procs, logs, progress_factory, say) if scans else []
        stages["earlier_s"] = time.monotonic() - t
        watch = LiveWatch(captures / name, say) if opts.live else None
        worker = _start_live_worker(opts, captures, procs, logs) if opts.live else None
        stages["start_s"] = time.monotonic() - t0 - stages["earlier_s"]

        t = time.monotonic()
        bar = progress_factory(opts.views, "scan (poses)", "pose")
        try:
            if watch is not None:
                watch.bar = bar
            record_started(out, name)
            _scan(sock, name, opts, bar, watch)
        finally:
            bar.close()
        stages["scan_s"] = time.monotonic() - t
        call(sock, "shutdown")

        t = time.monotonic()
        desc = "final reconstruction (training s)" if opts.live else "reconstruction (training s)"
        bar = progress_factory(opts.budget_s, desc, "s")
        try:
            show = ReconProgress(bar, say=say)
            if watch is not None:
                watch.bar = None  # the final run's own progress goes on this bar
                _finish_live(opts, captures, name, worker, logs, watch, show.follow)
            else:
                _reconstruct(opts, captures, name, procs, logs, show.follow)
            # The job's last progress, from its published log: a short job may end between two looks at its live one.
            show.follow(finished_job_run(captures, name))
        finally:
            bar.close()
        stages["reconstruct_s"] = time.monotonic() - t
    finally:
        procs.stop_all()
        if sock_tmp is not None:
            shutil.rmtree(sock_tmp, ignore_errors=True)
    stages["total_s"] = time.monotonic() - t0 - stages["earlier_s"]  # this run's own: the earlier scans' apart
    report_path = _find_report(captures / name)
    report = json.loads(report_path.read_text())
    summary = {
        "scene": opts.scene, "views": opts.views, "arm": opts.arm, "sensor": opts.sensor,
        "capture": str(captures / name),
        "mesh": str(report_path.parent / "mesh.ply"),
        "report": str(report_path),
        "report_html": str(report_path.parent / "report.html"),
        "pictures": sorted(str(p) for p in report_path.parent.glob("*.png")),
        "view3d": str(report_path.parent / "view3d.html"),
        "chamfer_mm": report.get("chamfer_mm"),
        "converged": report.get("converged"),
        "warnings": report.get("warnings") or [],
        "fscore_5mm": report.get("fscore_5mm"),
        "preset": report.get("preset"),
        "seconds": {k: round(v, 2) for k, v in stages.items()},
        "live": report.get("live") if opts.live else None,
        "dashboard": dashboard,
        "earlier": earlier,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return summary
