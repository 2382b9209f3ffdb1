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
  ``geodesic`` and ``faithful`` in one background thread: they take seconds; of the requests
  waiting there only the newest is computed), cached per pair, steps and kind; returns a
  :class:`concurrent.futures.Future`, shared by every caller asking for the same path;
- :meth:`Walks.progress`: how far a path being computed is (seconds, evaluations of the metric);
- :meth:`Walks.release`: a caller no longer waits for a path (its page moved on or went away);
  a path nobody waits for any more is dropped before it starts, and, released with
  ``stop=True`` (the page's cancel), stopped at its next evaluation of the metric.

The path thread runs at the process's own priority: at a lower one, a busy machine (other
processes) can starve it for minutes. The drags keep their frames' time another way: before each
evaluation of the metric the thread calls ``pause`` (the explorer's: waits, a fraction of a
second at most, while a frame is being made).

The worker thread outlives every request: a path whose future was cancelled, failed or
superseded is skipped or answered with an error, never an exception in the thread.
"""

from __future__ import annotations

import queue
import sys
import threading
import time
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


def metric_columns(dims, stride=paths.SEARCH_STRIDE) -> np.ndarray:
    """Flat indices (into a ``(3 * bins,)`` table row) of the metric's sub-grid bins."""
    return Quadrature.of(tuple(int(d) for d in dims), stride).index


class _Stopped(Exception):
    """The path being computed was cancelled by every page waiting for it."""


class _Watched:
    """The path metric as :func:`~mitsuba_manifold.manifold.paths.path` uses it, each call of
    one of its methods first counted and passed to ``tick`` (progress, pause, cancel).
    """

    def __init__(self, metric, tick) -> None:
        self._metric, self._tick = metric, tick

    def __getattr__(self, name):
        attr = getattr(self._metric, name)
        if name.startswith("_") or not callable(attr):
            return attr

        def watched(*args, **kwargs):
            self._tick()
            return attr(*args, **kwargs)

        return watched


class Walks:
    """Paths and distances of one explorer (see the module doc); ``rows``: the measured tables
    on the metric's sub-grid ``(N, size)``.
    """

    def __init__(self, manifold, rows, pause=None) -> None:
        self.manifold, self._pause = manifold, pause
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
        self._waiters: dict
        self._paths: OrderedDict
        self._paths, self._lock, self._waiters, self._busy = (
            OrderedDict(),
            threading.Lock(),
            {},
            False,
        )
        self._running = (
            None  # [future, started (monotonic), evaluations, stop] of the path computed now
        )
        self._queue: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._work, name="explore-paths", daemon=True)
        self._thread.start()

    def nearest_measured(self, x) -> dict:
        """``{"name", "distance", "spacing"}``: the measured material whose table is nearest to
        the table at ``x`` and the distance (``spacing``: the median nearest-neighbour distance
        between measured materials, for scale).
        """
        f = self.metric.features(np.asarray(x, dtype=np.float64)[None])[0].astype(np.float32)
        d2 = self._measured_sq + float(f @ f) - 2.0 * (self._measured @ f)
        i = int(np.argmin(d2))
        # the nearest one's distance again from the difference (the expanded square above
        # loses the small distances to cancellation: a measured material came out "very close")
        d = np.linalg.norm(self._measured[i].astype(np.float64) - f.astype(np.float64))
        return {
            "name": self.manifold.names[i],
            "distance": float(d),
            "spacing": self.spacing,
        }

    def submit(self, xa, xb, steps=STEPS, kind=paths.DEFAULT_KIND) -> Future:
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

    def release(self, future, stop=False) -> None:
        """One waiter of ``future`` (from :meth:`submit`) no longer needs it: when nobody does,
        a path not yet started is cancelled and dropped from the cache; a running one is kept
        (cached for the next request of that path) unless ``stop`` (the page cancelled it): it
        then stops at its next evaluation of the metric, failing with an InputError.
        """
        with self._lock:
            n = self._waiters.get(future, 0) - 1
            if n > 0:
                self._waiters[future] = n
                return
            self._waiters.pop(future, None)
            if future.cancel():
                self._drop(future)
            elif stop and self._running is not None and self._running[0] is future:
                self._running[3] = True

    def progress(self, future) -> dict | None:
        """``{"seconds", "evaluations"}`` of ``future`` while it is computed, else None."""
        run = self._running
        if run is None or run[0] is not future:
            return None
        return {"seconds": time.monotonic() - run[1], "evaluations": run[2]}

    def _tick(self) -> None:
        """Before each evaluation of the metric in the path thread: count it, let a frame being
        made go first, stop when cancelled.
        """
        run = self._running
        if run is None:
            return
        if run[3]:
            raise _Stopped()
        run[2] += 1
        if self._pause is not None:
            self._pause()

    def waiting(self) -> int:
        """Number of paths queued or computing (for tests and the server's status)."""
        return self._queue.qsize() + int(self._busy)

    def _drop(self, future) -> None:  # with self._lock held
        for k, f in list(self._paths.items()):
            if f is future:
                del self._paths[k]

    def _work(self) -> None:
        """Compute the waiting paths, newest only: one asked for before a newer one started is
        dropped (its future fails; the page asks for the ends it shows). Nothing a request does
        (cancelled, failed, superseded) ends this loop.
        """
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

    def _fail(self, future, error) -> None:
        """Fail a running ``future`` with ``error`` and drop it from the cache (asked again, it
        is computed again).
        """
        with self._lock:
            self._drop(future)
            self._waiters.pop(future, None)
        if not future.done():
            future.set_exception(error)

    def _run(self, future, xa, xb, steps, kind) -> None:
        """Compute one path into ``future`` (already running)."""
        watched = kind != "straight"  # straight: at once, in the caller's thread
        if watched:
            self._running = [future, time.monotonic(), 0, False]
        try:
            metric = _Watched(self.metric, self._tick) if watched else self.metric
            X = paths.path(self.manifold, xa, xb, steps, kind, metric=metric)
            lengths = self.metric.steps(X)
            result = {
                "kind": kind,
                "a": xa.tolist(),
                "b": xb.tolist(),
                "steps": steps,
                "points": X.tolist(),
                "lengths": lengths.tolist(),
            }
        except _Stopped:
            self._fail(future, InputError(f"the {kind} path was cancelled"))
            return
        except Exception as e:  # InputError or a numerical failure: the page falls back to straight
            self._fail(
                future,
                e
                if isinstance(e, InputError)
                else InputError(f"the {kind} path failed ({type(e).__name__}: {str(e)[:120]})"),
            )
            return
        finally:
            if watched:
                self._running = None
        if not future.done():
            future.set_result(result)
