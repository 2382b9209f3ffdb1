"""Full-GI reference renders of a latent point, in the background, with progress.

The blend (Eq. 13) holds the paths that touch the material at most once (L1-); a render
with ``manifold_brdf`` and Mitsuba's ``path`` integrator holds every path. A job loads the
basis's scene once, sets its material to ``x`` and renders it in passes of about a second
(:func:`~mitsuba_manifold.render.interrupt.sample_passes`; different seeds, averaged as
:func:`~mitsuba_manifold.render.interrupt.render_in_passes` does) so the page can show its
progress and a stopping server does not wait for a long render, then measures the blend
against it (:func:`mitsuba_manifold.imaging.metrics.compare`). One job renders at a time (the
renders share the CPU with the blends); the others wait in line.
"""

import itertools
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ...imaging import metrics
from ...render.interrupt import sample_passes
from ...render.scenes import load_scene, scene_resolution, set_points

MAX_SPP = 1 << 14
KEEP_JOBS = 16


@dataclass
class Job:
    id: str
    basis: str
    x: list
    spp: int
    kind: str = "reference"        # reference (path at x), refine (L1- blend + L2+ rendered at x)
    state: str = "queued"          # queued, rendering, done, failed
    progress: float = 0.0
    message: str = ""
    started: float = field(default_factory=time.time)
    seconds: float = 0.0
    images: dict = field(default_factory=dict)   # name -> linear float32 (H, W, 3)
    error: dict = None

    def status(self):
        return {"id": self.id, "basis": self.basis, "x": self.x, "spp": self.spp, "kind": self.kind, "state": self.state,
                "progress": self.progress, "message": self.message, "seconds": self.seconds,
                "error": self.error, "images": sorted(self.images)}


def agreement(blend_image, refined):
    """Whether the blend shown agrees with an unbiased refinement (:class:`~mitsuba_manifold.render.refine.Refined`)
    within the refinement's noise: their relative MSE (blend against refined) is at most twice
    the refinement's own estimated noise (its expectation where the blend is exact). Where it
    does not, the blend is off by more than the refinement's noise, and the refined image is
    the better one (``agrees`` False); ``None`` after one pass (no noise estimate yet)."""
    if refined.passes < 2:
        return {"noise_rel_mse": None, "blend_rel_mse": None, "agrees": None}
    diff = refined.rel_mse(blend_image)   # on the same scale as its noise
    return {"noise_rel_mse": refined.noise_rel_mse, "blend_rel_mse": diff,
            "agrees": bool(diff <= 2.0 * refined.noise_rel_mse)}


