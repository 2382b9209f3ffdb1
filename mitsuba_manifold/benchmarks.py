"""Benchmarks behind ``tools/bench.py``: each returns a JSON-ready dict of measurements.

Timings are wall-clock medians over repeats on the machine that runs them; ``machine()``
records which one. Targets are reported beside the numbers (``*_target`` and ``meets_*``
fields), never asserted.
"""

import os
import platform
import resource
import time

import numpy as np

from . import gplvm
from .database import Database
from .manifold import Manifold


def machine():
    """Where a benchmark ran."""
    info = {"platform": platform.platform(), "python": platform.python_version(),
            "cpus": os.cpu_count(), "processor": platform.processor() or platform.machine()}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
        with open("/proc/meminfo") as f:
            info["mem_total_gib"] = round(int(f.readline().split()[1]) / 2 ** 20, 1)
    except OSError:
        pass
    return info


def peak_rss_gib():
    """Peak resident memory of this process so far."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


def _median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), times


def bench_fit(folder, qs=(2, 5), names=None, progress=False):
    """Gram and optimisation times, final L for Hooke-Jeeves and L-BFGS from the same start.

    Targets: optimisation under 5 s for N = 100, q = 5; Gram under 5 s once the tables
    are in memory. The paper fits all of MERL in 122 s on one core.
    """
    db = Database(folder, names)
    t0 = time.perf_counter()
    tables = db.stack(progress=progress)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    _, S = db.gram(tables=tables)
    t_gram = time.perf_counter() - t0
    d = tables.shape[1]
    out = {"n_materials": len(db.names), "dims": list(db.dims), "d": int(d), "load_s": t_load,
           "gram_s": t_gram, "gram_target_s": 5.0, "meets_gram_target": t_gram < 5.0, "runs": []}
    for q in qs:
        init = gplvm.pca_init(S, q)
        for method in ("hooke-jeeves", "lbfgs"):
            res = gplvm.fit_latent(S, d, q=q, method=method, init=init)
            K = gplvm.kernel_matrix(res.latent)
            run = {"q": q, "method": method, "optimisation_s": res.time_s,
                   "initial_L": float(res.history[0]) if len(res.history) else None,
                   "final_L": float(res.log_likelihood), "iterations": len(res.history) - 1,
                   "evaluations": int(res.n_evaluations), "cond_K": float(np.linalg.cond(K))}
            if method == "hooke-jeeves" and q == 5:
                run["target_s"] = 5.0
                run["meets_target"] = res.time_s < 5.0
            out["runs"].append(run)
    out["peak_rss_gib"] = peak_rss_gib()
    return out


def bench_interp(folder, manifold=None, q=2, repeats=7, prunes=(1e-3, 1e-2, 3e-2, 1e-1)):
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
    a, b = _gi_pair(m)
    x = 0.5 * (m.latent[m.index(a)] + m.latent[m.index(b)])
    _, w = m.weights(x)
    t_weights, _ = _median_time(lambda: m.weights(x), repeats)
    t_full, _ = _median_time(lambda: m.combine(w, prune=0.0), repeats)
    full = m.combine(w, prune=0.0)[0]
    scale = float(np.abs(full).max())
    from .database import albedo_weights
    q_w = albedo_weights(full.shape[1:]).reshape(-1)
    albedo_full = full.reshape(3, -1) @ q_w
    pruned = []
    for prune in prunes:
        keep, _, dropped = m.prune(w, prune)
        t_p, _ = _median_time(lambda: m.combine(w, prune=prune), repeats)
        table = m.combine(w, prune=prune)[0]
        pruned.append({"prune": prune, "time_s": t_p, "materials_kept": int(len(keep)), "dropped_weight": dropped,
                       "l2_error_relative": float(np.linalg.norm(table - full) / np.linalg.norm(full)),
                       "max_error_relative_to_max": float(np.abs(table - full).max() / scale),
                       "albedo_error": float(np.abs(table.reshape(3, -1) @ q_w - albedo_full).max()),
                       "meets_pruned_target": t_p < 0.02})
    return {"n_materials": m.n, "table_values": int(tables.shape[1]), "tables_gib": tables.nbytes / 2 ** 30,
            "x": x.tolist(), "x_is": f"midpoint of {a} and {b}",
            "load_tables_s": t_load, "weights_s": t_weights,
            "unpruned_s": t_full, "unpruned_target_s": 0.1, "meets_unpruned_target": t_full < 0.1,
            "unpruned_bandwidth_gib_s": tables.nbytes / 2 ** 30 / t_full,
            "pruned": pruned, "pruned_target_s": 0.02, "peak_rss_gib": peak_rss_gib()}


def pca_errors(S, table_norms, components):
    """Relative reconstruction error of each training table with k principal components.

    The error of material i with k components is ``sqrt(sum_{j>k} lambda_j U_ij^2) / |t_i|``
    where ``S = U diag(lambda) U^T`` (the Gram matrix of the mean-subtracted tables) and
    ``t_i`` is the raw table; computed from the Gram matrix alone.
    """
    lam, U = np.linalg.eigh(S)
    order = np.argsort(lam)[::-1]
    lam, U = np.maximum(lam[order], 0), U[:, order]
    energy = U ** 2 * lam[None, :]
    errors = {}
    for k in components:
        errors[k] = np.sqrt(energy[:, k:].sum(axis=1)) / table_norms
    return errors


def bench_pca(folder, components=(5, 20, 40, 60), q=2, names=None, focus="color-changing-paint3"):
    """PCA reconstruction error of the training tables against the manifold's exact reproduction (Fig. 8)."""
    db = Database(folder, names)
    tables = db.stack()
    _, S = db.gram(tables=tables)
    norms = np.linalg.norm(tables.astype(np.float64), axis=1)
    errs = pca_errors(S, norms, [k for k in components if k < len(db.names)])
    m = Manifold.fit(db, q=q)
    m._tables = tables
    manifold_err = np.array([np.linalg.norm(m.interpolate(m.latent[i], prune=0.0)[0].reshape(-1)
                                            - tables[i]) / norms[i] for i in range(m.n)])
    out = {"n_materials": len(db.names), "dims": list(db.dims), "pca": {}, "manifold_q": q,
           "manifold_max_relative_error": float(manifold_err.max())}
    fi = db.names.index(focus) if focus in db.names else None
    for k, e in errs.items():
        out["pca"][str(k)] = {"mean": float(e.mean()), "median": float(np.median(e)), "max": float(e.max()),
                              "worst_material": db.names[int(e.argmax())]}
        if fi is not None:
            out["pca"][str(k)][focus] = float(e[fi])
    return out


