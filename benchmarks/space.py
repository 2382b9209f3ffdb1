"""Space benchmark: is the manifold a material space worth moving through?

For each configuration (a preset with overrides: features, q, interpolant), on the full
database with the tables loaded once:

* held-out fidelity: 10-fold cross-validation (fit on 90, project each of the other 10 with
  :func:`projection.project`; error = RMS of ``log(1 + rho)`` differences over all bins)
  against the nearest training material, PCA with k = q and k = 5 in ``log(1 + rho)`` and the
  mean; negative-bin fraction and albedo of the best points;
  the per-material ratio to the nearest material fold by fold (sets of ten none was tuned on);
* a reference with no latent space: the best convex blend of each held-out material's 4 and 8
  closest training materials (what convex weights could reach at best);
* path smoothness: 20 pairs of latent neighbours, 41 points each; the largest step's share
  of the path's length in weights and in tonemapped images of the basis (when given);
  in weights also on every pair of a material and its nearest latent neighbour;
* jump at training points, plausibility over the latent box (+10%);
* fit time (``Manifold.fit`` on the whole database) and one interpolated table, for the
  default; and the default prune's exact table error over random points.

The Gram matrices of all N tables in each feature space are computed once: the centred
Gram of any training subset is a centred sub-block.
"""

import os
import time

import numpy as np

from mitsuba_manifold._util.timing import median_time
from mitsuba_manifold.data.database import Database
from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.manifold import projection, space
from mitsuba_manifold.manifold.model import (
    DEFAULT_PRUNE,
    Manifold,
    fit_layout,
    make_interpolant,
    settings,
)
from mitsuba_manifold.manifold.presets import stress_distances, stress_of

#: Configurations compared: name -> (preset, overrides). ``default`` is the preset.
CONFIGS = {
    "paper": ("paper", {}),
    "paper-log": ("paper", {"features": "log"}),
    "paper-log-q5": ("paper", {"features": "log", "q": 5, "method": "lbfgs"}),
    "gp-continuous-log": (
        "paper",
        {"features": "log", "method": "lbfgs", "interpolant": {"kind": "gp", "exact": False}},
    ),
    "shepard-global-q3": (
        "default",
        {
            "q": 3,
            "stress": 0.0,
            "interpolant": {"kind": "shepard", "power": 2.0, "taper": float("inf"), "spread": 0.0},
        },
    ),
    "shepard-fixed-taper-q3": (
        "default",
        {
            "q": 3,
            "stress": 0.0,
            "interpolant": {"kind": "shepard", "power": 2.0, "taper": 0.2, "spread": 0.0},
        },
    ),
    "shepard-spread-0.3": (
        "default",
        {"interpolant": {"kind": "shepard", "power": 2.0, "taper": 0.2, "spread": 0.3}},
    ),
    "shepard-taper-0.15": (
        "default",
        {"interpolant": {"kind": "shepard", "power": 2.0, "taper": 0.15, "spread": 0.1}},
    ),
    "shepard-power-2.5": (
        "default",
        {"interpolant": {"kind": "shepard", "power": 2.5, "taper": 0.2, "spread": 0.1}},
    ),
    "shepard-spread-0.2": (
        "default",
        {"interpolant": {"kind": "shepard", "power": 2.0, "taper": 0.2, "spread": 0.2}},
    ),
    "shepard-local-q2": ("default", {"q": 2, "stress": 0.0}),
    "shepard-local-q3": ("default", {"q": 3, "stress": 0.0}),
    "shepard-local-q4": ("default", {"q": 4, "stress": 0.0}),
    "shepard-local-q5": ("default", {"q": 5, "stress": 0.0}),
    "shepard-coslog": ("default", {"features": "coslog"}),
    "default": ("default", {}),
}

TARGETS = {
    "beats_nearest": 0.9,
    "median_over_nearest": 0.75,
    "path_weights": 0.10,
    "path_images": 0.15,
    "jump": 0.1,
    "albedo_outside": 0.02,
    "median_negative_fraction": 0.005,
    "fit_s": 30.0,
    "interpolate_s": 0.1,
    "prune_error": 0.01,
}


def _cos_weights(dims):
    from mitsuba_manifold.data import merl

    th, td, pd = merl.bin_centres(dims)
    wi, wo = merl.directions(th, td, pd)
    return (
        (np.clip(wi[..., 2], 0, None) * np.clip(wo[..., 2], 0, None)).astype(np.float32).reshape(-1)
    )


