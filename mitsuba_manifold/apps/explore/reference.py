"""Full-GI reference renders of a latent point, in the background, with progress.

The blend (Eq. 13) holds the paths that touch the material at most once (L1-); a render
with ``manifold_brdf`` and Mitsuba's ``path`` integrator holds every path. A reference job
renders the basis's scene with its material at ``x`` in its own process
(:mod:`.render_job`, started with ``nice`` so that the blends of a drag take the CPU first,
and paused while a drag runs: :meth:`References.hold`) in passes of
:data:`~.render_job.PASS_SAMPLES` paths, so the page can show its progress, then measures the
blend against it (:func:`mitsuba_manifold.imaging.metrics.compare`) and against the reference's
own noise, which its passes measure (:func:`~mitsuba_manifold.imaging.metrics.noise_agreement`:
a blend that equals full GI still differs from a noisy reference by that noise). A refinement
(:meth:`References.submit_refine`) renders in the worker thread itself, at a lower priority.
One job runs at a time; the others wait in line, at most :data:`MAX_WAITING_PER_TAB` of one
page and :data:`MAX_WAITING` in all (beyond, :class:`~mitsuba_manifold.errors.BusyError`); a
newer refinement cancels the older ones still waiting. A reference render's files are in a
folder of its own inside one temporary folder of the explorer's (named with its process id),
removed when the render ends (done, failed or cancelled) and, with whatever is left in it, by
:meth:`References.shutdown`; the folders of explorers that were killed (no shutdown) are removed
when the next explorer starts.

Every job can be cancelled (:meth:`References.cancel`, or :meth:`References.cancel_tab` for
all the jobs a tab started, when its websocket closes): a queued job never starts, a running
reference's process is ended at once, a running refinement stops after its pass. Nothing a
job does (cancelled, failed) stops the worker.
"""

import itertools
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ...errors import BusyError
from ...imaging import metrics
from ...render.scene.references import BasisView, Reference
from .render_job import RenderSpec

MAX_SPP = 1 << 14
KEEP_JOBS = 16
#: Jobs of one page waiting or rendering at once, and of every page together.
MAX_WAITING_PER_TAB = 4
MAX_WAITING = 32
#: Niceness of the reference processes and of the refinements' thread.
NICENESS = 10
#: Seconds a reference render stays paused after a drag's last frame request (:meth:`References.hold`).
HOLD_S = 0.4
_ROOT = os.path.dirname(
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
)


class Cancelled(Exception):
    """The job was cancelled (by its page, or its page went away)."""


def _lower_priority():
    try:  # Linux: the calling thread's own niceness
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), NICENESS)
    except (AttributeError, OSError):
        pass


@dataclass
class Job:
    id: str
    basis: str
    x: list
    spp: int
    kind: str = "reference"  # reference (path at x), refine (L1- blend + L2+ rendered at x)
    tab: str = None  # the page that started it (its jobs end with its websocket)
    state: str = "queued"  # queued, rendering, done, failed, cancelled
    progress: float = 0.0
    message: str = ""
    started: float = field(default_factory=time.time)
    seconds: float = 0.0
    images: dict = field(default_factory=dict)  # name -> linear float32 (H, W, 3)
    error: dict = None
    cancelled: bool = False
    method: str = None  # a refinement's: how its L2+ light is rendered
    process: object = field(default=None, repr=False)  # a reference's render process while it runs

    def status(self):
        return {
            "id": self.id,
            "basis": self.basis,
            "x": self.x,
            "spp": self.spp,
            "kind": self.kind,
            "state": self.state,
            "progress": self.progress,
            "message": self.message,
            "seconds": self.seconds,
            "error": self.error,
            "images": sorted(self.images),
            "method": self.method,
        }


def agreement(blend_image, refined):
    """Whether the blend shown agrees with an unbiased refinement
    (:class:`~mitsuba_manifold.render.jobs.refine.Refined`) within the refinement's noise: their
    relative MSE (blend against refined) is at most twice the refinement's own estimated noise
    (its expectation where the blend is exact). Where it does not, the blend is off by more than
    the refinement's noise, and the refined image is the better one (``agrees`` False); ``None``
    after one pass (no noise estimate yet).
    """
    if refined.passes < 2:
        return {"noise_rel_mse": None, "blend_rel_mse": None, "agrees": None}
    # on the scale of the refinement's own noise (:class:`Refined`)
    scale = refined.image if refined.scale is None else refined.scale
    r = metrics.noise_agreement(blend_image, refined.image, refined.pixel_se, scale=scale)
    return {
        "noise_rel_mse": r["noise_rel_mse"],
        "blend_rel_mse": r["rel_mse"],
        "agrees": r["agrees"],
    }