def _queries(m, n_random=64, seed=0):
    """Typical query points: midpoints of each point's nearest pair and random points in the box."""
    d2 = ((m.latent[:, None] - m.latent[None]) ** 2).sum(-1) + np.eye(m.n) * 1e300
    mids = 0.5 * (m.latent + m.latent[d2.argmin(axis=1)])
    lo, hi = m.latent.min(0), m.latent.max(0)
    rng = np.random.default_rng(seed)
    return np.vstack([mids, rng.uniform(lo, hi, (n_random, m.q))])


def _weights_row(m, label, queries):
    row = {"case": label, "cond_K": m.condition_number(), "jump_at_training_points": m.discontinuity()}
    _, w = m.weights(queries)
    row.update({"max_abs_w": float(np.abs(w).max()), "max_sum_abs_w": float(np.abs(w).sum(1).max()),
                "max_sum_error": float(np.abs(w.sum(1) - 1).max()), "finite": bool(np.isfinite(w).all())})
    row["bounded"] = row["finite"] and row["max_sum_abs_w"] < 1e3
    return row


def bench_stability(folder, manifold=None, q=2, grid=48):
    """One table over stiff and extreme cases: does everything stay finite and bounded?

    Uses the latent points of a fitted manifold and varies the hyperparameters around them
    (``l`` from 1e-3 to 1e3, ``mu`` from 1e-10 to 1e-2), near-duplicate and far-away points,
    negative-weight blends (clamped bins, albedo outside [0, 1]), float32 against float64.
    """
    from .manifold import ManifoldError
    base = Manifold.load(manifold) if manifold else Manifold.fit(folder, q=q)
    tables = base.tables(folder if manifold else None)
    queries = _queries(base)
    rows = []

    def variant(latent, l, mu):
        return Manifold(base.names, latent, base.database, base.hashes, l, mu, base.features, base.albedos)

    for l in (1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0, 1e3):
        try:
            rows.append(_weights_row(variant(base.latent, l, base.noise), f"l={l:g}, mu={base.noise:g}", queries))
        except ManifoldError as e:
            rows.append({"case": f"l={l:g}", "error": str(e), "finite": True, "bounded": False})
    for mu in (1e-10, 1e-8, 1e-6, 1e-4, 1e-2):
        try:
            rows.append(_weights_row(variant(base.latent, base.length_scale, mu), f"l=1, mu={mu:g}", queries))
        except ManifoldError as e:
            rows.append({"case": f"mu={mu:g}", "error": str(e), "finite": True, "bounded": False})
    for eps in (1e-2, 1e-4, 1e-6, 1e-8):
        latent = base.latent.copy()
        latent[1] = latent[0] + eps
        try:
            m = variant(latent, base.length_scale, base.noise)
            row = _weights_row(m, f"near duplicate points, distance {eps:g}", np.vstack([queries, latent[:2].mean(0)]))
        except ManifoldError as e:
            row = {"case": f"near duplicate {eps:g}", "error": str(e), "finite": True, "bounded": False}
        rows.append(row)
    for dist in (1e3, 1e6, 1e12):
        x = base.latent.mean(0) + dist / np.sqrt(base.q)
        table, _, _ = base.interpolate(x, prune=0.0)
        mean = base.mean()
        rows.append({"case": f"far point at distance {dist:g}", "finite": bool(np.isfinite(table).all()),
                     "max_relative_difference_to_mean": float(np.abs(table - mean).max() / np.abs(mean).max()),
                     "bounded": bool(np.isfinite(table).all())})

    # negative-weight blends over a latent grid: clamped bins and albedo outside [0, 1]
    from .plots import albedo_grid
    _, _, alb = albedo_grid(base, resolution=grid)
    lo, hi = base.latent.min(0), base.latent.max(0)
    pts = np.random.default_rng(1).uniform(lo - 0.25 * (hi - lo), hi + 0.25 * (hi - lo), (24, base.q))
    _, W = base.weights(pts)
    neg_fraction = []
    for w in W:
        t, _, _ = base.combine(w, prune=0.0)
        neg_fraction.append(float((t < 0).mean()))
    rows.append({"case": "negative-weight blends (24 random points, box + 25%)",
                 "fraction_points_with_negative_weights": float((W < 0).any(1).mean()),
                 "mean_fraction_bins_clamped": float(np.mean(neg_fraction)),
                 "max_fraction_bins_clamped": float(np.max(neg_fraction)),
                 "albedo_map_outside_0_1": float(((alb < 0) | (alb > 1)).mean()),
                 "albedo_map_min": float(alb.min()), "albedo_map_max": float(alb.max()),
                 "finite": True, "bounded": True})

    # float32 accumulation (what the package does) against float64
    _, w = base.weights(queries[0])
    t32 = w.astype(np.float32) @ tables
    t64 = w @ tables.astype(np.float64)
    scale = np.abs(t64).max()
    rows.append({"case": "float32 vs float64 interpolated table", "max_abs_error_relative_to_max":
                 float(np.abs(t32 - t64).max() / scale), "finite": True, "bounded": True})
    return {"n_materials": base.n, "q": base.q, "rows": rows,
            "all_finite": all(r.get("finite", False) for r in rows)}


