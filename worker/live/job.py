"""A live job: reconstruct a scan while it is recorded, then finish it from the live state.

The job process of a live job (`Job.live`, queued by `spadscan worker --live` as soon as a scan's first chunk is
published) runs `execute_live_job`:

1. **Follow.** Poll the capture every `poll_s`: re-read the manifest, read each new chunk. Once `min_views` views are
   published, fit them (`LiveFit`), and refit warm on every view published so far once their number has grown by
   `rebuild_growth` or by `rebuild_views` (`refit_due`: never more than `rebuild_share` of the time goes to refits,
   which on a loaded machine would otherwise take most of it); between polls, train. Every
   `publish_every_s`, publish `<capture>/recon/live/` (mesh.ply, preview.png, status.json: `publish.py`); in between,
   rewrite status.json alone after every refit and every `status_every_s` (the views fitted, those published at the
   last poll, the steps). While an adaptive scan runs, hand the live state to the view ranking, which writes the
   capture's next_views.json.
2. **Finish.** When the scan is complete, run the ordinary reconstruction of the whole capture, its model
   warm-started from the live fit once that has left its coarse level and gone on as long on its last one
   (`LiveFit.continuable`) and has left out fewer views than a quarter of those it holds (`final_start`; else from
   the carved hull), for the job's budget or steps, else `final_polish_s` of steps (the preset's budget when it
   starts from the hull): the result is written into the job's scratch folder
   and published by the worker where every job's result goes. Of the final field and the live one, the one that
   explains every view better is meshed (`keep.py`: a short final run never publishes a worse or coarser mesh than
   the live one); report.json's `published` says which. A live job that never fitted anything (its scan was
   complete before it started, or held too few views) runs the ordinary job.
3. **Abort.** When the scan is aborted the job ends at once: the live folder keeps its last state, the status says
   `aborted`, and the job fails with the scan's reason (not retried). A job that starts after its scan was aborted
   (re-run after its worker died) says `aborted` there and clears nothing.

The live folder is one live job's (`publish.take_live_folder`; marked the job's when the queue hands it out,
`publish.claim_live_folder`): another live job of the same scan (another preset, or another queue's job of its id,
told apart by its owner token) writes nothing there and runs as an ordinary job. The queue leaves it queued while
the scan is recorded and hands it out as an ordinary job once the scan has ended (`Queue.live_claim`); one whose
process finds the folder taken all the same waits for the scan's end (`not_holding`).

A live job reads the capture and writes only under its `recon/` folder; the daemon never waits for it.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from spadscan.protocol.errors import SpadscanError
from spadscan.protocol.live_status import STATUS, LiveStatus, read_status

from .follower import ScanFollower, ScanProgress
from .keep import keep_the_better
from .next_views import is_adaptive, update_next_views
from .publish import clear_earlier, live_folder, publish_mesh, publish_status, take_live_folder
from .recoarse import RecoarsePolicy
from .saturation import live_saturation_warning


@dataclass(frozen=True)
class LiveSettings:
    """How a live job follows its scan. Seconds are wall-clock."""

    min_views: int = 8
    """Views published before the first fit (fewer carve no useful hull)."""
    poll_s: float = 0.5
    """How often the capture is looked at (the model trains in between)."""
    publish_every_s: float = 5.0
    """How often the mesh and preview in recon/live/ are rewritten (at least; never more than a fifth of the time goes
    to publishing)."""
    status_every_s: float = 2.0
    """How often recon/live/status.json alone is rewritten between two of those (and at once after every refit): the
    mesh, its preview and its Chamfer take seconds on a busy machine, so that publications come 12-15 s apart there,
    and a status written only with them said a fit of 8 views while the scan had published 21 and the job fitted
    19. Rewriting it is cheap (a small file)."""
    rebuild_growth: float = 0.25
    """Refit once the published views outnumber the fitted ones by this fraction ..."""
    rebuild_views: int = 16
    """... or by this many views, whichever comes first ..."""
    rebuild_share: float = 0.25
    """... and once the training since the last refit has taken (1 / share - 1) times that refit's wall time: refits
    (loading the capture, carving, building the problem) take at most this share of the live job's time."""
    mesh_resolution: int = 96
    """Marching-cubes cells along the longest side of the live mesh."""
    preview: bool = True
    """Draw recon/live/preview.png with each mesh."""
    rank_every_s: float = 5.0
    """How often an adaptive scan's candidates are ranked (next_views.json), at least: sooner once the scan has
    published half its `next_views_max_lag` of poses since the last ranking (`LiveRun._rank`)."""
    final_polish_s: float = 4.0
    """Training seconds of the final reconstruction when the job names neither a budget nor steps: it continues
    from the live fit, so it polishes rather than fits. Given to it as a step count (the live fit's recent step rate
    times this, at least `final_min_steps`), so that the stages after training (the full mesh, the metrics, the
    pictures) are never cut short as a budget this short would cut them."""
    final_min_steps: int = 10
    """Fewest steps of that final reconstruction."""
    final_checkpoints: int = 1
    """Trace checkpoints of that final reconstruction (its start and end besides): with a ground truth each one
    meshes and scores the field (0.3 s on 2 cores), which a polish of a few dozen steps would spend a dozen times
    over, after the scan's end, for a trace of nearly flat figures."""
    recoarse: RecoarsePolicy = RecoarsePolicy()
    """When a refit goes back to the coarse level (the first views see the object from one side only)."""
    quiet_note_s: float = 600.0
    """A scan that publishes nothing for this long (its daemon paused, stopped or gone) is said to be quiet, in the
    job's log and the live status, until it publishes again; the job keeps following it (a paused scan resumes)."""
    live_threads: int = 1
    """CPU threads of the live fit while the scan runs (the final run gets the job's own): the daemon beside it keeps
    a core."""
    overrides: tuple = ()
    """(dotted key, value) pairs changing the preset's config, for the live fit and the final run alike (as
    `spadscan reconstruct --set`; benchmarks and tests make small fits with it)."""