def _basis_images(basis, names):
    """(base, images (N, H, W, 3)) of a basis folder, or (None, None)."""
    if not basis:
        return None, None
    read = lambda n: imageio.read_exr(os.path.join(basis, n + ".exr")).astype(np.float32)  # noqa: E731
    return read("base"), np.stack([read(n) for n in names])


def _config_report(  # noqa: PLR0913  the data set's parts as run holds them
    name, cfg, tables, names, grams, albedos, images, base, folds, progress, *, distances=None
):
    """One configuration's report; ``distances``: the tables' perceptual distances, the targets
    of a configuration's stress term (as :meth:`Manifold.fit` uses them).
    """
    d = tables.shape[1]
    G_fit = grams[cfg["features"]]
    D = distances if stress_of(cfg).active else None

    def fit(train):
        sub = None if D is None else D[np.ix_(train, train)]
        res = fit_layout(space.centred(G_fit, train), d, cfg, distances=sub)
        return make_interpolant(res.latent, cfg)

    t0 = time.perf_counter()
    held = space.cross_validate(
        tables,
        names,
        fit,
        grams["log"],
        cfg["q"],
        albedos,
        split=space.FoldSplit(only=None if folds is None else tuple(folds)),
    )
    t_cv = time.perf_counter() - t0
    ip = fit(np.arange(len(names)))
    pairs = space.neighbour_pairs(ip.latent)
    paths = space.path_smoothness(ip, pairs, images=images, base=base)
    every = space.path_smoothness(ip, space.all_neighbour_pairs(ip.latent)).weight_share
    jump = space.training_jump(ip)
    plaus = space.plausibility(ip, albedos, tables)
    hs, ps, pl = held.summary(), paths.summary(), plaus.summary()
    ps.update(
        all_pairs=len(every),
        all_pairs_worst_weight_share=float(every.max()),
        all_pairs_over_target=int((every > TARGETS["path_weights"]).sum()),
    )
    row = {
        "settings": cfg,
        "held_out": hs,
        "paths": ps,
        "pairs": [[names[i], names[j]] for i, j in pairs],
        "jump": {"median": float(np.median(jump)), "max": float(jump.max())},
        "plausibility": pl,
        "cv_s": t_cv,
        "cv_fit_s": held.fit_s,
        "cv_project_s": held.project_s,
        "held_out_rows": held.as_dict(),
    }
    row["meets"] = {
        "held_out_beats_nearest": hs["beats_nearest"] >= TARGETS["beats_nearest"],
        "held_out_median_vs_nearest": hs["median_error_over_median_nearest"]
        <= TARGETS["median_over_nearest"],
        "held_out_median_vs_pca_q": hs["median_error"] <= hs["median_pca_q"],
        "held_out_every_fold": hs["worst_fold_median_ratio"] <= TARGETS["median_over_nearest"],
        "path_all_pairs": ps["all_pairs_worst_weight_share"] <= TARGETS["path_weights"],
        "path_weights": ps["worst_weight_share"] <= TARGETS["path_weights"],
        "path_images": ps.get("worst_image_share", np.inf) <= TARGETS["path_images"],
        "jump": row["jump"]["max"] <= TARGETS["jump"],
        "albedo_outside": pl["albedo_outside_fraction"] <= TARGETS["albedo_outside"],
        "median_negative_fraction": pl["median_negative_fraction"]
        <= TARGETS["median_negative_fraction"],
    }
    if progress:
        print(
            f"  {name}: held-out median {hs['median_error']:.4f} (nearest {hs['median_nearest']:.4f}, "
            f"PCA-q {hs['median_pca_q']:.4f}), beats nearest {hs['beats_nearest']:.0%}; worst path "
            f"{ps['worst_weight_share']:.3f} weights / {ps.get('worst_image_share', float('nan')):.3f} images; "
            f"jump {row['jump']['max']:.3g}; albedo outside {pl['albedo_outside_fraction']:.1%}; "
            f"({t_cv:.0f} s)",
            flush=True,
        )
    return row


