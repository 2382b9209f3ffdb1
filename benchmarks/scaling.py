"""Scaling benchmark: how each stage's time and peak memory grow with the number of
materials N, the table resolution, the image resolution and the samples per pixel, and
(``chunks``) what chunked basis rendering gains from 1 to 2 Ray workers.

Every point runs in its own subprocess (``python -m benchmarks.scaling STAGE
JSON``), so that its peak RSS (``ru_maxrss``) is that stage's alone, Python and Mitsuba
imports included (a floor of a few hundred MB). Stages: ``tabulate`` (tables of the built-in
set ``SOURCE``, evaluated from its networks and exported as MERL files), ``gram`` (loading
the float32 tables and the Gram matrix, log features), ``fit`` (Hooke-Jeeves and L-BFGS
from the PCA start, q = 2), ``interp`` (one unpruned interpolated table: the weighted sum of the N tables in memory, as
``Manifold.combine``), ``plugin`` (constructing one ``manifold_brdf`` at a new latent point,
after a warm-up construction), ``basis`` (a one-pass basis of ``table.xml``, after a 1-spp
warm-up render in the same process) and ``blend`` (one blend of that basis, images in memory).

N beyond 100 uses noisy copies of the 100 materials of ``SOURCE`` (multiplicative log-normal
noise of sigma 0.1, seeds 1, 2, ..., names suffixed ``~<seed>``) at a reduced table
resolution (22 x 22 x 45 bins: 1000 full-resolution tables would be 17.5 GB of float32
and 35 GB as MERL files). Exponents are least-squares slopes of log(time) and
log(peak RSS above the import floor) against log(size) over the points of each series.
"""

import json
import os
import subprocess
import sys
import time

import numpy as np

SMALL_DIMS = (22, 22, 45)
FULL_DIMS = (90, 90, 180)
NOISE = 0.1
#: The built-in set the series tabulate (the 100 measured MERL materials).
SOURCE = "merl"


# ------------------------------------------------------------------ one point (subprocess)


def _names(folder, n):
    from mitsuba_manifold.data.database import Database

    names = Database(folder).names
    if n > len(names):
        raise ValueError(f"{folder} holds {len(names)} tables, {n} asked")
    return names[:n]