class References:
    """Queue of reference jobs (one worker thread)."""

    def __init__(self):
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="explore-reference")
        self._jobs = {}
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._stopping = False
        self._latest_refine = None
        self._held_until = 0.0  # monotonic time until which the running renders stay paused
        self._paused = {}  # pid -> process paused by hold()
        self._resumer = None  # the timer that resumes them
        self._folder = None  # the temporary folder of the reference renders' files
        _sweep(tempfile.gettempdir())  # those of explorers killed before they could remove them

    def submit(self, name, basis, scene, manifold_path, x, spp, blend_image, tab=None):
        """Start a job; returns it. ``blend_image``: the blend at ``x`` to compare with; ``tab``:
        the page that asked (:meth:`cancel_tab`).
        """
        job = Job(
            id=f"r{next(self._ids)}", basis=name, x=[float(v) for v in x], spp=int(spp), tab=tab
        )
        with self._lock:
            self._admit(tab)
            self._jobs[job.id] = job
            self._trim()
        self._pool.submit(self._run, job, basis, scene, manifold_path, blend_image)
        return job

    def _admit(self, tab) -> None:
        """Raise :class:`BusyError` when page ``tab`` (or every page) has as many jobs waiting
        or rendering as allowed; called with the lock held.
        """
        live = [j for j in self._jobs.values() if j.state in ("queued", "rendering")]
        mine = [j for j in live if j.tab == tab] if tab is not None else []
        if len(mine) >= MAX_WAITING_PER_TAB:
            raise BusyError(
                f"this page has {len(mine)} renders waiting or running, at most "
                f"{MAX_WAITING_PER_TAB}: wait for one to finish or cancel one"
            )
        if len(live) >= MAX_WAITING:
            raise BusyError(
                f"the explorer has {len(live)} renders waiting or running, at most "
                f"{MAX_WAITING}: wait for one to finish or cancel one"
            )

    def submit_refine(self, name, basis, manifold, x, spp, blend_image, tab=None, **where):
        """Start a refinement of the blend at ``x`` (:func:`~mitsuba_manifold.render.jobs.refine.refine_passes`;
        ``where``: its ``scene``, ``manifold_file`` and ``prune``): its image (``"refined"``) after
        every pass, in ``error`` the noise the passes measure and whether ``blend_image`` (the
        blend shown) agrees with it within that noise. A newer refinement supersedes it.
        """
        job = Job(
            id=f"r{next(self._ids)}",
            basis=name,
            x=[float(v) for v in x],
            spp=int(spp),
            kind="refine",
            tab=tab,
        )
        with self._lock:
            for old in self._jobs.values():  # never to start: this one supersedes them
                if old.kind == "refine" and old.state == "queued":
                    old.cancelled = True
                    old.state, old.message = "cancelled", "superseded by a newer refinement"
            self._admit(tab)
            self._latest_refine = job.id
            self._jobs[job.id] = job
            self._trim()
        self._pool.submit(self._run_refine, job, basis, manifold, blend_image, where)
        return job

    def supersede_refine(self):
        """A drag began: the running refinement stops after its pass, the queued ones never start
        (they would take the frames' CPU).
        """
        with self._lock:
            self._latest_refine = None

    def hold(self, seconds=None):
        """A drag's frame was asked for: the running reference processes pause (``SIGSTOP``)
        until no frame has been asked for ``seconds`` (default :data:`HOLD_S`), then go on (``SIGCONT``). Niceness alone
        does not keep a render from halving a drag's frames where the render shares the
        processor's cores (hyperthreads, other users' load); paused, it takes none of their time.
        Without ``SIGSTOP`` (not POSIX) this does nothing.
        """
        if not hasattr(signal, "SIGSTOP"):
            return
        seconds = HOLD_S if seconds is None else float(seconds)
        with self._lock:
            self._held_until = time.monotonic() + seconds
            for job in self._jobs.values():
                proc = job.process
                if proc is not None and proc.pid not in self._paused and proc.poll() is None:
                    try:
                        os.killpg(proc.pid, signal.SIGSTOP)
                    except OSError:  # ended meanwhile
                        continue
                    self._paused[proc.pid] = proc
            if self._paused and self._resumer is None:
                self._start_resumer(seconds)

    def _start_resumer(self, seconds):
        self._resumer = threading.Timer(seconds, self._resume)
        self._resumer.daemon = True
        self._resumer.start()

    def _resume(self):
        with self._lock:
            left = self._held_until - time.monotonic()
            if left > 0 and not self._stopping:  # asked again meanwhile: wait for the rest
                self._start_resumer(left)
                return
            self._resumer = None
            for pid in list(self._paused):
                self._continue(pid)

    def _continue(self, pid):
        """Let a paused process go on (also one about to be ended: a stopped process ends only
        once it runs); called with the lock held.
        """
        if self._paused.pop(pid, None) is not None:
            try:
                os.killpg(pid, signal.SIGCONT)
            except OSError:
                pass

    def cancel(self, job_id):
        """Cancel a job: queued, it never starts; rendering, it stops after its pass. Returns
        the job (None when unknown).
        """
        with self._lock:
            job = self._jobs.get(job_id)
            if job is not None and job.state in ("queued", "rendering"):
                job.cancelled = True
                if job.state == "queued":
                    job.state, job.message = "cancelled", "cancelled before it started"
                proc = job.process
                if proc is not None and proc.poll() is None:
                    proc.terminate()
                    self._continue(proc.pid)
        return job

    def cancel_tab(self, tab):
        """Cancel every job the page ``tab`` started (its websocket closed)."""
        with self._lock:
            ids = [j.id for j in self._jobs.values() if j.tab == tab]
        for job_id in ids:
            self.cancel(job_id)

    def _trim(self):
        for old in list(self._jobs)[:-KEEP_JOBS]:
            if self._jobs[old].state in ("done", "failed", "cancelled"):
                del self._jobs[old]

    def _run_refine(self, job, basis, manifold, blend_image, where):
        from ...render.jobs.refine import refine_passes

        def passes():
            self._check_current(job)  # queued behind a newer one: never started
            _lower_priority()
            for r in refine_passes(
                basis,
                manifold,
                x=np.asarray(job.x),
                spp=job.spp,
                passes=max(1, min(4, job.spp)),
                blend_image=blend_image,
                **where,
            ):
                self._check_current(job)
                job.images = {"blend": blend_image, "refined": r.image}
                job.method = r.method
                job.progress, job.message = r.spp / job.spp, f"{r.spp}/{job.spp} spp"
                if r.passes == 0:  # a training material: the blend is already exact
                    job.progress, job.message = (
                        1.0,
                        "exact at a training material: nothing to render",
                    )
                job.error = agreement(blend_image, r)

        self._execute(job, passes)

    def _check_current(self, job):
        self._check(job)
        if job.id != self._latest_refine:
            raise Cancelled("superseded by a newer refinement")

    def _check(self, job):
        """Raise when the job is to stop now (cancelled, or the server stopping)."""
        if self._stopping:
            raise RuntimeError("the server is stopping")
        if job.cancelled:
            raise Cancelled("cancelled")

    def _execute(self, job, work):
        """Run ``work()`` as ``job`` (unless cancelled meanwhile): its state, its failure shown
        on the page, its seconds. Nothing a job does ends the worker thread.
        """
        with self._lock:
            if job.cancelled or job.state != "queued":
                return
            job.state = "rendering"
        t0 = time.perf_counter()
        try:
            work()
            job.state = "done"
        except Cancelled as e:
            job.state, job.message = "cancelled", f"{e} ({job.progress:.0%} done)"
        except Exception as e:  # shown on the page; the server keeps running
            job.state, job.message = "failed", f"{type(e).__name__}: {e}"
        finally:
            job.seconds = time.perf_counter() - t0

    def get(self, job_id):
        with self._lock:
            return self._jobs.get(job_id)

    def _run(self, job, basis, scene, manifold_path, blend_image):
        def render():
            ref = self._render(job, basis, scene, manifold_path)
            job.images = {"blend": blend_image, "reference": ref.image}
            job.error = metrics.compare(blend_image, ref.image)
            noise = metrics.noise_agreement(blend_image, ref.image, ref.pixel_se)
            del noise["rel_mse"]  # compare's, the same (None after one pass)
            job.error.update(noise)

        self._execute(job, render)

    def _render(self, job, basis, scene_path, manifold_path):
        """The reference image of a job, rendered by :mod:`.render_job` in a process of its own
        (``nice``); ended when the job is cancelled or the server stops.
        """
        tmp = tempfile.mkdtemp(prefix="job-", dir=self._job_folders())
        try:
            view = BasisView.of(
                basis, scene=os.path.abspath(scene_path), manifold=os.path.abspath(manifold_path)
            )
            spec = RenderSpec(view, list(job.x), job.spp, os.path.join(tmp, "reference.npz"))
            spec.write(os.path.join(tmp, "spec.json"))
            env = dict(os.environ)
            env["PYTHONPATH"] = os.pathsep.join([_ROOT] + [p for p in [env.get("PYTHONPATH")] if p])
            cmd = [
                "nice",
                "-n",
                str(NICENESS),
                sys.executable,
                "-m",
                "mitsuba_manifold.apps.explore.render_job",
                os.path.join(tmp, "spec.json"),
            ]
            with self._lock, open(os.path.join(tmp, "stderr.txt"), "w") as log:
                self._check(job)
                job.process = subprocess.Popen(
                    cmd,
                    stdout=subprocess.PIPE,
                    stderr=log,
                    env=env,
                    start_new_session=True,
                    text=True,
                )
            proc = job.process
            try:
                for line in proc.stdout:  # "done total" after each pass
                    parts = line.split()
                    if len(parts) == 2 and parts[0].isdigit():
                        done = int(parts[0])
                        job.progress, job.message = done / job.spp, f"{done}/{job.spp} spp"
                proc.wait()
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.wait()
                with self._lock:
                    self._paused.pop(proc.pid, None)
                    job.process = None
            self._check(job)
            if proc.returncode != 0:
                with open(os.path.join(tmp, "stderr.txt"), errors="replace") as f:
                    lines = [ln for ln in f.read().splitlines() if ln.strip()]
                raise RuntimeError(
                    lines[-1] if lines else f"the render exited with {proc.returncode}"
                )
            return Reference.read(spec.out)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def _job_folders(self) -> str:
        """The explorer's temporary folder of reference renders (made on first use)."""
        with self._lock:
            if self._stopping:
                raise RuntimeError("the server is stopping")
            if self._folder is None or not os.path.isdir(self._folder):
                self._folder = tempfile.mkdtemp(prefix=f"explore-reference-{os.getpid()}-")
            return self._folder

    def busy(self):
        """Whether a job is rendering now."""
        with self._lock:
            return any(j.state == "rendering" for j in self._jobs.values())

    def shutdown(self, wait=0.0):
        """Drop the queued jobs; the running one stops (a reference at once, a refinement after
        its current pass). Waits up to ``wait`` seconds for it; returns whether no job is
        rendering any more.
        """
        self._stopping = True
        self._pool.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            ids = [j.id for j in self._jobs.values() if j.state == "rendering"]
        for job_id in ids:
            self.cancel(job_id)
        deadline = time.monotonic() + wait
        while self.busy() and time.monotonic() < deadline:
            time.sleep(0.02)
        with self._lock:  # still running: ended now, so that their files can go
            procs = [j.process for j in self._jobs.values() if j.process is not None]
            folder, self._folder = self._folder, None
        for proc in procs:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except OSError:
                pass
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)
        return not self.busy()


_FOLDER = re.compile(r"^explore-reference-([0-9]+)-")


def _sweep(folder) -> None:
    """Remove the reference renders' folders in ``folder`` left by explorers that no longer run
    (killed: no shutdown removed them); a folder is an explorer's by its name, which holds the
    process id.
    """
    try:
        names = os.listdir(folder)
    except OSError:
        return
    for name in names:
        m = _FOLDER.match(name)
        if m is None or int(m.group(1)) == os.getpid():
            continue
        try:
            os.kill(int(m.group(1)), 0)
            continue  # that explorer runs
        except ProcessLookupError:
            pass
        except (OSError, OverflowError):
            continue  # another user's, or not a process id: left alone
        shutil.rmtree(os.path.join(folder, name), ignore_errors=True)