def _blend_reference(tables, G_log, only_folds=None, ks=(4, 8)):
    """What a space of convex weights could reach: for each held-out material (the same
    folds), the best convex blend of its ``k`` closest training materials, with no latent
    space at all; its error (all bins) over the nearest material's, as in the held-out rows.
    """
    n, d = tables.shape
    bins = projection.search_bins(d)
    T = tables[:, bins].astype(np.float64)
    tests = [
        f for i, f in enumerate(space.folds(n)) if only_folds is None or i in only_folds
    ]  # as cross_validate's
    ratios, bounds = {k: [] for k in ks}, np.cumsum([0] + [len(f) for f in tests])
    for test in tests:
        train = np.setdiff1d(np.arange(n), test)
        nearest = space.baseline_errors(G_log, train, test, d, components=())["nearest"]
        for t, near in zip(test, nearest):
            y = np.log1p(np.maximum(T[t], 0.0))
            order = train[np.argsort(projection.log_rms(T[train], y))]
            full_y = np.log1p(np.maximum(tables[t], 0.0))
            for k in ks:
                w = space.convex_blend(T[order[:k]], y)
                blend = w.astype(np.float32) @ tables[order[:k]]
                ratios[k].append(float(projection.log_rms(blend, full_y)) / near)
    return {
        f"closest_{k}": {
            "median_ratio_to_nearest": float(np.median(r)),
            "fold_median_ratios": [
                float(np.median(r[a:b])) for a, b in zip(bounds[:-1], bounds[1:])
            ],
        }
        for k, r in ((k, np.asarray(v)) for k, v in ratios.items())
    }


def _default_costs(folder, names, repeats=7, n_points=20, seed=0):
    """Fit time of the default on the whole database, one interpolated table, the default prune."""
    t0 = time.perf_counter()
    m = Manifold.fit(folder, names=names)
    t_fit = time.perf_counter() - t0
    rng = np.random.default_rng(seed)
    lo, hi = space.latent_box(m.latent)
    X = lo + rng.random((n_points, m.q)) * (hi - lo)
    t_interp, _ = median_time(lambda: m.interpolate(X[0]), repeats)
    errors, kept = [], []
    for x in X:
        w = m.weights(x).w
        full = m.combine(w, prune=0.0).table
        table, keep, _ = m.combine(w)
        errors.append(float(np.linalg.norm(table - full) / np.linalg.norm(full)))
        kept.append(int(len(keep)))
    return m, {
        "fit_s": t_fit,
        "fit_breakdown_s": {k: m.info[k] for k in ("time_load_s", "time_gram_s", "time_fit_s")},
        "interpolate_s": t_interp,
        "prune": DEFAULT_PRUNE,
        "prune_l2_error": {"median": float(np.median(errors)), "max": float(np.max(errors))},
        "prune_materials_kept": {"median": float(np.median(kept)), "max": int(np.max(kept))},
        "meets": {
            "fit_s": t_fit <= TARGETS["fit_s"],
            "interpolate_s": t_interp <= TARGETS["interpolate_s"],
            "prune_error": float(np.max(errors)) <= TARGETS["prune_error"],
        },
    }


def run(folder, basis=None, configs=None, names=None, folds=None, progress=True):
    """Measure each configuration of :data:`CONFIGS` (or the named ``configs``); see the module doc.

    Parameters
    ----------
    folder : path
        Database (the full built-in one for the issue's targets).
    basis : path, optional
        A basis folder of the same materials (the main job's ``gi/basis_*``) for the
        image-space path smoothness.
    folds : iterable of int, optional
        Run only these of the 10 folds (quicker, partial).
    """
    from .inputs import database_names, fold_numbers, known

    configs = (
        list(CONFIGS)
        if configs is None
        else known("`configs`", configs, list(CONFIGS), "configuration")
    )
    folds = fold_numbers(folds, n=len(names) if names else len(database_names(folder)))
    db = Database(folder, names)
    names = db.names
    t0 = time.perf_counter()
    tables = db.stack(names)
    albedos = db.albedo(names, tables=tables)
    t_load = time.perf_counter() - t0
    cfgs = {c: settings(CONFIGS[c][0], **CONFIGS[c][1]) for c in configs}
    distances = None
    if any(stress_of(cfg).active for cfg in cfgs.values()):
        distances = stress_distances(tables, db.dims)
    cos = _cos_weights(db.dims)
    t0 = time.perf_counter()
    grams = {
        f: space.feature_gram(tables, f, cos)
        for f in sorted({"log"} | {c["features"] for c in cfgs.values()})
    }
    t_gram = time.perf_counter() - t0
    base, images = _basis_images(basis, names)
    if progress:
        print(
            f"{len(names)} tables loaded in {t_load:.1f} s, Gram matrices in {t_gram:.1f} s",
            flush=True,
        )
    out = {
        "n_materials": len(names),
        "dims": list(db.dims),
        "search_bins": projection.SEARCH_BINS,
        "folds": "all 10" if folds is None else list(folds),
        "basis": basis,
        "targets": TARGETS,
        "load_s": t_load,
        "gram_s": t_gram,
        "configs": {},
    }
    for c in configs:
        out["configs"][c] = _config_report(
            c,
            cfgs[c],
            tables,
            names,
            grams,
            albedos,
            images,
            base,
            folds,
            progress,
            distances=distances,
        )
    out["convex_blend_reference"] = _blend_reference(tables, grams["log"], folds)
    del tables
    if "default" in configs:
        _, out["default_costs"] = _default_costs(folder, names)
    return out