def refit_due(have: int, published: int, trained_s: float, last_refit_s: float, settings: LiveSettings) -> bool:
    """Whether a fit of `have` views is refitted on the `published` ones now, `trained_s` wall seconds after the
    last refit, which took `last_refit_s`: the views must grow by `rebuild_growth` or `rebuild_views` (a refit per
    chunk costs more than it brings), and refits keep to `rebuild_share` of the time."""
    s = settings
    wanted = max(1, min(s.rebuild_views, math.ceil(s.rebuild_growth * have)))
    if published - have < wanted:
        return False
    return trained_s >= last_refit_s * (1.0 / s.rebuild_share - 1.0)


def final_start(fit, views: int, settings: LiveSettings) -> tuple[str, str | None]:
    """Where the final run of a scan of `views` views starts: ('live', None) from the live fit, else ('hull', why).

    Not from a fit still young on its level (`LiveFit.continuable`), nor from one that has left out `rebuild_growth`
    (a quarter) of its own views or more: the scan ended long before the next refit (a pause and a fast resume, a
    loaded machine whose refits wait their share of the time). A field fitted to part of the views is a start the
    complete capture cannot recover from: a goblet scan of 48 views that ended with 26 fitted came out at 54-87 mm from
    the live fit (polished, or trained for the preset's whole budget), and 1.36 mm from the hull. A scan at a steady
    pace ends with its fit some views behind (a refit is due at `rebuild_views`, 16, and waits its share of the time:
    107 of 128 in a steady replay), which a warm refit is meant to take in: the cut-off is the growth that makes a
    refit go on warm, not the count that makes it due."""
    if not fit.continuable:
        return "hull", "the live fit is too young (on its coarse level, or only just past it)"
    if views - fit.views_used >= math.ceil(settings.rebuild_growth * fit.views_used):
        return "hull", (f"the live fit holds {fit.views_used} of the scan's {views} views (the scan ended before "
                        f"its next refit)")
    return "live", None


