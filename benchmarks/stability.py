"""Stability benchmark: cond(K), weights, clamping and precision over stiff and extreme cases."""

import numpy as np

from mitsuba_manifold.manifold.model import Manifold


def query_points(m, n_random=64, seed=0):
    """Typical query points: midpoints of each point's nearest pair and random points in the box."""
    d2 = ((m.latent[:, None] - m.latent[None]) ** 2).sum(-1) + np.eye(m.n) * 1e300
    mids = 0.5 * (m.latent + m.latent[d2.argmin(axis=1)])
    lo, hi = m.latent.min(0), m.latent.max(0)
    rng = np.random.default_rng(seed)
    return np.vstack([mids, rng.uniform(lo, hi, (n_random, m.q))])


def weights_row(m, label, queries):
    row = {
        "case": label,
        "cond_K": m.condition_number(),
        "jump_at_training_points": m.discontinuity(),
    }
    _, w = m.weights(queries)
    row.update(
        {
            "max_abs_w": float(np.abs(w).max()),
            "max_sum_abs_w": float(np.abs(w).sum(1).max()),
            "max_sum_error": float(np.abs(w.sum(1) - 1).max()),
            "finite": bool(np.isfinite(w).all()),
        }
    )
    row["bounded"] = row["finite"] and row["max_sum_abs_w"] < 1e3
    return row


def run(folder, manifold=None, q=2, grid=48):
    """One table over stiff and extreme cases: does everything stay finite and bounded?

    Uses the latent points of a fitted manifold and varies the hyperparameters around them
    (``l`` from 1e-3 to 1e3, ``mu`` from 1e-10 to 1e-2), near-duplicate and far-away points,
    negative-weight blends (clamped bins, albedo outside [0, 1]), float32 against float64.
    """
    from mitsuba_manifold.manifold.model import InputError

    base = Manifold.load(manifold) if manifold else Manifold.fit(folder, q=q)
    tables = base.tables(folder if manifold else None)
    queries = query_points(base)
    rows = []

    def variant(latent, l, mu):
        return Manifold(
            base.names, latent, base.database, base.hashes, l, mu, base.features, base.albedos
        )

    for l in (1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0, 1e3):
        try:
            rows.append(
                weights_row(
                    variant(base.latent, l, base.noise), f"l={l:g}, mu={base.noise:g}", queries
                )
            )
        except InputError as e:
            rows.append({"case": f"l={l:g}", "error": str(e), "finite": True, "bounded": False})
    for mu in (1e-10, 1e-8, 1e-6, 1e-4, 1e-2):
        try:
            rows.append(
                weights_row(variant(base.latent, base.length_scale, mu), f"l=1, mu={mu:g}", queries)
            )
        except InputError as e:
            rows.append({"case": f"mu={mu:g}", "error": str(e), "finite": True, "bounded": False})
    for eps in (1e-2, 1e-4, 1e-6, 1e-8):
        latent = base.latent.copy()
        latent[1] = latent[0] + eps
        try:
            m = variant(latent, base.length_scale, base.noise)
            row = weights_row(
                m,
                f"near duplicate points, distance {eps:g}",
                np.vstack([queries, latent[:2].mean(0)]),
            )
        except InputError as e:
            row = {
                "case": f"near duplicate {eps:g}",
                "error": str(e),
                "finite": True,
                "bounded": False,
            }
        rows.append(row)
    for dist in (1e3, 1e6, 1e12):
        x = base.latent.mean(0) + dist / np.sqrt(base.q)
        table, _, _ = base.interpolate(x, prune=0.0)
        mean = base.mean()
        rows.append(
            {
                "case": f"far point at distance {dist:g}",
                "finite": bool(np.isfinite(table).all()),
                "max_relative_difference_to_mean": float(
                    np.abs(table - mean).max() / np.abs(mean).max()
                ),
                "bounded": bool(np.isfinite(table).all()),
            }
        )

    # negative-weight blends over a latent grid: clamped bins and albedo outside [0, 1]
    from mitsuba_manifold.imaging.plots import albedo_grid

    _, _, alb = albedo_grid(base, resolution=grid)
    lo, hi = base.latent.min(0), base.latent.max(0)
    pts = np.random.default_rng(1).uniform(
        lo - 0.25 * (hi - lo), hi + 0.25 * (hi - lo), (24, base.q)
    )
    _, W = base.weights(pts)
    neg_fraction = []
    for w in W:
        t, _, _ = base.combine(w, prune=0.0)
        neg_fraction.append(float((t < 0).mean()))
    rows.append(
        {
            "case": "negative-weight blends (24 random points, box + 25%)",
            "fraction_points_with_negative_weights": float((W < 0).any(1).mean()),
            "mean_fraction_bins_clamped": float(np.mean(neg_fraction)),
            "max_fraction_bins_clamped": float(np.max(neg_fraction)),
            "albedo_map_outside_0_1": float(((alb < 0) | (alb > 1)).mean()),
            "albedo_map_min": float(alb.min()),
            "albedo_map_max": float(alb.max()),
            "finite": True,
            "bounded": True,
        }
    )

    # float32 accumulation (what the package does) against float64
    _, w = base.weights(queries[0])
    t32 = w.astype(np.float32) @ tables
    t64 = w @ tables.astype(np.float64)
    scale = np.abs(t64).max()
    rows.append(
        {
            "case": "float32 vs float64 interpolated table",
            "max_abs_error_relative_to_max": float(np.abs(t32 - t64).max() / scale),
            "finite": True,
            "bounded": True,
        }
    )
    return {
        "n_materials": base.n,
        "q": base.q,
        "rows": rows,
        "all_finite": all(r.get("finite", False) for r in rows),
    }
