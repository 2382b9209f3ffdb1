"""Fit benchmark: the default layout's optimisers and starts compared, its convergence, its time,
and whether it is a property of the data (paper Sec. 3, "Optimization").

For the database (default ``merl``; ``all`` for the 159) at its resolution, with the default
preset's objective (log features, q = 4, the stress term towards the tables' perceptual
distances): each optimiser from each start is run to its own stop and reported with the
objective ``F = L - lambda (d N / 2) sigma`` it reached, ``L``, its iterations and evaluations,
whether its convergence test was met, the final gradient norm, and its wall and CPU time:

* ``lbfgs-2000 / pca``: L-BFGS-B capped at 2000 iterations from the PCA start (what the
  default fit did before it had a convergence test);
* ``lbfgs / mds``: L-BFGS-B to its gradient test (cap 20000) from the MDS start;
* ``newton / pca``, ``newton / mds-0.5``, ``newton / mds-2``, ``newton / mds`` (the default):
  trust-region Newton (each step solved on a 64-vector Krylov subspace) from the PCA start
  and from the MDS start at scales 0.5, 2 and 1;
* ``newton-128 / mds``: the default with a 128-vector Krylov subspace
  (:attr:`gplvm.NewtonOptions.krylov`);
* ``newton / mds + continuation``: the same from the MDS start through a noise continuation
  (fits at ``mu = 1e-2`` and ``1e-3`` first, :attr:`gplvm.NewtonOptions.continuation`).

Sameness: the default fit again on data that differ in their last bits (``S`` and the
distances times ``1 + 1e-14 e``, :data:`LAST_BITS` draws of ``e``: what another BLAS or another
machine does), and the continuation run on the same draws (``continuation_last_bits_*``;
with the objective each ends at: whether it is the same maximum), on the materials in a random
order, and ``Manifold.fit`` itself on one and two BLAS threads and with the materials
reversed: the largest difference of a latent point from the reference, after mapping names
(no alignment: the pose is canonical). Targets: the default fit converged, of all 159 within
30 s of CPU time, the same points to 1e-3.
"""

import os
import time

import numpy as np

from mitsuba_manifold._util.blas import one_thread
from mitsuba_manifold.data import gram as gram_mod
from mitsuba_manifold.data.database import Database, albedo_weights
from mitsuba_manifold.gp import gplvm
from mitsuba_manifold.manifold.presets import (
    canonical_order,
    fit_layout,
    settings,
    stress_distances,
)

from .common import peak_rss_gib

#: Targets: the default fit's time for the 159 (s) and the sameness of its points.
TARGETS = {"fit_s": 30.0, "same_points": 1e-3}

#: The default run's name in :data:`RUNS`.
DEFAULT_RUN = "newton / mds"
#: The compared run through the noise continuation.
CONTINUATION_RUN = "newton / mds + continuation"
#: Its noise levels.
CONTINUATION = (1e-2, 1e-3)
#: (name, method, start, optimiser options) of the runs compared.
RUNS = (
    ("lbfgs-2000 / pca", "lbfgs", "pca", {"max_iter": 2000}),
    ("lbfgs / mds", "lbfgs", "mds", {}),
    ("newton / pca", "newton", "pca", {}),
    ("newton / mds-0.5", "newton", "mds-0.5", {}),
    ("newton / mds-2", "newton", "mds-2", {}),
    (DEFAULT_RUN, "newton", "mds", {}),
    ("newton-128 / mds", "newton", "mds", {"krylov": 128}),
    (CONTINUATION_RUN, "newton", "mds", {"continuation": CONTINUATION}),
)
#: Draws of last-bit noise the sameness check fits again.
LAST_BITS = 4


def _start(kind, S, D, q):
    if kind == "pca":
        return gplvm.pca_init(S, q)
    scale = float(kind.split("-")[1]) if "-" in kind else 1.0
    return gplvm.mds_init(D, q, scale)


def _one(S, d, D, cfg, order, init=None, **options):
    import warnings

    from mitsuba_manifold.errors import ConvergenceWarning

    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # reported as converged: false
        res = fit_layout(S, d, cfg, init=init, distances=D, order=order, **options)
    return res, time.perf_counter() - t0, time.process_time() - c0