def status_finishing(scan: Path, job, progress: ScanProgress, note: str) -> None:
    """The live status of a job that found its scan complete (a fast scan, or a job taken over after the scan's end):
    'final', so that whoever follows it sees the final run and, once published, its result. It reconstructs from
    scratch: nothing an earlier attempt fitted stays (figures, mesh, preview), which would read as this run's."""
    folder = live_folder(scan)
    clear_earlier(folder)
    publish_status(folder, LiveStatus(views_used=0, views_published=progress.views_published, steps=0, state="final",
                                      views_planned=progress.views_planned, job=job.id, note=note,
                                      owner=job.owner))


class ScanAborted(SpadscanError):
    """The scan a live job followed was aborted: the job ends (not retried)."""


def status_aborted(folder: Path, job, progress: ScanProgress, note: str) -> None:
    """The live status of a job whose scan was aborted before it began (its earlier attempt's worker died, and the
    job was queued again): 'aborted', everything else as the earlier attempt left it (its figures describe the mesh
    and preview beside them, which stay: the scan will publish nothing more for a fit to replace them)."""
    try:
        status = read_status(Path(folder) / STATUS)
    except SpadscanError:
        status = LiveStatus(views_used=0, views_published=progress.views_published, steps=0,
                            views_planned=progress.views_planned)
    try:
        publish_status(folder, dataclasses.replace(status, state="aborted", note=note, job=job.id, updated_utc="",
                                                   owner=job.owner))
    except OSError:  # the scan's folder moved away (how a scan no daemon will resume is ended), a full disk
        pass


def not_holding(job, root: Path, out: Path, recon, queue, follower: ScanFollower, progress: ScanProgress,
                holder: str, settings: LiveSettings, log: Callable[[str], None]) -> dict:
    """Run live job `job` of a scan whose live folder another live job (`holder`) holds (`take_live_folder`): it
    writes nothing there, waits for the scan's end, and reconstructs the complete capture as an ordinary job (its
    result in its own folder, `recon/<job>/`). Raises ScanAborted when the scan is aborted. Rare: the queue hands
    such a job out only once its scan has ended, as an ordinary job (`Queue.live_claim`); this is for one whose
    claim did not see the folder taken."""
    from ..jobs import execute_job

    whose = f"another queue's live job {holder}" if holder == job.id else f"live job {holder}"
    log(f"live: {job.scan}/recon/live is {whose}'s: this job publishes nothing there; it reconstructs "
        f"the scan as an ordinary job once the scan is complete")
    while not progress.ended:
        time.sleep(settings.poll_s)
        progress = follower.poll()
    if progress.state == "aborted":
        raise ScanAborted(f"scan {job.scan} was aborted ({progress.reason or 'no reason given'}): its job ended")
    return execute_job(dataclasses.replace(job, live=False), root, out, recon, queue=queue)


