"""Speed of the perceptual paths: seconds per path and for the latent graph, cold and cached.

What the explorer's path scrubber and ``blend.py --path`` wait for (:mod:`manifold.paths`):

* ``cold``: a process that has the tables in memory (just fitted) and no disk cache: the
  metric's rows picked from the tables (``rows_s``) and the graph's edges weighed
  (``graph_s``);
* ``cached``: a fresh process (the manifold loaded from its file, the tables not read):
  the metric's rows and the graph's edges read from the database's cache folder
  (``rows_s``, ``graph_s``), then the first path of the default kind (``first_path_s``:
  what a user waits for after starting the explorer);
* ``path_s``: seconds per path of each kind (median, max; ``cpu_median``: the process's CPU
  seconds, which a loaded machine does not stretch as it does the wall time) over the
  paper's three pairs and ten pairs of latent neighbours (:func:`fig9.pair_sets`'s tuned
  pairs), the graph built.

Targets (the explorer's): graph <= 5 s once cached, a path of the default kind
(:data:`~mitsuba_manifold.manifold.paths.DEFAULT_KIND`) <= 1 s median; the geodesic's median is
reported against the same second.
"""

from __future__ import annotations

import os
import tempfile
import time

import numpy as np

from mitsuba_manifold.manifold import latent_graph, paths
from mitsuba_manifold.manifold.model import Manifold

from . import fig9

TARGETS = {"graph_cached_s": 5.0, "default_median_s": 1.0, "geodesic_median_s": 1.0}


def _timed(f):
    t0 = time.perf_counter()
    value = f()
    return value, time.perf_counter() - t0


def cold(m):
    """Rows and graph of ``m`` (tables in memory) built without reading or writing the disk cache."""
    metric, rows_s = _timed(lambda: paths.PathMetric(m, paths.SEARCH_STRIDE, tables=m.tables()))
    graph, graph_s = _timed(lambda: latent_graph.LatentGraph.build(metric, cache=False))
    return {
        "rows_s": rows_s,
        "graph_s": graph_s,
        "graph_nodes": int(len(graph.nodes)),
        "graph_edges": int(graph.graph.nnz // 2),
        "search_values": int(metric.quad.size),
    }


def cached(file, pair):
    """A fresh load of the manifold ``file``: rows and graph from the cache, then one path of the
    default kind for ``pair``.
    """
    m = Manifold.load(file)
    metric, rows_s = _timed(lambda: paths.PathMetric.of(m))
    _, graph_s = _timed(metric.graph)
    _, first_s = _timed(lambda: paths.path(m, *pair, fig9.STEPS, paths.DEFAULT_KIND, metric=metric))
    return {
        "rows_s": rows_s,
        "graph_s": graph_s,
        "first_path_s": first_s,
        "first_path_kind": paths.DEFAULT_KIND,
        "tables_read": m._tables is not None,
    }


def run(folder, names=None, preset="default", kinds=paths.KINDS, progress=True):
    """Path speeds on the manifold of ``preset`` fitted to the database ``folder`` (module doc)."""
    m, fit_s = _timed(lambda: Manifold.fit(folder, names=names, preset=preset))
    out = {
        "preset": preset,
        "n_materials": m.n,
        "dims": list(m.info["dims"]),
        "fit_s": fit_s,
        "search_stride": list(paths.SEARCH_STRIDE),
        "targets": TARGETS,
        "cold": cold(m),
    }
    metric = paths.PathMetric.of(m)
    metric.graph()  # writes the caches the fresh load reads
    sets = fig9.pair_sets(m)
    pairs = sets["paper"] + sets["neighbours"]
    with tempfile.TemporaryDirectory() as tmp:
        file = os.path.join(tmp, "manifold.npz")
        m.save(file)
        out["cached"] = cached(file, pairs[0])
    out["path_s"] = {}
    for kind in kinds:
        times, cpus = [], []
        for a, b in pairs:
            c0 = time.process_time()
            times.append(_timed(lambda: paths.path(m, a, b, fig9.STEPS, kind, metric=metric))[1])
            cpus.append(time.process_time() - c0)
        out["path_s"][kind] = {
            "median": float(np.median(times)),
            "max": float(np.max(times)),
            "cpu_median": float(np.median(cpus)),
            "n": len(times),
        }
        if progress:
            print(
                f"  {kind:>9s}: {np.median(times):.3f} s a path (max {np.max(times):.3f})",
                flush=True,
            )
    out["default_kind"] = paths.DEFAULT_KIND
    out["meets"] = {
        "graph_cached_s": out["cached"]["graph_s"] <= TARGETS["graph_cached_s"],
        "default_median_s": out["path_s"].get(paths.DEFAULT_KIND, {"median": np.inf})["median"]
        <= TARGETS["default_median_s"],
        "geodesic_median_s": out["path_s"].get("geodesic", {"median": np.inf})["median"]
        <= TARGETS["geodesic_median_s"],
    }
    return out