def run(folder="merl", names=None, progress=False, sameness=True, manifold_fits=True, runs=None):  # noqa: PLR0915  one measurement after another, each reported
    """The comparison, the default fit's time and its sameness (module doc); ``manifold_fits``
    False leaves out the three ``Manifold.fit`` runs (each reads and sums every table again);
    ``runs``: the names of :data:`RUNS` to make (default all; the default's is always made).
    """
    from mitsuba_manifold.manifold.model import Manifold

    db = Database(folder, names)
    names = db.names
    t0 = time.perf_counter()
    tables = db.stack(names, progress=progress)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    cfg = settings("default")
    g = gram_mod.gram(
        tables, cfg["features"], centre=True, weights=albedo_weights(db.dims).reshape(-1)
    )
    with one_thread():
        D = stress_distances(tables, db.dims)
    t_gram = time.perf_counter() - t0
    S, d = g.S, tables.shape[1]
    del tables, g
    order = canonical_order(db.hashes(names), names)
    out = {
        "n_materials": len(names),
        "dims": list(db.dims),
        "d": int(d),
        "load_s": t_load,
        "gram_s": t_gram,
        "load_average": os.getloadavg()[0],
        "targets": TARGETS,
        "runs": [],
    }
    q = cfg["q"]
    default = None
    chosen = [r for r in RUNS if runs is None or r[0] in runs or r[0] == DEFAULT_RUN]
    continued = None
    for name, method, start, options in chosen:
        init = _start(start, S[np.ix_(order, order)], D[np.ix_(order, order)], q)
        back = np.empty_like(order)
        back[order] = np.arange(len(order))
        res, wall, cpu = _one(
            S, d, D, settings("default", method=method), order, init[back], **options
        )
        row = {
            "run": name,
            "objective": float(res.history[-1]),
            "log_likelihood": float(res.log_likelihood),
            "stress": float(res.stress),
            "iterations": int(res.n_iterations),
            "evaluations": int(res.n_evaluations),
            "converged": bool(res.converged),
            "grad_norm": float(res.grad_norm),
            "stop": res.message,
            "stages": [[float(mu), int(k)] for mu, k in res.stages or ()],
            "wall_s": wall,
            "cpu_s": cpu,
            "load_average": os.getloadavg()[0],
        }
        out["runs"].append(row)
        if progress:
            print(row, flush=True)
        if name == DEFAULT_RUN:
            default = res
        if name == CONTINUATION_RUN:
            continued = res
    best = max(out["runs"], key=lambda r: r["objective"])
    out["best_run"] = best["run"]
    out["default_run"] = DEFAULT_RUN
    row = next(r for r in out["runs"] if r["run"] == DEFAULT_RUN)
    out["default_converged"] = row["converged"]
    out["default_fit_s"], out["default_fit_cpu_s"] = row["wall_s"], row["cpu_s"]
    out["meets_fit_target"] = row["cpu_s"] < TARGETS["fit_s"]
    if sameness:
        same, objectives = {}, {"default": float(default.history[-1])}
        if continued is not None:
            objectives["continuation"] = float(continued.history[-1])
        rng = np.random.default_rng(0)
        for k in range(LAST_BITS):
            e = rng.standard_normal(S.shape)
            e = e + e.T
            S2, D2 = S * (1 + 1e-14 * e), D * (1 + 1e-14 * np.abs(e))
            res, *_ = _one(S2, d, D2, cfg, order)
            same[f"last_bits_{k}"] = float(np.abs(res.latent - default.latent).max())
            objectives[f"last_bits_{k}"] = float(res.history[-1])
            if continued is not None:  # the same draw through the continuation, not a target
                res, *_ = _one(S2, d, D2, cfg, order, continuation=CONTINUATION)
                out.setdefault("continuation_sameness", {})[f"continuation_last_bits_{k}"] = float(
                    np.abs(res.latent - continued.latent).max()
                )
                objectives[f"continuation_last_bits_{k}"] = float(res.history[-1])
        out["last_bits_objectives"] = objectives
        perm = rng.permutation(len(names))
        res, *_ = _one(
            S[np.ix_(perm, perm)],
            d,
            D[np.ix_(perm, perm)],
            cfg,
            canonical_order([db.hash(names[i]) for i in perm], [names[i] for i in perm]),
        )
        same["material_order"] = float(np.abs(res.latent - default.latent[perm]).max())
        ref = None
        manifolds = (
            ("manifold_2_threads", 2, names),
            ("manifold_1_thread", 1, names),
            ("manifold_reversed", 2, names[::-1]),
        )
        for label, threads, given in manifolds if manifold_fits else ():
            from threadpoolctl import threadpool_limits

            with threadpool_limits(limits=threads, user_api="blas"):
                m = Manifold.fit(db, names=given)
            pts = {n: m.latent[i] for i, n in enumerate(m.names)}
            if ref is None:
                ref = pts
                same["manifold_vs_fit"] = float(
                    max(np.abs(pts[n] - default.latent[i]).max() for i, n in enumerate(names))
                )
                out["manifold_info"] = {
                    k: m.info.get(k) for k in ("converged", "n_iterations", "grad_norm", "stop")
                }
                out["manifold_log_likelihood"] = m.info["log_likelihood"]
            else:
                same[label] = float(max(np.abs(pts[n] - ref[n]).max() for n in ref))
            del m
        out["sameness"] = same
        out["largest_difference"] = max(same.values())
        out["meets_sameness_target"] = out["largest_difference"] < TARGETS["same_points"]
    out["peak_rss_gib"] = peak_rss_gib()
    return out