class References:
    """Queue of reference jobs (one worker thread)."""

    def __init__(self):
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="explore-reference")
        self._jobs = {}
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._stopping = False
        self._latest_refine = None

    def submit(self, name, basis, scene, manifold_path, x, spp, blend_image):
        """Start a job; returns it. ``blend_image``: the blend at ``x`` to compare with."""
        job = Job(id=f"r{next(self._ids)}", basis=name, x=[float(v) for v in x], spp=int(spp))
        with self._lock:
            self._jobs[job.id] = job
            self._trim()
        self._pool.submit(self._run, job, basis, scene, manifold_path, blend_image)
        return job

    def submit_refine(self, name, basis, manifold, x, spp, blend_image, **where):
        """Start a refinement of the blend at ``x`` (:func:`~mitsuba_manifold.render.refine.refine_passes`;
        ``where``: its ``scene``, ``manifold_path`` and ``prune``): its image (``"refined"``) after
        every pass, in ``error`` the noise the passes measure and whether ``blend_image`` (the
        blend shown) agrees with it within that noise. A newer refinement supersedes it."""
        job = Job(id=f"r{next(self._ids)}", basis=name, x=[float(v) for v in x], spp=int(spp), kind="refine")
        with self._lock:
            self._latest_refine = job.id
            self._jobs[job.id] = job
            self._trim()
        self._pool.submit(self._run_refine, job, basis, manifold, blend_image, where)
        return job

    def supersede_refine(self):
        """A drag began: the running refinement stops after its pass, the queued ones never start
        (they would take the frames' CPU)."""
        with self._lock:
            self._latest_refine = None

    def _trim(self):
        for old in list(self._jobs)[:-KEEP_JOBS]:
            if self._jobs[old].state in ("done", "failed"):
                del self._jobs[old]

    def _run_refine(self, job, basis, manifold, blend_image, where):
        from ...render.refine import CONTROL_VARIATE, refine_passes

        def passes():
            self._check_current(job)   # queued behind a newer one: never started
            for r in refine_passes(basis, manifold, x=np.asarray(job.x), spp=job.spp, passes=max(1, min(4, job.spp)),
                                   blend_image=blend_image, **where):
                self._check_current(job)
                job.images = {"blend": blend_image, "refined": r.image}
                what = "L2+ correction" if r.method == CONTROL_VARIATE else "L2+"
                job.progress, job.message = r.spp / job.spp, f"{r.spp}/{job.spp} spp of {what}"
                if r.passes == 0:   # a training material: the blend is already exact
                    job.progress, job.message = 1.0, "exact at a training material: nothing to render"
                job.error = agreement(blend_image, r)
        self._execute(job, passes)

    def _check_current(self, job):
        if self._stopping:
            raise RuntimeError("the server is stopping")
        if job.id != self._latest_refine:
            raise RuntimeError("superseded by a newer refinement")

    @staticmethod
    def _execute(job, work):
        """Run ``work()`` as ``job``: its state, its failure shown on the page, its seconds."""
        job.state, t0 = "rendering", time.perf_counter()
        try:
            work()
            job.state = "done"
        except Exception as e:  # shown on the page; the server keeps running
            job.state, job.message = "failed", f"{type(e).__name__}: {e}"
        finally:
            job.seconds = time.perf_counter() - t0

    def get(self, job_id):
        with self._lock:
            return self._jobs.get(job_id)

    def _run(self, job, basis, scene, manifold_path, blend_image):
        def render():
            job.images = {"blend": blend_image, "reference": self._render(job, basis, scene, manifold_path)}
            job.error = metrics.compare(blend_image, job.images["reference"])
        self._execute(job, render)

    def _render(self, job, basis, scene_path, manifold_path):
        """The reference image of a job, in passes; stops between passes when the server does."""
        import mitsuba as mi

        loaded = load_scene(scene_path, manifold_path, job.spp, scene_resolution(basis.manifest),
                            basis.manifest.max_depth, job.x, basis.manifest.variant, sensor=basis.sensor)
        set_points(loaded.targets, job.x)
        integrator = loaded.integrator.reference(loaded.scene)   # the scene's own, as the basis
        w, h = basis.resolution
        acc, done = None, 0
        for k, spp in enumerate(sample_passes(job.spp, w * h)):
            if self._stopping:
                raise RuntimeError("the server is stopping")
            img = np.array(mi.render(loaded.scene, integrator=integrator, spp=spp, seed=1000 + k,
                                     sensor=basis.sensor),   # the basis's own view
                           dtype=np.float64)[..., :3]
            acc = img * spp if acc is None else acc + img * spp
            done += spp
            job.progress, job.message = done / job.spp, f"{done}/{job.spp} spp"
        return (acc / job.spp).astype(np.float32)

    def busy(self):
        """Whether a job is rendering now."""
        with self._lock:
            return any(j.state == "rendering" for j in self._jobs.values())

    def shutdown(self, wait=0.0):
        """Drop the queued jobs; the running one stops after its current pass. Waits up to
        ``wait`` seconds for it; returns whether no job is rendering any more."""
        self._stopping = True
        self._pool.shutdown(wait=False, cancel_futures=True)
        deadline = time.monotonic() + wait
        while self.busy() and time.monotonic() < deadline:
            time.sleep(0.02)
        return not self.busy()