# ------------------------------------------------------------------- rendering

SCENES = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scenes")


def _mitsuba(variant=None):
    import mitsuba as mi

    import mitsuba_manifold
    from .basis import default_variant
    variant = variant or default_variant()
    if mi.variant() != variant:
        mi.set_variant(variant)
    mitsuba_manifold.register()
    return mi


def _sphere_with(bsdf_xml, spp, res, manifold=None):
    """``scenes/sphere.xml`` with its material block replaced by ``bsdf_xml``."""
    import re

    mi = _mitsuba()
    with open(os.path.join(SCENES, "sphere.xml")) as f:
        text = f.read()
    text = re.sub(r'<bsdf type="manifold_brdf" id="material">.*?</bsdf>', bsdf_xml, text, flags=re.S)
    mi.Thread.thread().file_resolver().prepend(SCENES)
    params = {"spp": str(spp), "res": str(res)}
    if manifold is not None:
        params["manifold"] = os.path.abspath(manifold)
    return mi.load_string(text, **params)


def _time_renders(scenes, repeats):
    """Interleaved timings (seconds) of ``mi.render`` per named scene, after a warm-up render."""
    import drjit as dr
    import mitsuba as mi
    times = {k: [] for k in scenes}
    for s in scenes.values():
        dr.eval(mi.render(s, seed=1000))
    for rep in range(repeats):
        for k, s in scenes.items():
            t0 = time.perf_counter()
            img = mi.render(s, seed=rep)
            dr.eval(img)
            dr.sync_thread()
            times[k].append(time.perf_counter() - t0)
    return {k: {"min_s": float(np.min(v)), "median_s": float(np.median(v))} for k, v in times.items()}