def execute_live_job(job, root: Path, out: Path, recon: Callable | None = None,
                     settings: LiveSettings | None = None, log: Callable[[str], None] | None = None,
                     queue: Path | None = None) -> dict:
    """Run the live job `job` (see the module): follow its scan, then reconstruct the complete capture into `out`
    (the job's scratch folder) from the live state. Returns the final report, with `live` (what the live phase
    did). Raises ScanAborted when the scan is aborted, SpadscanError (one line) for a capture that cannot be read.
    `queue`: the queue the job was claimed from, passed on to `execute_job`."""
    from ..jobs import add_to_report, execute_job, ground_truth, scan_path

    settings = settings or LiveSettings()
    log = log or _stderr
    scan = scan_path(job, root)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    follower = ScanFollower(scan)
    progress = follower.poll()
    folder = live_folder(scan)
    holder = take_live_folder(folder, job, LiveStatus(
        views_used=0, views_published=progress.views_published, steps=0, state="waiting",
        views_planned=progress.views_planned, job=job.id, owner=job.owner))
    if holder is not None:
        return not_holding(job, root, out, recon, queue, follower, progress, holder, settings, log)
    if progress.ended and progress.state == "complete":
        # (also where an earlier attempt fitted live and its worker was stopped: this attempt found the scan ended)
        note = (f"scan {scan.name} was already complete when its live job started (or was retried): reconstructing "
                f"it from scratch")
        log(f"live: {note}")
        status_finishing(scan, job, progress, note)
        return execute_job(dataclasses.replace(job, live=False), root, out, recon, queue=queue)
    if progress.ended:  # aborted before this attempt began: what the last attempt published stays as it is
        reason = progress.reason or "no reason given"
        log(f"live: scan aborted: {reason}")
        status_aborted(folder, job, progress, f"scan aborted: {reason}")
        raise ScanAborted(f"scan {scan.name} was aborted ({reason}) before its live job started: the last live "
                          f"result stays in {folder}")
    runner = LiveRun(job, scan, folder, follower, settings, log)
    runner.begin(progress)  # before the set-up (the ground truth, torch, the device), which takes seconds
    gt, _ = ground_truth(progress.manifest, out)
    runner.start(progress, gt)
    try:
        progress = runner.follow(progress)
    except SpadscanError as exc:  # a chunk or manifest that cannot be read: the job fails saying why
        runner.stopped("stopped", str(exc))
        raise
    finally:
        runner.restore_threads()
    if progress.state == "aborted":
        runner.stopped("aborted", f"scan aborted: {progress.reason or 'no reason given'}")
        raise ScanAborted(f"scan {scan.name} was aborted ({progress.reason or 'no reason given'}): its live job "
                          f"ended; the last live result stays in {folder}")
    if runner.fit.model is None:
        why = no_live_model(runner.fit, progress.views_published)
        runner.stopped("final", f"{why}: reconstructing it from scratch")
        return execute_job(dataclasses.replace(job, live=False), root, out, recon, queue=queue)
    start, why = final_start(runner.fit, progress.views_published, settings)
    if progress.state == "complete":
        # The status only: the live mesh is at most publish_every_s old, and meshing and drawing it again would
        # delay the final result that replaces it.
        runner.write_status(progress, "final", final_start=start)
    final, bounds = final_job(job, runner.fit, settings, start)
    live_report = runner.fit.report()
    length = (f"{final.budget_s:g} s" if final.budget_s is not None else
              f"{final.steps} steps" if final.steps is not None else "the preset's budget")
    how = "continues from the live fit" if start == "live" else f"starts from the carved hull: {why}"
    log(f"live: scan complete ({live_report['views_used']} views fitted, {live_report['steps']} steps); the final "
        f"reconstruction {how}, for {length}")
    report = execute_job(final, root, out, runner.final_recon(recon, start == "live", chose_polish(job, final)),
                         queue=queue)
    extra = {"live": {**live_report, **bounds, "final_start": start}}
    add_to_report(out, extra)
    report.update(extra)
    return report


def no_live_model(fit, views_published: int) -> str:
    """Why a scan that ended has no live model (`fit.model` None): the live fit never started, or it diverged twice on
    its views and was dropped (`LiveFit.restart`; its `not_yet` says so). An early try's failure (too few views yet)
    that `not_yet` may still hold is not the reason: the scan ended before the next try."""
    if fit.not_yet and fit.diverged_views == fit.views_used:
        return fit.not_yet
    return f"the scan completed with {views_published} views before the live fit started"


def final_job(job, fit, settings: LiveSettings, start: str) -> tuple:
    """The final run's job and report.json's record of its bounds: the job's own budget or steps where it names
    them; else, continuing from the live fit (`start` 'live', `final_start`), `settings.final_polish_s` of training
    as a step count at the live fit's recent rate, and from the hull the preset's own budget (both None)."""
    if job.budget_s is not None or job.steps is not None:
        return dataclasses.replace(job, live=False), {"final_budget_s": job.budget_s, "final_steps": job.steps}
    if start != "live":  # the final run starts from the carved hull: a polish cannot fit the object
        return dataclasses.replace(job, live=False), {"final_budget_s": None, "final_steps": None}
    rate = fit.recent_steps_per_s() or fit.steps_per_s() or 0.0
    steps = max(settings.final_min_steps, round(rate * settings.final_polish_s))
    return dataclasses.replace(job, live=False, steps=steps), {"final_budget_s": None, "final_steps": steps}


