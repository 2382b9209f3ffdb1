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
    unpruned table is reading all N float32 tables once at memory bandwidth. Pruning
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
    t_full, _ = median_time(lambda: m.combine(w, prune=0.0), repeats)
    full = m.combine(w, prune=0.0)[0]
    scale = float(np.abs(full).max())
    from mitsuba_manifold.data.database import albedo_weights

    q_w = albedo_weights(full.shape[1:]).reshape(-1)
    albedo_full = full.reshape(3, -1) @ q_w
    pruned = []
    for prune in prunes:
        keep, _, dropped = m.prune(w, prune)
        t_p, _ = median_time(lambda: m.combine(w, prune=prune), repeats)
        table = m.combine(w, prune=prune)[0]
        pruned.append(
            {
                "prune": prune,
                "time_s": t_p,
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
        "unpruned_target_s": 0.1,
        "meets_unpruned_target": t_full < 0.1,
        "unpruned_bandwidth_gib_s": tables.nbytes / 2**30 / t_full,
        "pruned": pruned,
        "pruned_target_s": 0.02,
        "peak_rss_gib": peak_rss_gib(),
    }