def _interpolated_point(m, a="chrome", b="gold-paint"):
    if a in m.names and b in m.names:
        return 0.5 * (m.latent[m.index(a)] + m.latent[m.index(b)]), f"midpoint of {a} and {b}"
    return 0.5 * (m.latent[0] + m.latent[1]), f"midpoint of {m.names[0]} and {m.names[1]}"


def bench_bsdf(folder, manifold=None, spp=64, res=256, repeats=7, mse_res=96, mse_spp=32, ref_spp=2048,
               materials=("chrome", "steel", "gold-metallic-paint", "red-fabric")):
    """manifold_brdf against roughconductor, cdf against cosine sampling, construction time.

    Targets: render time at most 1.5x roughconductor at equal spp; relative MSE at least
    5x lower with ``cdf`` than with ``cosine`` for the spiky metals.
    """
    from . import metrics
    from .bsdf import sampling_cache_path
    mi = _mitsuba()
    m = Manifold.load(manifold) if manifold else None
    if m is None:
        manifold = os.path.join(folder, ".manifold-cache", "bench_q2.npz")
        m = Manifold.fit(folder, q=2)
        m.save(manifold)
    x, where = _interpolated_point(m)
    xs = ", ".join(repr(float(v)) for v in x)
    out = {"variant": mi.variant(), "x": x.tolist(), "x_is": where, "n_materials": m.n}

    # construction of an interpolated material, with and without the sampling cache
    db = m.open_database()
    keep, _, _ = m.prune(m.weights(x)[1])
    for i in keep:
        path = sampling_cache_path(db, m.names[i])
        if os.path.exists(path):
            os.remove(path)
    spec = {"type": "manifold_brdf", "manifold": os.path.abspath(manifold), "x": xs}
    t0 = time.perf_counter()
    mi.load_dict(spec)
    out["construct_without_cache_s"] = time.perf_counter() - t0
    out["construct_with_cache_s"] = _median_time(lambda: mi.load_dict(spec), 3)[0]
    out["construct_materials_used"] = int(len(keep))
    out["table_dims"] = list(db.dims)

    # render time against roughconductor
    scenes = {
        "manifold_brdf": _sphere_with(f'<bsdf type="manifold_brdf" id="material"><string name="manifold" '
                                      f'value="$manifold"/><string name="x" value="{xs}"/></bsdf>',
                                      spp, res, manifold),
        "roughconductor": _sphere_with('<bsdf type="roughconductor" id="material"><string name="material" '
                                       'value="Cr"/><float name="alpha" value="0.05"/></bsdf>', spp, res)}
    t = _time_renders(scenes, repeats)
    ratio = t["manifold_brdf"]["min_s"] / t["roughconductor"]["min_s"]
    out["render"] = {"spp": spp, "resolution": res, "times": t, "ratio_min": ratio,
                     "ratio_median": t["manifold_brdf"]["median_s"] / t["roughconductor"]["median_s"],
                     "ratio_target": 1.5, "meets_target": ratio <= 1.5}

    # relative MSE at equal spp, cdf against cosine
    rows = []
    for name in materials:
        if name not in m.names:
            continue
        sc = {mode: _sphere_with(f'<bsdf type="manifold_brdf" id="material"><string name="manifold" '
                                 f'value="$manifold"/><string name="material" value="{name}"/>'
                                 f'<string name="sampling" value="{mode}"/></bsdf>', mse_spp, mse_res, manifold)
              for mode in ("cdf", "cosine")}
        ref = np.mean([np.array(mi.render(sc["cdf"], spp=ref_spp // 4, seed=100 + k)) for k in range(4)], axis=0)
        err = {mode: float(np.mean([metrics.rel_mse(np.array(mi.render(sc[mode], seed=k)), ref) for k in range(4)]))
               for mode in sc}
        spiky = name in ("chrome", "steel")
        rows.append({"material": name, "rel_mse_cdf": err["cdf"], "rel_mse_cosine": err["cosine"],
                     "cosine_over_cdf": err["cosine"] / err["cdf"],
                     **({"target_ratio": 5.0, "meets_target": err["cosine"] / err["cdf"] >= 5.0} if spiky else {})})
    out["sampling"] = {"spp": mse_spp, "resolution": mse_res, "reference_spp": ref_spp, "rows": rows}
    return out


def _gi_pair(m, max_clamped=1e-3, min_share=0.6):
    """Two latent neighbours to interpolate between, for the GI comparison and the path sheet.

    Among the pairs (material, its nearest latent neighbour) whose midpoint is a genuine
    interpolation of the two (their weights there sum to at least ``min_share``) and whose
    midpoint table needs (almost) no clamping, the one whose albedos differ most, so that
    the interpolation is visible. Far-apart pairs cross other materials' regions, where an
    affine combination with large weights of both signs goes negative in many bins; the
    plugin clamps those but a blend cannot, so such a midpoint measures clamping rather
    than Eq. 13.
    """
    d2 = ((m.latent[:, None] - m.latent[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    pairs = sorted({tuple(sorted((i, int(j)))) for i, j in enumerate(d2.argmin(axis=1))})
    alb = m.albedos.mean(axis=1) if m.albedos is not None else np.zeros(m.n)
    best, best_score = pairs[0], -1.0
    for i, j in sorted(pairs, key=lambda p: -abs(alb[p[0]] - alb[p[1]])):
        x = 0.5 * (m.latent[i] + m.latent[j])
        _, w = m.weights(x)
        if w[i] + w[j] >= min_share and m.negative_fraction(x) <= max_clamped:
            best = (i, j)
            break
    i, j = best
    return m.names[i], m.names[j]


def _gi_points(m, a, b):
    """Training point, midpoint and extrapolated point on the latent segment from a to b."""
    xa, xb = m.latent[m.index(a)], m.latent[m.index(b)]
    return [("training", f"{a}", xa), ("midpoint", f"midpoint {a}-{b}", 0.5 * (xa + xb)),
            ("extrapolated", f"{a} + 1.5 ({b} - {a})", xa + 1.5 * (xb - xa))]


def _bias(a, ref):
    """Mean relative difference of two images and its standard error (pixels independent)."""
    d = (a - ref).reshape(-1, 3).astype(np.float64).mean(axis=1)
    scale = float(np.mean(ref))
    return float(d.mean() / scale), float(d.std() / np.sqrt(d.size) / scale)


def bench_gi(folder, manifold=None, scenes=("sphere", "table"), res=128, basis_spp=64, ref_spp=4096,
             direct_spp=(1, 4, 16, 64, 256, 1024), mode="onepass", out=None, seed=0, save_images=False,
             progress=False, plot=None):
    """Error against run time: the blend (Eq. 13) beside re-rendering the interpolated material.

    For each scene and latent point (training, midpoint, extrapolated): the blend's time and
    error against a high-spp full-GI reference (``path``), and the error and time of direct
    renders at increasing spp. On a convex scene L2+ is zero and the blend is unbiased; on
    a concave one the bias (L2+) is measured. Writes a log-log plot (``plot``, default in
    ``out``); with
    ``save_images`` also the blends, references and error images (EXR and PNG) and the
    contact sheet of the latent path between the two materials (paper Fig. 12).
    """
    from . import imageio
    from . import basis as basis_mod
    from . import blend as blend_mod
    from . import metrics
    mi = _mitsuba()
    if manifold is None:
        manifold = os.path.join(folder, ".manifold-cache", "bench_q2.npz")
        Manifold.fit(folder, q=2).save(manifold)
    m = Manifold.load(manifold)
    out = out or os.path.join(folder, ".manifold-cache", "bench_gi")
    os.makedirs(out, exist_ok=True)
    pair = _gi_pair(m)
    report = {"resolution": res, "basis_spp": basis_spp, "reference_spp": ref_spp, "mode": mode,
              "variant": mi.variant(), "pair": list(pair), "scenes": {}}
    for name in scenes:
        scene_path = os.path.join(SCENES, name + ".xml")
        folder_b = os.path.join(out, f"basis_{name}_{res}_{basis_spp}_{mode}")
        if os.path.isdir(folder_b):  # time a whole basis, not a resumed one
            import shutil
            shutil.rmtree(folder_b)
        t0 = time.perf_counter()
        basis_mod.render_basis(scene_path, manifold, folder_b, spp=basis_spp, mode=mode, resolution=res, seed=seed,
                               progress=progress)
        t_basis = time.perf_counter() - t0
        b = blend_mod.Basis.load(folder_b, manifold=m)
        rows = []
        for kind, label, x in _gi_points(m, *pair):
            ref = blend_mod.render_reference(scene_path, manifold, x, ref_spp, seed=seed + 7919, resolution=(res, res))
            img, info = blend_mod.blend(b, m, x=x)
            t_blend = _median_time(lambda: blend_mod.blend(b, m, x=x), 5)[0]
            bias, bias_se = _bias(img, ref)
            row = {"point": kind, "x_is": label, "x": np.asarray(x).tolist(),
                   "clamped_fraction": m.negative_fraction(x),
                   "blend": {"time_s": t_blend, **metrics.compare(img, ref), "relative_bias": bias,
                             "relative_bias_se": bias_se, "materials_used": int(info["n_images"])},
                   "direct": []}
            for spp in direct_spp:
                t0 = time.perf_counter()
                direct = blend_mod.render_reference(scene_path, manifold, x, spp, seed=seed + spp,
                                                    resolution=(res, res))
                row["direct"].append({"spp": spp, "time_s": time.perf_counter() - t0, **metrics.compare(direct, ref)})
            rows.append(row)
            if save_images:
                stem = os.path.join(out, f"{name}_{kind}")
                for suffix, image in (("blend", img), ("reference", ref)):
                    imageio.write_exr(f"{stem}_{suffix}.exr", image)
                    imageio.write_png(f"{stem}_{suffix}.png", image)
                metrics.write_error_png(f"{stem}_error.png", img, ref)
            if progress:
                print(f"  {name}: {kind} done (blend rel. MSE {row['blend']['rel_mse']:.3g})", flush=True)
        if save_images:
            images, _, _ = blend_mod.blend_path(b, m, *pair, steps=20)
            blend_mod.write_contact_sheet(os.path.join(out, f"{name}_path_sheet.png"), images,
                                          labels=[f"{t:.2f}" for t in np.linspace(0, 1, len(images))])
        report["scenes"][name] = {"basis_time_s": t_basis, "basis_images": len(b.keys) + 1, "points": rows}
    report["plot"] = _plot_gi(report, plot or os.path.join(out, "gi_error_vs_time.png"))
    return report


def _plot_gi(report, path):
    from .plots import _figure, _save
    plt = _figure()
    names = list(report["scenes"])
    fig, axes = plt.subplots(1, len(names), figsize=(6 * len(names), 4.5), squeeze=False)
    for ax, name in zip(axes[0], names):
        sc = report["scenes"][name]
        for k, row in enumerate(sc["points"]):
            colour = f"C{k}"
            d = row["direct"]
            ax.loglog([r["time_s"] for r in d], [r["rel_mse"] for r in d], "o-", color=colour,
                      label=f"direct render, {row['point']}")
            ax.loglog([row["blend"]["time_s"]], [row["blend"]["rel_mse"]], "*", ms=14, color=colour,
                      label=f"blend, {row['point']}")
        ax.set_title(f"{name}.xml: basis rendered once in {sc['basis_time_s']:.0f} s "
                     f"({report['basis_spp']} spp)", fontsize=9)
        ax.set_xlabel("time per image (s)")
        ax.set_ylabel(f"relative MSE vs {report['reference_spp']} spp full GI")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


# ------------------------------------------------------------------- basis (issue 5)

def _basis_run(scene_path, manifold, folder, spp, mode, res, seed):
    """One basis rendered from scratch by the real tool (``render_basis``).

    Returns the wall time (scene loading, rendering, writing every EXR and the manifest)
    and the render time (the sum of the manifest's per-image times: the renders only).
    """
    import shutil

    from . import basis as basis_mod
    shutil.rmtree(folder, ignore_errors=True)
    t0 = time.perf_counter()
    manifest = basis_mod.render_basis(scene_path, manifold, folder, spp=spp, mode=mode, resolution=res, seed=seed)
    wall = time.perf_counter() - t0
    return {"spp": int(spp), "wall_s": wall, "render_s": float(sum(e["time_s"] for e in manifest["images"].values())),
            "images": len(manifest["images"])}


def _l1_reference(scene_path, manifold, x, spp, seed, res):
    """The L1- image of latent point ``x`` (what a blend estimates), rendered directly."""
    import mitsuba as mi

    from . import blend as blend_mod
    scene, _, max_depth = blend_mod.load_scene(scene_path, manifold, spp, (res, res), x=x)
    integ = mi.load_dict({"type": "manifold_path", "component": "l1", "max_depth": int(max_depth)})
    return np.array(mi.render(scene, integrator=integ, spp=int(spp), seed=int(seed)), dtype=np.float32)[..., :3]


def bench_basis(folder, manifold=None, scene="table", res=256, spp=64, ref_spp=4096, repeats=3, out=None, seed=0):
    """One-pass basis rendering (issue 5) against one render per material, and the blends' error.

    Both modes run through :func:`basis.render_basis` on ``scenes/<scene>.xml`` with every
    material of the manifold, at ``res`` x ``res`` and ``spp`` samples per pixel; one-pass
    runs are interleaved with single-material renders (``touch`` and ``path``) and
    repeated (minimum reported); the per-material mode runs once. Targets: one-pass at
    least 10x faster than per-material, and under 3x one single-material render.

    Then, at equal total basis time: the one-pass mode gets the spp that makes its wall
    time that of the per-material mode (fitted from its times at ``spp`` and ``4 spp``,
    rounded down to whole passes of ``spp``), and both blends at the midpoint of
    :func:`_gi_pair` are compared with a full-GI reference (``path``, ``ref_spp``) and with
    the L1- reference (``manifold_path``, ``component=l1``, ``ref_spp``), which is what a
    blend estimates without bias.
    """
    import shutil

    import drjit as dr

    from . import blend as blend_mod
    from . import metrics
    from .integrators import _PACKET
    mi = _mitsuba()
    if manifold is None:
        manifold = os.path.join(folder, ".manifold-cache", "bench_q2.npz")
        Manifold.fit(folder, q=2).save(manifold)
    m = Manifold.load(manifold)
    scene_path = os.path.join(SCENES, scene + ".xml")
    out = out or os.path.join(folder, ".manifold-cache", "bench_basis")
    os.makedirs(out, exist_ok=True)
    report = {"scene": scene + ".xml", "resolution": res, "spp": spp, "n_materials": m.n, "variant": mi.variant(),
              "threads": dr.thread_count()}

    # The interleaved tables one-pass rendering reads (built once per set of materials).
    db = m.open_database()
    t0 = time.perf_counter()
    rows = db.material_rows(m.names, pad=_PACKET)
    report["tables_cache"] = {"s": time.perf_counter() - t0, "bytes": int(rows.nbytes),
                              "note": "Database.material_rows: built on first use, then read from the cache"}
    del rows

    # Timings: one-pass runs interleaved with single-material renders, per-material once.
    sc, targets, max_depth = blend_mod.load_scene(scene_path, manifold, spp, (res, res))
    targets[0].set_material(m.names[0])
    single = {"touch": mi.load_dict({"type": "manifold_path", "component": "touch", "max_depth": max_depth}),
              "path": mi.load_dict({"type": "path", "max_depth": max_depth})}
    t_single = {k: [] for k in single}

    def render_single(kind, s):
        t0 = time.perf_counter()
        dr.eval(mi.render(sc, integrator=single[kind], spp=spp, seed=s))
        dr.sync_thread()
        return time.perf_counter() - t0

    one_dir = os.path.join(out, f"onepass_{spp}")
    for kind in single:  # warm-up (kernel compilation)
        render_single(kind, 1000)
    first = _basis_run(scene_path, manifold, one_dir, spp, "onepass", res, seed)
    runs = []
    for rep in range(repeats):
        runs.append(_basis_run(scene_path, manifold, one_dir, spp, "onepass", res, seed))
        for kind in single:
            t_single[kind].append(render_single(kind, rep))
    per = _basis_run(scene_path, manifold, os.path.join(out, f"per_material_{spp}"), spp, "per-material", res, seed)
    runs.append(_basis_run(scene_path, manifold, one_dir, spp, "onepass", res, seed))  # and once after it
    for kind in single:
        t_single[kind].append(render_single(kind, repeats))
    wall = [r["wall_s"] for r in runs]
    render = [r["render_s"] for r in runs]
    touch, path = min(t_single["touch"]), min(t_single["path"])
    report["onepass"] = {"images": runs[0]["images"], "first_wall_s": first["wall_s"],
                         "first_render_s": first["render_s"], "wall_s": wall, "render_s": render,
                         "min_wall_s": min(wall), "min_render_s": min(render)}
    report["per_material"] = per
    report["single_render"] = {k: {"min_s": float(np.min(v)), "median_s": float(np.median(v)), "times_s": v}
                               for k, v in t_single.items()}
    speedup = per["wall_s"] / min(wall)
    ratio_render = min(render) / touch
    ratio_wall = min(wall) / touch
    report["targets"] = {
        "speedup_wall": speedup, "speedup_render": per["render_s"] / min(render), "speedup_target": 10.0,
        "meets_speedup_target": speedup >= 10.0,
        "onepass_render_over_touch_render": ratio_render, "onepass_render_over_path_render": min(render) / path,
        "onepass_wall_over_touch_render": ratio_wall, "single_render_ratio_target": 3.0,
        "meets_single_render_target": ratio_render < 3.0,
        "meets_single_render_target_wall": ratio_wall < 3.0,
        "note": ("speedup_wall: render_basis wall times (scene loading, rendering, writing 101 EXRs and the "
                 "manifest) of the two modes; *_render: the rendering alone (manifest per-image times: "
                 "render_onepass, or the sum of the per-material mi.render calls); single renders: one "
                 "mi.render of one material (component touch, and full-GI path) at the same spp"),
    }

    # Equal total time: one-pass spp fitted from its wall times at spp and 4 spp.
    four = _basis_run(scene_path, manifold, os.path.join(out, f"onepass_{4 * spp}"), 4 * spp, "onepass", res, seed)
    slope = max((four["wall_s"] - min(wall)) / (3 * spp), 1e-9)
    fixed = min(wall) - slope * spp
    spp_eq = max(spp, int((per["wall_s"] - fixed) / slope) // spp * spp)
    eq = _basis_run(scene_path, manifold, os.path.join(out, f"onepass_{spp_eq}"), spp_eq, "onepass", res, seed)
    tries = [(spp_eq, eq["wall_s"])]
    if abs(eq["wall_s"] / per["wall_s"] - 1.0) > 0.1:  # one secant step from the two largest runs
        slope = max((eq["wall_s"] - four["wall_s"]) / max(spp_eq - 4 * spp, 1), 1e-9)
        spp_eq = max(spp, int(4 * spp + (per["wall_s"] - four["wall_s"]) / slope) // spp * spp)
        shutil.rmtree(os.path.join(out, f"onepass_{tries[0][0]}"), ignore_errors=True)
        eq = _basis_run(scene_path, manifold, os.path.join(out, f"onepass_{spp_eq}"), spp_eq, "onepass", res, seed)
        tries.append((spp_eq, eq["wall_s"]))
    report["equal_time"] = {
        "onepass_spp": spp_eq, "onepass_wall_s": eq["wall_s"], "per_material_spp": spp,
        "per_material_wall_s": per["wall_s"], "time_ratio_onepass_over_per_material": eq["wall_s"] / per["wall_s"],
        "fit": {"fixed_s": fixed, "s_per_spp": slope, "onepass_wall_s_at_4spp": four["wall_s"],
                "tries_spp_wall_s": tries},
        "how": (f"the per-material basis at {spp} spp sets the time; the one-pass basis gets the spp that "
                f"makes its render_basis wall time equal (wall = fixed + slope * spp fitted from its runs at "
                f"{spp} and {4 * spp} spp, rounded down to a multiple of {spp}; refitted once from the two "
                f"largest runs when 10% off)")}

    # Blend error at a midpoint latent point, each basis against the references.
    a, b = _gi_pair(m)
    x = 0.5 * (m.latent[m.index(a)] + m.latent[m.index(b)])
    ref = blend_mod.render_reference(scene_path, manifold, x, ref_spp, seed=seed + 7919, resolution=(res, res))
    ref_l1 = _l1_reference(scene_path, manifold, x, ref_spp, seed + 7919, res)
    blends = {}
    for key, where, s in (("per_material", f"per_material_{spp}", spp), ("onepass", f"onepass_{spp}", spp),
                          ("onepass_equal_time", f"onepass_{spp_eq}", spp_eq)):
        img, _ = blend_mod.blend(blend_mod.Basis.load(os.path.join(out, where), manifold=m), m, x=x)
        bias, bias_se = _bias(img, ref)
        blends[key] = {"spp": s, "vs_full_gi": {**metrics.compare(img, ref), "relative_bias": bias,
                                                "relative_bias_se": bias_se},
                       "vs_l1": metrics.compare(img, ref_l1)}
    report["blend"] = {
        "x": x.tolist(), "x_is": f"midpoint {a}-{b}", "reference_spp": ref_spp,
        "clamped_fraction": m.negative_fraction(x), "bases": blends,
        "equal_time_rel_mse_ratio_vs_full_gi": (blends["per_material"]["vs_full_gi"]["rel_mse"]
                                                / blends["onepass_equal_time"]["vs_full_gi"]["rel_mse"]),
        "equal_time_rel_mse_ratio_vs_l1": (blends["per_material"]["vs_l1"]["rel_mse"]
                                           / blends["onepass_equal_time"]["vs_l1"]["rel_mse"]),
        "note": ("vs_full_gi includes the L2+ light a blend leaves out (table.xml is concave), the same for "
                 "every basis; vs_l1 is the blend's own error (noise)")}
    report["peak_rss_gib"] = peak_rss_gib()
    return report
