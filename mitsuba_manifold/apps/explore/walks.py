"""The explorer's perceptual side: paths of :func:`Manifold.path` kinds and the distance to
the nearest measured material (the metric of :mod:`mitsuba_manifold.data.distance`).

Both need the :class:`~mitsuba_manifold.manifold.paths.PathMetric` of the manifold, whose
rows are the tables at the bins of its search sub-grid (:data:`~.paths.SEARCH_STRIDE`).
:class:`~.material.TableStack` keeps exactly those columns of every measured table (read
with the preview tables and cached beside them), so ``PathMetric(manifold, rows=...)`` is the
same metric without the full table stack in memory (1.7 GB for 100 MERL tables).

:class:`Walks` answers:

- :meth:`Walks.nearest_measured`: the measured table nearest to the table at ``x`` under the
  metric (the distance the paths are even in), a few ms: one product over the sub-grid
  columns and a Gram product with the measured tables' features, computed once;
- :meth:`Walks.submit`: a path ``a -> b`` of a kind (``straight`` at once, ``uniform`` and
  ``geodesic`` in one low-priority background thread: the geodesic takes seconds; of the
  requests waiting there only the newest is computed), cached per pair, steps and kind;
  returns a :class:`concurrent.futures.Future`.
"""

import os
import queue
import threading
from collections import OrderedDict
from concurrent.futures import Future

import numpy as np

from ...data.distance import Quadrature, gram_distances
from ...errors import InputError
from ...manifold import paths

#: Paths kept (per pair of ends, steps and kind).
PATHS_KEPT = 32
#: Default points of a path sent to the page (the scrubber interpolates between them).
STEPS = 21
MAX_STEPS = 201


def metric_columns(dims, stride=paths.SEARCH_STRIDE):
    """Flat indices (into a ``(3 * bins,)`` table row) of the metric's sub-grid bins."""
    return Quadrature.of(tuple(int(d) for d in dims), stride).index


def _lower_priority(niceness=10):
    try:   # Linux: a thread's own niceness; drags keep the CPU
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), niceness)
    except (AttributeError, OSError):
        pass


class Walks:
    """Paths and distances of one explorer (see the module doc); ``rows``: the measured tables
    on the metric's sub-grid ``(N, size)``."""

    def __init__(self, manifold, rows):
        self.manifold = manifold
        self.metric = paths.PathMetric(manifold, rows=rows)
        measured = self.metric.quad.features(self.metric.rows).astype(np.float32)
        self._measured, self._measured_sq = measured, np.einsum("nk,nk->n", measured, measured, dtype=np.float64)
        D = gram_distances([(measured, measured)])
        np.fill_diagonal(D, np.inf)
        #: median distance of a measured material to its nearest measured neighbour (a scale)
        self.spacing = float(np.median(D.min(axis=1))) if manifold.n > 1 else 1.0
        self._paths, self._lock = OrderedDict(), threading.Lock()
        self._queue = queue.Queue()
        self._thread = threading.Thread(target=self._work, name="explore-paths", daemon=True)
        self._thread.start()

    def nearest_measured(self, x):
        """``{"name", "distance", "spacing"}``: the measured material whose table is nearest to
        the table at ``x`` and the distance (``spacing``: the median nearest-neighbour distance
        between measured materials, for scale)."""
        f = self.metric.features(np.asarray(x, dtype=np.float64)[None])[0].astype(np.float32)
        d2 = self._measured_sq + float(f @ f) - 2.0 * (self._measured @ f)
        i = int(np.argmin(d2))
        return {"name": self.manifold.names[i], "distance": float(np.sqrt(max(d2[i], 0.0))),
                "spacing": self.spacing}

    def submit(self, xa, xb, steps=STEPS, kind=paths.DEFAULT_KIND):
        """Future of ``{"kind", "a", "b", "steps", "points", "lengths"}`` for the path from latent
        point ``xa`` to ``xb`` (done at once for ``straight`` and cached paths)."""
        if kind not in paths.KINDS:
            raise InputError(f"kind must be one of {list(paths.KINDS)}, got {kind!r:.40}")
        xa, xb = (np.asarray(v, dtype=np.float64) for v in (xa, xb))
        if np.array_equal(xa, xb):
            raise InputError("the path's two ends are the same point; choose two different ends")
        key = (xa.tobytes(), xb.tobytes(), int(steps), kind)
        with self._lock:
            if key in self._paths:
                self._paths.move_to_end(key)
                return self._paths[key]
            future = Future()
            self._paths[key] = future
            while len(self._paths) > PATHS_KEPT:
                self._paths.popitem(last=False)
        if kind == "straight":
            self._run(future, xa, xb, int(steps), kind)
        else:
            self._queue.put((future, xa, xb, int(steps), kind))
        return future

    def _work(self):
        """Compute the waiting paths, newest only: one asked for before a newer one started is
        dropped (its future fails; the page asks for the ends it shows)."""
        _lower_priority()
        while True:
            item = self._queue.get()
            if not self._queue.empty():
                self._forget(item[0], InputError("a newer path was asked for; this one was not computed"))
                continue
            self._run(*item)

    def _forget(self, future, error):
        with self._lock:
            for k, f in list(self._paths.items()):
                if f is future:
                    del self._paths[k]
        future.set_exception(error)

    def _run(self, future, xa, xb, steps, kind):
        try:
            X = paths.path(self.manifold, xa, xb, steps, kind, metric=self.metric)
            lengths = self.metric.steps(X)
            future.set_result({"kind": kind, "a": xa.tolist(), "b": xb.tolist(), "steps": steps,
                               "points": X.tolist(), "lengths": lengths.tolist()})
        except Exception as e:   # InputError or a numerical failure: the page falls back to straight
            self._forget(future, e if isinstance(e, InputError) else
                         InputError(f"the {kind} path failed ({type(e).__name__}: {str(e)[:120]})"))
