"""Interpolation benchmark: one full interpolated table (paper Eq. 1), pruned and unpruned."""

import time

import numpy as np

from mitsuba_manifold._util.timing import median_time
from mitsuba_manifold.apps import gi_comparison as comparison
from mitsuba_manifold.manifold.model import Manifold

from .common import peak_rss_gib


def run(folder, manifold=None, q=2, repeats=7, prunes=(1e-3, 1e-2, 3e-2, 1e-1)):
    """Time of one full interpolated table, unpruned and pruned, with the tables in memory.

    Targets: under 0.1 s unpruned, under 20 ms pruned. The physical limit for the
    unpruned table is reading all N float32 tables once at memory bandwidth: measured here
    as NumPy's read of the stack (a sum) and copy of a quarter of it (read and write), the
    limits ``tables_gib / read bandwidth`` for float32 tables and half that for float16
    (:func:`bandwidth`). CPU times (``*_cpu_s``) beside the wall times say how much of a
    wall time on a loaded machine was waiting for a core. Pruning
    (``Manifold.prune``) is measured at several levels, with the materials it keeps and
    the error it makes (relative to the table's maximum and in albedo).
    """
    m = Manifold.load(manifold) if manifold else Manifold.fit(folder, q=q)
    t0 = time.perf_counter()
    tables = m.tables(folder if manifold else None)
    t_load = time.perf_counter() - t0
    # the midpoint of two latent neighbours (as the GI benchmark), a typical interpolation query
    a, b = comparison.gi_pair(m)
    x = 0.5 * (m.latent[m.index(a)] + m.latent[m.index(b)])
    _, w = m.weights(x)
    t_weights, _ = median_time(lambda: m.weights(x), repeats)
    t_full, cpu_full = timed(lambda: m.combine(w, prune=0.0), repeats)
    bw = bandwidth(tables, repeats)
    full = m.combine(w, prune=0.0)[0]
    scale = float(np.abs(full).max())
    from mitsuba_manifold.data.database import albedo_weights

    q_w = albedo_weights(full.shape[1:]).reshape(-1)
    albedo_full = full.reshape(3, -1) @ q_w
    pruned = []
    for prune in prunes:
        keep, _, dropped = m.prune(w, prune)
        t_p, cpu_p = timed(lambda: m.combine(w, prune=prune), repeats)
        table = m.combine(w, prune=prune)[0]
        pruned.append(
            {
                "prune": prune,
                "time_s": t_p,
                "cpu_s": cpu_p,
                "materials_kept": int(len(keep)),
                "dropped_weight": dropped,
                "l2_error_relative": float(np.linalg.norm(table - full) / np.linalg.norm(full)),
                "max_error_relative_to_max": float(np.abs(table - full).max() / scale),
                "albedo_error": float(np.abs(table.reshape(3, -1) @ q_w - albedo_full).max()),
                "meets_pruned_target": t_p < 0.02,
            }
        )
    return {
        "n_materials": m.n,
        "table_values": int(tables.shape[1]),
        "tables_gib": tables.nbytes / 2**30,
        "x": x.tolist(),
        "x_is": f"midpoint of {a} and {b}",
        "load_tables_s": t_load,
        "weights_s": t_weights,
        "unpruned_s": t_full,
        "unpruned_cpu_s": cpu_full,
        "unpruned_target_s": 0.1,
        "meets_unpruned_target": t_full < 0.1,
        "unpruned_bandwidth_gib_s": tables.nbytes / 2**30 / t_full,
        **bw,
        "pruned": pruned,
        "pruned_target_s": 0.02,
        "peak_rss_gib": peak_rss_gib(),
    }


def timed(fn, repeats):
    """Median wall time and median process CPU time (all threads) of ``repeats`` calls of ``fn()``."""
    walls, cpus = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)
    return float(np.median(walls)), float(np.median(cpus))


def bandwidth(tables, repeats):
    """Memory bandwidth NumPy reaches on ``tables`` (N, d) and the unpruned table's limits from it.

    ``read``: a sum over the whole stack (one read, nothing written); ``copy``: a copy of a
    quarter of it (read and write, counted twice). The limits are the stack's size (float32)
    and half of it (float16) over the best read bandwidth measured.
    """
    gib = tables.nbytes / 2**30
    t_read = min(timed(lambda: np.add.reduce(tables, axis=None), 1)[0] for _ in range(repeats))
    part = tables[: max(1, len(tables) // 4)]
    dst = np.empty_like(part)
    t_copy = min(timed(lambda: np.copyto(dst, part), 1)[0] for _ in range(repeats))
    read = gib / t_read
    return {
        "read_bandwidth_gib_s": read,
        "copy_bandwidth_gib_s": 2 * part.nbytes / 2**30 / t_copy,
        "limit_float32_s": gib / read,
        "limit_float16_s": gib / 2 / read,
    }