def report(result: dict) -> str:
    """Markdown section for docs/benchmarks.md: per configuration, the 10-fold held-out error
    against the nearest material, path smoothness, the jump at the data and plausibility.
    """
    r = result["result"] if "result" in result else result
    t = r["targets"]
    dims = "x".join(map(str, r.get("dims", ())))
    folds = (
        "10-fold"
        if str(r.get("folds", "all")).startswith("all")
        else f"folds {r['folds']} of a 10-fold"
    )
    lines = [
        f"### The material space ({r.get('n_materials', '?')} materials, {dims})",
        "",
        f"`tools/bench.py space --configs {','.join(r['configs'])} --database "
        f"{result.get('database', 'merl')} --json benchmarks/results/space.json` "
        f"({folds}"
        " cross-validation: each held-out table against its projection onto the manifold of the "
        "others).",
        "",
        "| configuration | figure | value | target | met |",
        "|---|---|---|---|---|",
    ]
    yes = lambda ok: "yes" if ok else "no"  # noqa: E731
    for name, c in r["configs"].items():
        h, p, j, pl = c["held_out"], c["paths"], c["jump"], c["plausibility"]
        rows = [
            (
                "held-out median error / nearest material's",
                f"{h['median_ratio_to_nearest']:.3f}",
                f"<= {t['median_over_nearest']:g}",
                h["median_ratio_to_nearest"] <= t["median_over_nearest"],
            ),
            (
                "held-out materials beating the nearest",
                f"{h['beats_nearest']:.0%}",
                f">= {t['beats_nearest']:.0%}",
                h["beats_nearest"] >= t["beats_nearest"],
            ),
            (
                "worst fold's median ratio",
                f"{h['worst_fold_median_ratio']:.3f}",
                "< 1",
                h["worst_fold_median_ratio"] < 1,
            ),
            (
                "path: worst weight share of a step",
                f"{p['worst_weight_share']:.3f}",
                f"<= {t['path_weights']:g}",
                p["worst_weight_share"] <= t["path_weights"],
            ),
            (
                "every neighbour pair's worst step",
                f"{p.get('all_pairs_worst_weight_share', float('nan')):.3f}",
                f"<= {t['path_weights']:g}",
                p.get("all_pairs_over_target", 1) == 0,
            ),
            (
                "weight jump at the data",
                f"{j['max']:.2g}",
                f"<= {t['jump']:g}",
                j["max"] <= t["jump"],
            ),
            (
                "albedo outside the data's range",
                f"{pl['albedo_outside_fraction']:.3f}",
                f"<= {t['albedo_outside']:g}",
                pl["albedo_outside_fraction"] <= t["albedo_outside"],
            ),
        ]
        if p.get("worst_image_share") is not None:
            rows.insert(
                4,
                (
                    "path: worst image share of a step",
                    f"{p['worst_image_share']:.3f}",
                    f"<= {t['path_images']:g}",
                    p["worst_image_share"] <= t["path_images"],
                ),
            )
        for figure, value, target, ok in rows:
            lines.append(f"| {name} | {figure} | {value} | {target} | {yes(ok)} |")
    return "\n".join(lines)
