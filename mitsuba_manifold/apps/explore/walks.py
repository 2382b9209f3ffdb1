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
- :meth:`Walks.submit`: a path ``a -> b`` of a kind (``straight`` at once, ``uniform``,
  ``geodesic`` and ``faithful`` in one low-priority background thread: they take seconds; of the
  requests waiting there only the newest is computed), cached per pair, steps and kind;
  returns a :class:`concurrent.futures.Future`, shared by every caller asking for the same path;
- :meth:`Walks.release`: a caller no longer waits for a path (its page moved on or went away);
  a path nobody waits for any more is dropped before it starts.

The worker thread outlives every request: a path whose future was cancelled, failed or
superseded is skipped or answered with an error, never an exception in the thread.
"""

import os
import queue
import sys
import threading
import traceback
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
    try:  # Linux: a thread's own niceness; drags keep the CPU
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), niceness)
    except (AttributeError, OSError):
        pass


class Walks:
    """Paths and distances of one explorer (see the module doc); ``rows``: the measured tables
    on the metric's sub-grid ``(N, size)``.
    """

    def __init__(self, manifold, rows):
        self.manifold = manifold
        self.metric = paths.PathMetric(manifold, rows=rows)
        measured = self.metric.quad.features(self.metric.rows).astype(np.float32)
        self._measured, self._measured_sq = (
            measured,
            np.einsum("nk,nk->n", measured, measured, dtype=np.float64),
        )
        D = gram_distances([(measured, measured)])
        np.fill_diagonal(D, np.inf)
        #: median distance of a measured material to its nearest measured neighbour (a scale)
        self.spacing = float(np.median(D.min(axis=1))) if manifold.n > 1 else 1.0
        self._paths, self._lock, self._waiters, self._busy = (
            OrderedDict(),
            threading.Lock(),
            {},
            False,
        )
        self._queue = queue.Queue()
        self._thread = threading.Thread(target=self._work, name="explore-paths", daemon=True)
        self._thread.start()

    def nearest_measured(self, x):
        """``{"name", "distance", "spacing"}``: the measured material whose table is nearest to
        the table at ``x`` and the distance (``spacing``: the median nearest-neighbour distance
        between measured materials, for scale).
        """
        f = self.metric.features(np.asarray(x, dtype=np.float64)[None])[0].astype(np.float32)
        d2 = self._measured_sq + float(f @ f) - 2.0 * (self._measured @ f)
        i = int(np.argmin(d2))
        return {
            "name": self.manifold.names[i],
            "distance": float(np.sqrt(max(d2[i], 0.0))),
            "spacing": self.spacing,
        }

    def submit(self, xa, xb, steps=STEPS, kind=paths.DEFAULT_KIND):
        """Future of ``{"kind", "a", "b", "steps", "points", "lengths"}`` for the path from latent
        point ``xa`` to ``xb`` (done at once for ``straight`` and cached paths). Each call counts
        as one waiter until :meth:`release`.
        """
        if kind not in paths.KINDS:
            raise InputError(f"kind must be one of {list(paths.KINDS)}, got {kind!r:.40}")
        xa, xb = (np.asarray(v, dtype=np.float64) for v in (xa, xb))
        if np.array_equal(xa, xb):
            raise InputError("the path's two ends are the same point; choose two different ends")
        key = (xa.tobytes(), xb.tobytes(), int(steps), kind)
        with self._lock:
            future = self._paths.get(key)
            if future is not None and not future.cancelled():
                self._paths.move_to_end(key)
                self._waiters[future] = self._waiters.get(future, 0) + 1
                return future
            future = Future()
            self._paths[key] = future
            self._waiters[future] = 1
            while len(self._paths) > PATHS_KEPT:  # its waiters still get it
                self._paths.popitem(last=False)
        if kind == "straight":
            future.set_running_or_notify_cancel()
            self._run(future, xa, xb, int(steps), kind)
        else:
            self._queue.put((future, xa, xb, int(steps), kind))
        return future

    def release(self, future):
        """One waiter of ``future`` (from :meth:`submit`) no longer needs it: when nobody does,
        a path not yet started is cancelled and dropped from the cache (a running or finished
        one is kept: it is cached for the next request of that path).
        """
        with self._lock:
            n = self._waiters.get(future, 0) - 1
            if n > 0:
                self._waiters[future] = n
                return
            self._waiters.pop(future, None)
            if future.cancel():
                self._drop(future)

    def waiting(self):
        """Number of paths queued or computing (for tests and the server's status)."""
        return self._queue.qsize() + int(self._busy)

    def _drop(self, future):  # with self._lock held
        for k, f in list(self._paths.items()):
            if f is future:
                del self._paths[k]

    def _work(self):
        """Compute the waiting paths, newest only: one asked for before a newer one started is
        dropped (its future fails; the page asks for the ends it shows). Nothing a request does
        (cancelled, failed, superseded) ends this loop.
        """
        _lower_priority()
        while True:
            item = self._queue.get()
            try:
                if not item[0].set_running_or_notify_cancel():  # released by every waiter
                    continue
                if not self._queue.empty():
                    self._fail(
                        item[0], InputError("a newer path was asked for; this one was not computed")
                    )
                    continue
                self._busy = True
                self._run(*item)
            except Exception:  # a bug in one path: reported on the console, the next path runs
                traceback.print_exc(file=sys.stderr)
                self._fail(
                    item[0],
                    InputError("internal error computing the path; see the server's console"),
                )
            finally:
                self._busy = False

    def _fail(self, future, error):
        """Fail a running ``future`` with ``error`` and drop it from the cache (asked again, it
        is computed again).
        """
        with self._lock:
            self._drop(future)
            self._waiters.pop(future, None)
        if not future.done():
            future.set_exception(error)

    def _run(self, future, xa, xb, steps, kind):
        """Compute one path into ``future`` (already running)."""
        try:
            X = paths.path(self.manifold, xa, xb, steps, kind, metric=self.metric)
            lengths = self.metric.steps(X)
            result = {
                "kind": kind,
                "a": xa.tolist(),
                "b": xb.tolist(),
                "steps": steps,
                "points": X.tolist(),
                "lengths": lengths.tolist(),
            }
        except Exception as e:  # InputError or a numerical failure: the page falls back to straight
            self._fail(
                future,
                e
                if isinstance(e, InputError)
                else InputError(f"the {kind} path failed ({type(e).__name__}: {str(e)[:120]})"),
            )
            return
        if not future.done():
            future.set_result(result)