def report(result: dict) -> str:
    """Markdown section for docs/benchmarks.md: the runs compared, the default's time and sameness."""
    r = result["result"] if "result" in result else result
    db = result.get("database", "merl")
    lines = [
        f"### Fit ({r['n_materials']} materials, {'x'.join(map(str, r['dims']))}, default objective)",
        "",
        f"`tools/bench.py fit --database {db} --json benchmarks/results/"
        f"{'fit' if db == 'merl' else 'fit_' + str(db)}.json`"
        " (times are wall and CPU; CPU time is the figure that does not depend on other work).",
        "",
        "| run | objective F | L | iterations | converged | gradient norm | wall s | CPU s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in r["runs"]:
        mark = " (default)" if row["run"] == r.get("default_run") else ""
        lines.append(
            f"| {row['run']}{mark} | {row['objective']:.6g} | {row['log_likelihood']:.6g} | "
            f"{row['iterations']} | {'yes' if row['converged'] else 'no'} | "
            f"{row['grad_norm']:.2g} | {row['wall_s']:.1f} | {row['cpu_s']:.1f} |"
        )
    lines += [
        "",
        "| figure | value | target | met |",
        "|---|---|---|---|",
        f"| default fit converged | {r['default_converged']} | true | "
        f"{'yes' if r['default_converged'] else 'no'} |",
        f"| default fit CPU time | {r['default_fit_cpu_s']:.1f} s | < {TARGETS['fit_s']:g} s | "
        f"{'yes' if r['meets_fit_target'] else 'no'} |",
    ]
    if "sameness" in r:
        lines.append(
            f"| largest point difference (last bits, order, BLAS threads) | "
            f"{r['largest_difference']:.2g} | < {TARGETS['same_points']:g} | "
            f"{'yes' if r['meets_sameness_target'] else 'no'} |"
        )
    if r.get("continuation_sameness"):
        worst = max(r["continuation_sameness"].values())
        lines.append(
            f"| the same through the noise continuation (last bits only; not the default) | "
            f"{worst:.2g} | < {TARGETS['same_points']:g} | "
            f"{'yes' if worst < TARGETS['same_points'] else 'no'} |"
        )
    if r.get("last_bits_objectives"):
        objs = r["last_bits_objectives"]
        lines += [
            "",
            "Objective F each last-bit fit ends at (the same maximum reads the same F): "
            + ", ".join(f"{k} {v:.6g}" for k, v in objs.items())
            + ".",
        ]
    return "\n".join(lines)
