"""Full-GI reference renders of a latent point, in the background, with progress.

The blend (Eq. 13) holds the paths that touch the material at most once (L1-); a render
with ``manifold_brdf`` and Mitsuba's ``path`` integrator holds every path. A job renders
the basis's scene at ``x`` in passes of a few samples (different seeds, averaged) so the
page can show its progress, then measures the blend against it
(:func:`mitsuba_manifold.imaging.metrics.compare`). One job renders at a time (the renders share
the CPU with the blends); the others wait in line.
"""

import itertools
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ...imaging import metrics
from ...render.scenes import render_reference

PASSES = 8
MAX_SPP = 1 << 14
KEEP_JOBS = 16


@dataclass
class Job:
    id: str
    basis: str
    x: list
    spp: int
    state: str = "queued"          # queued, rendering, done, failed
    progress: float = 0.0
    message: str = ""
    started: float = field(default_factory=time.time)
    seconds: float = 0.0
    images: dict = field(default_factory=dict)   # name -> linear float32 (H, W, 3)
    error: dict = None

    def status(self):
        return {"id": self.id, "basis": self.basis, "x": self.x, "spp": self.spp, "state": self.state,
                "progress": self.progress, "message": self.message, "seconds": self.seconds,
                "error": self.error, "images": sorted(self.images)}


class References:
    """Queue of reference jobs (one worker thread)."""

    def __init__(self):
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="explore-reference")
        self._jobs = {}
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._stopping = False

    def submit(self, name, basis, scene, manifold_path, x, spp, blend_image):
        """Start a job; returns it. ``blend_image``: the blend at ``x`` to compare with."""
        job = Job(id=f"r{next(self._ids)}", basis=name, x=[float(v) for v in x], spp=int(spp))
        with self._lock:
            self._jobs[job.id] = job
            for old in list(self._jobs)[:-KEEP_JOBS]:
                if self._jobs[old].state in ("done", "failed"):
                    del self._jobs[old]
        self._pool.submit(self._run, job, basis, scene, manifold_path, blend_image)
        return job

    def get(self, job_id):
        with self._lock:
            return self._jobs.get(job_id)

    def _run(self, job, basis, scene, manifold_path, blend_image):
        job.state, t0 = "rendering", time.perf_counter()
        try:
            passes = min(PASSES, job.spp)
            per = [job.spp // passes + (1 if k < job.spp % passes else 0) for k in range(passes)]
            acc, done = None, 0
            for k, spp in enumerate(per):
                if self._stopping:
                    raise RuntimeError("the server is stopping")
                img = render_reference(scene, manifold_path, job.x, spp, seed=1000 + k,
                                          resolution=tuple(basis.resolution),
                                          max_depth=basis.manifest["max_depth"], variant=basis.manifest["variant"])
                acc = img * spp if acc is None else acc + img * spp
                done += spp
                job.progress = done / job.spp
                job.message = f"{done}/{job.spp} spp"
            ref = (acc / job.spp).astype(np.float32)
            job.images = {"blend": blend_image, "reference": ref}
            job.error = metrics.compare(blend_image, ref)
            job.state = "done"
        except Exception as e:  # shown on the page; the server keeps running
            job.state, job.message = "failed", f"{type(e).__name__}: {e}"
        finally:
            job.seconds = time.perf_counter() - t0

    def shutdown(self):
        """Drop the queued jobs; the running one stops after its current pass."""
        self._stopping = True
        self._pool.shutdown(wait=False, cancel_futures=True)