def chose_polish(job, final) -> bool:
    """Whether the final run `final` (`final_job`'s) of live job `job` is a polish for the step count the live job
    chose itself: the job named neither a budget nor steps, and the final run went on from the live fit for steps.
    Too short for the plateau test to judge (`end_of_run.RunFacts.polish`); steps the user asked for are not."""
    return job.budget_s is None and job.steps is None and final.steps is not None


def _rank_after(manifest: dict) -> float:
    """Poses published since the last ranking that make the next one due at once: half the scan's
    `next_views_max_lag` (its manifest's schedule record), at least 1; never when the record does not say."""
    schedule = manifest.get("schedule")
    lag = schedule.get("next_views_max_lag") if isinstance(schedule, dict) else None
    return max(1, lag // 2) if isinstance(lag, int) and not isinstance(lag, bool) else math.inf


def _stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class LiveRun:
    """The follow phase of one live job: the fit, the live folder, and when to refit, train and publish."""

    def __init__(self, job, scan: Path, folder: Path, follower: ScanFollower, settings: LiveSettings,
                 log: Callable[[str], None]):
        self.job, self.scan, self.folder, self.follower, self.settings, self.log = (job, scan, folder, follower,
                                                                                    settings, log)
        self.fit = None
        self.truth = None
        self.fit_views = 0
        self.tried_views = 0
        """Views published when a first fit last failed: the same views would fail again (no returns, no hull)."""
        self.chamfer_mm: float | None = None
        self.chamfer_views: int | None = None
        """The views of the fit whose mesh `chamfer_mm` was measured on."""
        self.next_publish = -math.inf
        self.publish_cost_s = 0.0
        self.status_at = -math.inf
        """When status.json was last written (time.monotonic()): `update_status` rewrites it every `status_every_s`."""
        self.last_rebuild = -math.inf
        """When the last refit ended (time.monotonic())."""
        self.last_rebuild_cost = 0.0
        """Its wall seconds."""
        self.next_rank = -math.inf
        self.ranked_views = 0
        """Views published when the last ranking was made."""
        self.rank_free_at = -math.inf
        """No ranking before this (time.monotonic()): the last one's cost again, so that ranking takes at most half
        the time and the fit trains in the other half."""
        self.last: ScanProgress | None = None
        self.last_news = time.monotonic()
        """When the scan last published a chunk or rewrote its manifest (time.monotonic())."""
        self.quiet_note: str | None = None
        """What the live status says while the scan is quiet (`quiet_note_s`), else None."""
        self.preview_warning: str | None = None
        """Why the last published mesh has no preview ("no preview.png: <why>", as a run's report says it), else
        None: every status says it (`write_status`), as long as it holds."""
        self.saturation_warning: str | None = None
        """The pile-up line (`live_saturation_warning`) while the views last fitted are mostly saturated, else None:
        every status says it, first among its warnings."""

    # ---- set-up --------------------------------------------------------------------------------------------------
    def begin(self, progress: ScanProgress) -> None:
        """This attempt's first word: remove what an earlier attempt left (`clear_earlier`: its mesh and preview,
        which beside this attempt's status would read as this one's), then at once say 'waiting'. Until then a
        reader sees the earlier attempt's last status (its 'queued' note, or the figures of an attempt whose worker
        died): said before the set-up, that status never stands over a job that runs again."""
        clear_earlier(self.folder)
        self.publish(progress, state="waiting", force=True)

    def start(self, progress: ScanProgress, gt: Path | None) -> None:
        """Load the reconstruction's settings, the device and the ground truth (torch is imported here)."""
        import torch

        from ..ground_truth import load_ground_truth
        from ..reconstruct import resolve_device, run_config
        from .live_fit import LiveFit

        self.threads = torch.get_num_threads()
        torch.set_num_threads(max(1, min(self.threads, self.settings.live_threads)))
        config = run_config(self.job.preset, dict(self.settings.overrides) or None)
        self.config = config
        self.fit = LiveFit(self.scan, config, resolve_device(self.job.device), self.job.seed, self.log,
                           self.settings.recoarse)
        if gt is not None:
            try:
                self.truth = load_ground_truth(gt)
            except SpadscanError as exc:
                self.log(f"live: no Chamfer while scanning: {exc}")

    def restore_threads(self) -> None:
        """Give the final run the job's own CPU threads back."""
        import torch

        torch.set_num_threads(self.threads)

    # ---- following -----------------------------------------------------------------------------------------------
    def follow(self, progress: ScanProgress) -> ScanProgress:
        """Refit, train and publish until the scan ends; returns the last poll (state 'complete' or 'aborted')."""
        s = self.settings
        while True:
            if progress.ended:
                self.last = progress
                return progress
            now = time.monotonic()
            self._note_quiet(progress, now)
            self.last = progress
            if self._refit_due(progress, now):
                rebuilt = self.fit.rebuild(progress.views_planned)
                self.last_rebuild_cost = time.monotonic() - now
                self.last_rebuild = time.monotonic()
                if rebuilt:
                    self.fit_views = self.fit.views_used
                    self._saturation_said(self.fit.scene)
                    level = getattr(self.fit.model, "level", None)
                    level = "coarse level" if level == 0 else f"level {level}"
                    # the refit read the capture itself, and may have seen views the last poll had not
                    published = max(progress.views_published, self.fit.views_used)
                    self.log(f"live: fitting {self.fit.views_used} of {published} published views "
                             f"(refit {self.fit.rebuilds}, {self.fit.steps} steps so far, {level})")
                    if self.fit.rebuilds == 1:
                        self.publish(progress, force=True)  # the first fit's mesh at once
                    else:  # the refit said at once; its mesh at the next publication, when due
                        self.update_status(progress, force=True)
                else:
                    self.tried_views = progress.views_published
            self.publish(progress)
            self.update_status(progress)
            self._rank(progress)
            until = time.monotonic() + s.poll_s
            if self.fit.model is not None and not self.fit.converged:
                self.fit.train(until)
            else:
                time.sleep(max(0.0, until - time.monotonic()))
            progress = self.follower.poll()

    def _note_quiet(self, progress: ScanProgress, now: float) -> None:
        """Say so when the scan has published nothing for `quiet_note_s`, and when it publishes again. A scan whose
        daemon stopped mid-scan stays 'running' until a daemon takes it over; this job holds its process till then."""
        before = self.last
        if before is None or progress.new_chunks or progress.manifest.get("updated_utc") != before.manifest.get(
                "updated_utc"):
            self.last_news = now
            if self.quiet_note is not None:
                self.quiet_note = None
                self.log("live: the scan publishes again")
            return
        quiet_s = now - self.last_news
        if self.quiet_note is None and quiet_s >= self.settings.quiet_note_s:
            self.quiet_note = (f"the scan has published nothing for {quiet_s / 60:.0f} min (its daemon paused or "
                               f"stopped?); still following it: `spadscan ctl status` says whether it is paused; a "
                               f"scan no daemon will resume ends this job when its folder is moved out of the "
                               f"captures root")
            self.log(f"live: {self.quiet_note}")
            self.publish(progress, force=True)

    def _refit_due(self, progress: ScanProgress, now: float) -> bool:
        s = self.settings
        have, published = self.fit.views_used, progress.views_published
        if published < s.min_views or published <= have:
            return False
        if self.fit.model is None:
            # A failed first fit is tried again at the next poll that brings more views (loading the capture again
            # for the same ones costs a load per poll, for the whole of a scan that sees nothing).
            return published > self.tried_views and now - self.last_rebuild >= s.poll_s
        return refit_due(have, published, now - self.last_rebuild, self.last_rebuild_cost, s)

    def _rank(self, progress: ScanProgress) -> None:
        """Hand the live state to the view ranking of an adaptive scan every `rank_every_s`, and sooner once the scan
        has published half its `next_views_max_lag` of poses since the last ranking: the daemon calls a ranking
        that many poses old stale, and an arm quicker than a pose a second would otherwise find every one stale
        (measured: 39 of 48 poses from the fallback plan with a pose every 0.55 s). Ranking takes at most half the
        time (`rank_free_at`)."""
        now = time.monotonic()
        if self.fit.model is None or now < self.rank_free_at or not is_adaptive(progress.manifest):
            return
        if now < self.next_rank and progress.views_published - self.ranked_views < _rank_after(progress.manifest):
            return
        self.next_rank = now + self.settings.rank_every_s
        self.ranked_views = progress.views_published
        try:
            update_next_views(self.scan, progress.manifest, self.fit.snapshot(), progress.poses)
        except (SpadscanError, ValueError, OSError) as exc:  # OSError: a full disk; the scan goes on without them
            self.log(f"live: no next views this time: {' '.join(str(exc).split())}")
        self.rank_free_at = 2 * time.monotonic() - now  # from now on, as long again as this ranking took

    # ---- publishing ----------------------------------------------------------------------------------------------
    def publish(self, progress: ScanProgress, state: str | None = None, force: bool = False) -> None:
        """Rewrite recon/live/ when due (or `force`): the mesh and preview of the current fit, then the status."""
        now = time.monotonic()
        if not force and now < self.next_publish:
            return
        t0 = time.perf_counter()
        fit = self.fit
        if fit is not None and fit.model is not None:
            try:
                mesh = fit.mesh(self.settings.mesh_resolution)
                warning = publish_mesh(self.folder, mesh, None if self.truth is None else self.truth.mesh,
                                       preview=self.settings.preview)
                self._preview_said(warning)
                if self.truth is not None:
                    self.chamfer_mm = self.truth.metrics(mesh, n_points=self.config.trace_points).chamfer_mm
                    self.chamfer_views = fit.views_used
            except SpadscanError as exc:  # no surface yet: the status says so
                self.log(f"live: no mesh yet: {exc}")
            except OSError as exc:  # a full disk: the fit goes on, and publishes again when there is room
                self.log(f"live: the live mesh not published this time: {' '.join(str(exc).split())}")
            fit.remember()
        try:
            self._write_following(progress, state)
        except OSError as exc:
            self.log(f"live: the live status not published this time: {' '.join(str(exc).split())}")
        self.publish_cost_s = time.perf_counter() - t0
        # Publishing takes at most about a fifth of the time: a slow machine publishes less often.
        self.next_publish = time.monotonic() + max(self.settings.publish_every_s, 4.0 * self.publish_cost_s)

    def _saturation_said(self, scene) -> None:
        """Keep whether the views just fitted are saturated (pile-up) for the statuses, and log it when that
        changes: said while the scan runs, the power can be lowered before the rest is taken."""
        warning = live_saturation_warning(scene.counts.cpu().numpy(), scene.valid.cpu().numpy())
        if warning is not None and self.saturation_warning is None:
            self.log(f"live: warning: {warning}")
        self.saturation_warning = warning

    def _preview_said(self, warning: str | None) -> None:
        """Keep why the mesh just published has no preview (None: it has one) for the statuses, and log it once."""
        if warning is not None and warning != self.preview_warning:
            self.log(f"live: {warning}")
        self.preview_warning = warning

    def update_status(self, progress: ScanProgress, force: bool = False) -> None:
        """Rewrite status.json alone when `status_every_s` has passed since it was last written (or `force`: a
        refit): the views fitted, those the scan has published at this poll, the steps. The mesh, the preview and
        the Chamfer (of that mesh) stay as the last publication left them: they keep their own cadence (`publish`)."""
        if not force and time.monotonic() < self.status_at + self.settings.status_every_s:
            return
        try:
            self._write_following(progress)
        except OSError:  # a full disk: the next publication says so in the log (not a line every few seconds)
            pass

    def _write_following(self, progress: ScanProgress, state: str | None = None) -> None:
        """Write the status of the follow phase: 'live' once there is a fit, else 'waiting' (with why). Raises
        OSError when it cannot be written (a full disk); the next try is `status_every_s` later all the same."""
        self.status_at = time.monotonic()
        fitting = self.fit is not None and self.fit.model is not None
        self.write_status(progress, state or ("live" if fitting else "waiting"),
                          note=self.quiet_note or (None if fitting else self._waiting_note(progress)))

    def _waiting_note(self, progress: ScanProgress) -> str | None:
        """Why there is no live fit yet: the last try's failure; else, with enough views published, that the first
        fit is being made (loading the views and carving their hull take a while: without a note, "waiting for
        views: 0/124" reads as if none had come)."""
        fit = self.fit
        if fit is not None and fit.not_yet:
            return fit.not_yet
        if progress.views_published >= self.settings.min_views:
            return f"making the first fit of {progress.views_published} views (loading them, carving their hull)"
        return None

    def write_status(self, progress: ScanProgress, state: str, note: str | None = None,
                     final_start: str | None = None) -> None:
        """Write status.json: the fit's figures in `state`, with `note` and, where the live mesh has no preview, why
        (`preview_warning`) in its warnings."""
        fit = self.fit
        used = 0 if fit is None else fit.views_used
        # A refit reads the capture itself and can see views that the last poll had not: every view it uses was
        # published, so the status never says more views used than published ("101/98 views").
        publish_status(self.folder, LiveStatus(
            views_used=used, views_published=max(progress.views_published, used),
            steps=0 if fit is None else fit.steps, converged=bool(fit is not None and fit.converged), state=state,
            chamfer_mm=None if self.chamfer_mm is None else round(float(self.chamfer_mm), 4),
            views_planned=progress.views_planned, job=self.job.id, owner=self.job.owner, note=note,
            final_start=final_start,
            chamfer_views=self.chamfer_views,
            warnings=tuple(w for w in (self.saturation_warning, self.preview_warning) if w)))

    def stopped(self, state: str, note: str) -> None:
        """The follow phase ended otherwise than by a finished scan with a fit: say so in the status."""
        self.log(f"live: {note}")
        try:
            self.write_status(self.last, state, note)
        except OSError:  # the scan's folder moved away (how a scan no daemon will resume is ended), a full disk
            pass

    # ---- the final run -------------------------------------------------------------------------------------------
    def final_recon(self, recon: Callable | None, from_live: bool, polish: bool = False) -> Callable:
        """The reconstruction function of the final run: the ordinary one, its model warm-started from the live fit
        where `from_live` (the field, the level and where its learning-rate decay stands; `final_start` decides),
        else started from the carved hull, and once trained holding the better of its
        own field and the live fit's (keep.py) for its mesh, pictures and metrics; `polish`: its step count is the
        one the live job chose (`final_job`), which its report's checks know (`end_of_run.RunFacts.polish`). A
        replacement reconstruction (`--recon`, tests) is used as it is."""
        from ..reconstruct import reconstruct_capture

        if recon is not None and recon is not reconstruct_capture:
            return recon
        overrides = {"trace_checkpoints": self.settings.final_checkpoints, **dict(self.settings.overrides)}
        keep = functools.partial(keep_the_better, live=self.fit.live_state(), log=self.log)
        return functools.partial(reconstruct_capture, make=self.fit.warm_factory(from_live), overrides=overrides,
                                 after_training=keep, polish=polish)


__all__ = ["LiveSettings", "ScanAborted", "execute_live_job", "LiveRun", "final_start", "refit_due", "chose_polish",
           "no_live_model"]