def _point(stage, p):
    """Measure one point in this process; returns ``{"time_s": ..., ...}`` (RSS added by main)."""
    from mitsuba_manifold._util.timing import median_time
    from mitsuba_manifold.data import database
    from mitsuba_manifold.data.database import Database

    if stage == "tabulate":
        names = Database(SOURCE).names[: p["n"]]
        t0 = time.perf_counter()
        database.write_database(
            p["out"], (SOURCE,), tuple(p["dims"]), materials=names, export=True, force=True
        )
        return {"time_s": time.perf_counter() - t0}
    if stage == "gram":
        db = Database(p["db"], _names(p["db"], p["n"]))
        t0 = time.perf_counter()
        tables = db.stack()
        t_load = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, S = db.gram(tables=tables, features="log")
        np.save(p["gram_out"], S)
        return {"time_s": time.perf_counter() - t0, "load_s": t_load, "d": int(tables.shape[1])}
    if stage == "fit":
        from mitsuba_manifold.gp import gplvm

        S = np.load(p["gram"])
        d = 3 * int(np.prod(p["dims"]))
        init = gplvm.pca_init(S, 2)
        res = gplvm.fit_latent(S, d, q=2, method=p["method"], init=init)
        return {
            "time_s": res.time_s,
            "evaluations": int(res.n_evaluations),
            "final_L": float(res.log_likelihood),
        }
    if (
        stage == "manifold"
    ):  # for the later stages, whose cost does not depend on how well the fit converged
        from mitsuba_manifold.manifold.model import Manifold

        m = Manifold.fit(
            p["db"], q=2, names=_names(p["db"], p["n"]), features="log", max_iter=p["max_iter"]
        )
        m.save(p["save"])
        return {"time_s": m.info["time_fit_s"]}
    if stage == "interp":
        db = Database(p["db"], _names(p["db"], p["n"]))
        tables = db.stack()
        w = np.random.default_rng(0).normal(size=p["n"])
        w += (1 - w.sum()) / p["n"]
        t, _ = median_time(lambda: w.astype(np.float32) @ tables, 3)
        return {"time_s": t, "table_bytes": int(tables.nbytes // p["n"])}
    from mitsuba_manifold.render.scene.scenes import use_variant

    mi = use_variant()
    if stage == "plugin":
        from mitsuba_manifold.manifold.model import Manifold

        m = Manifold.load(p["manifold"])
        mi.load_dict(
            {"type": "manifold_brdf", "manifold": p["manifold"], "material": m.names[0]}
        )  # warm-up
        # a point never asked before, so that no cached mixture or sampling table is found
        x = m.latent[:2].mean(axis=0) + np.random.default_rng().normal(scale=1e-3, size=m.q)
        x = ", ".join(str(float(v)) for v in x)
        t0 = time.perf_counter()
        bsdf = mi.load_dict({"type": "manifold_brdf", "manifold": p["manifold"], "x": x})
        return {"time_s": time.perf_counter() - t0, "bsdf": str(type(bsdf).__name__)}
    if stage == "basis":
        import shutil
        import tempfile

        from mitsuba_manifold.manifold.model import Manifold
        from mitsuba_manifold.render.jobs.render_basis import render_basis
        from mitsuba_manifold.render.scene.scenes import scene_path

        Manifold.load(
            p["manifold"]
        ).open_database().material_rows()  # the interleaved cache, built once
        with tempfile.TemporaryDirectory() as tmp:  # warm-up: scene loading, kernel compilation
            render_basis(
                scene_path("table"), p["manifold"], tmp, spp=1, mode="onepass", resolution=p["res"]
            )
        shutil.rmtree(p["out"], ignore_errors=True)
        t0 = time.perf_counter()
        render_basis(
            scene_path("table"),
            p["manifold"],
            p["out"],
            spp=p["spp"],
            mode="onepass",
            resolution=p["res"],
        )
        return {"time_s": time.perf_counter() - t0}
    if stage == "blend":
        from mitsuba_manifold.basis.blend import blend
        from mitsuba_manifold.basis.folder import Basis
        from mitsuba_manifold.manifold.model import Manifold

        m = Manifold.load(p["manifold"])
        b = Basis.load(p["basis"], manifold=m)
        x = m.latent[:2].mean(axis=0)
        blend(b, m, x=x, prune=0.0)  # reads the images once
        t, _ = median_time(lambda: blend(b, m, x=x, prune=0.0), 5)
        return {"time_s": t}
    raise ValueError(f"unknown stage {stage!r}")


def _main_point(argv):
    import resource

    stage, params = argv[0], json.loads(argv[1])
    out = _point(stage, params)
    peak = max(
        resource.getrusage(who).ru_maxrss
        for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
    )
    out["peak_rss_gib"] = peak / 2**20  # children: the tabulation's worker processes (largest one)
    print("RESULT " + json.dumps(out), flush=True)


def measure(stage, params, timeout=300):
    """Run one point in a subprocess; its measurements, or ``{"error": ...}``."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    try:
        r = subprocess.run(
            [sys.executable, "-m", "benchmarks.scaling", stage, json.dumps(params)],
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
        )
    except subprocess.TimeoutExpired:
        return {"error": f"over {timeout} s", "wall_s": time.perf_counter() - t0}
    line = [ln for ln in r.stdout.splitlines() if ln.startswith("RESULT ")]
    if r.returncode or not line:
        return {
            "error": (r.stderr.strip().splitlines() or ["no output"])[-1],
            "wall_s": time.perf_counter() - t0,
        }
    out = json.loads(line[-1][7:])
    out["wall_s"] = time.perf_counter() - t0
    return out


# ------------------------------------------------------------------ the series


def _noisy_database(work, n_total, dims, progress):
    """A folder of ``n_total`` tables: the materials of ``SOURCE``, then noisy copies (seeds 1,
    2, ...: each stored value times exp(``NOISE`` * a standard normal draw of that seed and
    material)).
    """
    import zlib

    from mitsuba_manifold.data import database, merl

    folder = os.path.join(work, f"db_{n_total}_{'x'.join(map(str, dims))}")
    names = database.Database(SOURCE).names
    copies = -(-n_total // len(names))
    t0 = time.perf_counter()
    os.makedirs(folder, exist_ok=True)
    exported = [os.path.join(folder, f"{name}.binary") for name in names]
    if not all(os.path.exists(f) for f in exported):
        database.write_database(folder, (SOURCE,), dims, materials=names, export=True, force=True)
    for seed in range(1, copies):
        for name, source in zip(names, exported):
            target = os.path.join(folder, f"{name}~{seed}.binary")
            if os.path.exists(target):
                continue
            rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
            raw = merl.read_binary(source)
            noisy = raw * np.exp(NOISE * rng.standard_normal(raw.shape))
            merl.write_binary(target, np.where(raw < 0, raw, noisy))
    if progress:
        print(
            f"  {copies * len(names)} tables at {dims} in {time.perf_counter() - t0:.1f} s",
            flush=True,
        )
    return folder, time.perf_counter() - t0, copies * len(names)


def exponent(xs, ys, floor=0.0):
    """Least-squares slope of log(y - floor) against log(x) (None with fewer than 2 usable points)."""
    pts = [(x, y - floor) for x, y in zip(xs, ys) if y is not None and y - floor > 0]
    if len(pts) < 2:
        return None
    lx, ly = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(lx, ly, 1)[0])


def _series(name, axis, values, stage, make_params, progress, timeout=300):
    rows = []
    for v in values:
        r = measure(stage, make_params(v), timeout)
        r[axis] = v
        rows.append(r)
        if progress:
            err = f" ({r['error']})" if "error" in r else ""
            print(
                f"  {name} {axis}={v}: {r.get('time_s', float('nan')):.3g} s, "
                f"peak {r.get('peak_rss_gib', float('nan')):.2f} GiB{err}",
                flush=True,
            )
    return {"stage": stage, "axis": axis, "rows": rows}


def run(
    folder=None,
    out=None,
    ns=(10, 30, 100, 300, 1000),
    dims_list=((11, 11, 22), SMALL_DIMS, (45, 45, 90), FULL_DIMS),
    res_list=(32, 64, 128, 256),
    spp_list=(4, 16, 64, 256),
    n_images=30,
    progress=True,
    chunks=True,
):
    """All series (see the module docstring); returns rows, exponents and the estimated walls."""
    work = out or os.path.join(os.getcwd(), "scaling_work")
    os.makedirs(work, exist_ok=True)
    t_start = time.perf_counter()
    report = {"work": work, "small_dims": list(SMALL_DIMS), "noise_copies": NOISE, "series": {}}
    S = report["series"]
    n_max = max(ns)

    # databases: N up to n_max at SMALL_DIMS (noisy copies beyond 100); 20 materials per resolution
    big, t_big, _ = _noisy_database(work, n_max, SMALL_DIMS, progress)
    S["tabulate_vs_dims"] = _series(
        "tabulate",
        "dims",
        [list(d) for d in dims_list],
        "tabulate",
        lambda d: {"out": os.path.join(work, f"tab_{'x'.join(map(str, d))}"), "dims": d, "n": 10},
        progress,
    )
    S["tabulate_vs_n"] = _series(
        "tabulate",
        "n",
        [10, 30, 100],
        "tabulate",
        lambda n: {"out": os.path.join(work, f"tabn_{n}"), "dims": SMALL_DIMS, "n": n},
        progress,
    )
    gram = lambda n: os.path.join(work, f"gram_{n}.npy")  # noqa: E731
    S["gram_vs_n"] = _series(
        "gram", "n", list(ns), "gram", lambda n: {"db": big, "n": n, "gram_out": gram(n)}, progress
    )
    dim_db = {tuple(d): os.path.join(work, f"tab_{'x'.join(map(str, d))}") for d in dims_list}
    S["gram_vs_dims"] = _series(
        "gram",
        "dims",
        [list(d) for d in dims_list],
        "gram",
        lambda d: {
            "db": dim_db[tuple(d)],
            "n": 10,
            "gram_out": os.path.join(work, "gram_dims.npy"),
        },
        progress,
    )
    manifold = lambda n: os.path.join(work, f"manifold_{n}.npz")  # noqa: E731
    for method in ("hooke-jeeves", "lbfgs"):
        S[f"fit_{method}_vs_n"] = _series(
            f"fit {method}",
            "n",
            list(ns),
            "fit",
            lambda n: {"gram": gram(n), "dims": SMALL_DIMS, "method": method},
            progress,
            timeout=150,
        )
    for n in (
        ns
    ):  # Hooke-Jeeves capped at 20 sweeps, the PCA start beyond 300 (20 sweeps took over 400 s at
        # 1000); the plugin, basis and blend costs do not depend on how far the fit went
        measure(
            "manifold",
            {"db": big, "n": n, "max_iter": 20 if n <= 300 else 0, "save": manifold(n)},
            timeout=300,
        )
    S["interp_vs_n"] = _series(
        "interp", "n", list(ns), "interp", lambda n: {"db": big, "n": n}, progress
    )
    S["interp_vs_dims"] = _series(
        "interp",
        "dims",
        [list(d) for d in dims_list],
        "interp",
        lambda d: {"db": dim_db[tuple(d)], "n": 10},
        progress,
    )
    have = [n for n in ns if os.path.exists(manifold(n))]
    S["plugin_vs_n"] = _series(
        "plugin", "n", have, "plugin", lambda n: {"manifold": manifold(n)}, progress
    )
    basis_dir = lambda n, r, s: os.path.join(work, f"basis_{n}_{r}_{s}")  # noqa: E731
    S["basis_vs_n"] = _series(
        "basis",
        "n",
        have,
        "basis",
        lambda n: {"manifold": manifold(n), "out": basis_dir(n, 64, 16), "res": 64, "spp": 16},
        progress,
    )
    n_img = max([n for n in have if n <= n_images] or have[:1])
    S["basis_vs_res"] = _series(
        "basis",
        "res",
        list(res_list),
        "basis",
        lambda r: {
            "manifold": manifold(n_img),
            "out": basis_dir(n_img, r, 16),
            "res": r,
            "spp": 16,
        },
        progress,
    )
    S["basis_vs_spp"] = _series(
        "basis",
        "spp",
        list(spp_list),
        "basis",
        lambda s: {
            "manifold": manifold(n_img),
            "out": basis_dir(n_img, 64, s),
            "res": 64,
            "spp": s,
        },
        progress,
    )
    S["blend_vs_n"] = _series(
        "blend",
        "n",
        have,
        "blend",
        lambda n: {"manifold": manifold(n), "basis": basis_dir(n, 64, 16)},
        progress,
    )
    S["blend_vs_res"] = _series(
        "blend",
        "res",
        list(res_list),
        "blend",
        lambda r: {"manifold": manifold(n_img), "basis": basis_dir(n_img, r, 16)},
        progress,
    )
    report["database_for_n_s"] = t_big
    report["n_images_series"] = n_img
    if chunks and have:
        report["chunks"] = chunk_speedup(manifold(n_img), work, progress=progress)
    report["summary"] = summarise(report)
    report["wall_s"] = time.perf_counter() - t_start
    return report


def _size(axis, v):
    return int(np.prod(v)) if axis == "dims" else (v * v if axis == "res" else v)


def summarise(report):
    """Exponents per series and the first wall on this machine's memory."""
    floor = min(
        (
            r["peak_rss_gib"]
            for s in report["series"].values()
            for r in s["rows"]
            if "peak_rss_gib" in r
        ),
        default=0.0,
    )
    out = {
        "rss_floor_gib": floor,
        "exponents": {},
        "note": (
            "exponents: d log(time) / d log(size) and d log(peak RSS - floor) / d log(size); size = N, "
            "bins (dims), pixels (res) or spp"
        ),
    }
    for key, s in report["series"].items():
        ok = [r for r in s["rows"] if "time_s" in r]
        xs = [_size(s["axis"], r[s["axis"]]) for r in ok]
        out["exponents"][key] = {
            "time": exponent(xs, [r["time_s"] for r in ok]),
            "memory": exponent(xs, [r["peak_rss_gib"] for r in ok], floor * 0.98),
            "points": len(ok),
            "failed": [r[s["axis"]] for r in s["rows"] if "error" in r],
        }
    # memory wall: the float32 tables in memory (Gram, interp) at full resolution
    table_gib = 3 * np.prod(FULL_DIMS) * 4 / 2**30
    mem = 24.0
    out["walls"] = {
        "tables_in_memory_full_res_n": int((mem - floor) / table_gib),
        "how": (
            f"the Gram and an unpruned interpolated table hold all N float32 tables ({table_gib * 1024:.1f} MiB "
            f"each at 90x90x180) in memory; 24 GiB less the {floor:.2f} GiB floor holds that many"
        ),
    }
    for method in (
        "hooke-jeeves",
        "lbfgs",
    ):  # time wall: 600 s, from the local exponent of the last two points
        rows = report["series"].get(f"fit_{method}_vs_n", {}).get("rows", [])
        done = [r for r in rows if "time_s" in r]
        failed = [r["n"] for r in rows if "error" in r]
        if failed:  # over the point's time limit there
            out["walls"][f"fit_{method}_over_time_limit_at_n"] = min(failed)
        if len(done) >= 2 and not (failed and min(failed) <= done[-1]["n"] * 3):
            (a, b) = done[-2:]
            e = exponent([a["n"], b["n"]], [a["time_s"], b["time_s"]])
            if e and e > 0:
                out["walls"][f"fit_{method}_600s_n"] = int(
                    b["n"] * (600.0 / b["time_s"]) ** (1.0 / e)
                )
                out["walls"][f"fit_{method}_local_exponent"] = e
    return out


def plot(report, path):
    """Log-log curves: time and peak RSS against N, and time against bins, pixels and spp."""
    from mitsuba_manifold.imaging.plots import finish, subplots

    fig, axes = subplots(1, 3, figsize=(16, 4.6))
    series = report["series"]
    expo = report["summary"]["exponents"]
    for key, s in series.items():
        ok = [r for r in s["rows"] if "time_s" in r]
        if not ok:
            continue
        xs = [_size(s["axis"], r[s["axis"]]) for r in ok]
        e = expo.get(key, {}).get("time")
        label = f"{key.replace('_vs_' + s['axis'], '')} ({'~' + format(e, '.2f') if e else '-'})"
        if s["axis"] == "n":
            axes[0].loglog(xs, [r["time_s"] for r in ok], "o-", label=label)
            axes[1].loglog(
                xs, [r["peak_rss_gib"] for r in ok], "o-", label=key.replace("_vs_n", "")
            )
        else:
            axes[2].loglog(xs, [r["time_s"] for r in ok], "o-", label=f"{label} vs {s['axis']}")
    axes[0].set(xlabel="materials N", ylabel="time (s)", title="time vs N (exponent)")
    axes[1].set(xlabel="materials N", ylabel="peak RSS (GiB, own process)", title="memory vs N")
    axes[2].set(
        xlabel="bins / pixels / spp",
        ylabel="time (s)",
        title="time vs table bins, image pixels, spp",
    )
    return finish(fig, axes, path)


# ------------------------------------------------------------------ chunks on Ray


def chunk_speedup(manifold, work, res=128, spp=256, chunks=4, progress=True):
    """One basis in ``chunks`` chunks: local executor, Ray with 1 worker, Ray with 2 workers.

    Cluster start-up is timed apart (``start_s``); ``wall_s`` is rendering and merging.
    Returns the per-chunk times and the estimate for a 16-node cluster: a warm chunk
    costs ``a + b spp`` (fitted from the fastest chunk at ``spp / chunks`` and one chunk
    at ``spp``, both in a warm process), each process pays once ``startup`` (its first
    chunk's extra time: scene loading, kernel compilation), so
    ``T_16(S) = startup + a + b S / 16 + merge`` against ``startup + a + b S`` on one node.
    """
    import shutil

    from mitsuba_manifold.render.jobs.chunks import render_chunked
    from mitsuba_manifold.render.jobs.executor import LocalExecutor, RayExecutor
    from mitsuba_manifold.render.scene.scenes import scene_path

    scene = scene_path("table")
    out = {"resolution": res, "spp": spp, "chunks": chunks, "manifold": manifold, "runs": {}}
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {"env_vars": {"PYTHONPATH": root + os.pathsep + os.environ.get("PYTHONPATH", "")}}
    for label, ex_fn in (
        ("local_1_process", lambda: LocalExecutor()),
        ("ray_1_worker", lambda: RayExecutor(num_cpus=1, runtime_env=env)),
        ("ray_2_workers", lambda: RayExecutor(num_cpus=2, runtime_env=env)),
    ):
        folder = os.path.join(work, f"chunks_{label}")
        shutil.rmtree(folder, ignore_errors=True)
        t0 = time.perf_counter()
        ex = ex_fn()
        if hasattr(ex, "start"):
            ex.start()
        start = time.perf_counter() - t0
        t0 = time.perf_counter()
        try:
            run = render_chunked(
                scene,
                manifold,
                folder,
                spp=spp,
                chunks=chunks,
                executor=ex,
                mode="onepass",
                resolution=res,
            )
        finally:
            ex.close()
        wall = time.perf_counter() - t0
        out["runs"][label] = {
            "start_s": start,
            "wall_s": wall,
            "merge_s": run.merge_s,
            "chunk_s": [r[1] for r in run.rendered],
            "pids": sorted({r[3] for r in run.rendered}),
        }
        if progress:
            print(
                f"  chunks {label}: start {start:.1f} s, {wall:.1f} s (chunks "
                f"{[round(r[1], 1) for r in run.rendered]})",
                flush=True,
            )
    one = os.path.join(work, "chunks_one")
    shutil.rmtree(one, ignore_errors=True)
    single = render_chunked(scene, manifold, one, spp=spp, chunks=1, mode="onepass", resolution=res)
    local = out["runs"]["local_1_process"]["chunk_s"]
    warm, c_big = min(local), single.rendered[0][1]
    startup = max(local) - warm
    b = max((c_big - warm) / (spp - spp / chunks), 0.0)
    a = max(warm - b * spp / chunks, 0.0)
    merge = out["runs"]["local_1_process"]["merge_s"]
    big_s = 4096
    one_node, sixteen = startup + a + b * big_s, startup + a + b * big_s / 16 + merge
    out["speedup_1_to_2_workers"] = (
        out["runs"]["ray_1_worker"]["wall_s"] / out["runs"]["ray_2_workers"]["wall_s"]
    )
    out["chunk_model"] = {
        "startup_s": startup,
        "fixed_s": a,
        "s_per_spp": b,
        "one_chunk_at_spp_s": c_big,
        "warm_chunk_at_spp_over_k_s": warm,
    }
    out["cluster_16_estimate"] = {
        "spp": big_s,
        "resolution": res,
        "one_node_s": one_node,
        "sixteen_nodes_s": sixteen,
        "speedup": one_node / sixteen,
        "how": (
            "16 nodes render 16 chunks of S/16 spp at once, each paying its start-up, then the driver merges "
            "(merge time as measured here; moving the images over a network not included)"
        ),
    }
    return out


if __name__ == "__main__":
    _main_point(sys.argv[1:])
