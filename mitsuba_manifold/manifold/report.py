"""Diagnostics of a fitted manifold and its printed summary.

* :func:`coincident` — materials the GP cannot tell apart (latent points within ``tol * l``);
* :func:`bound_terms` — the terms of the paper's Eq. 7 bound on ``|z(x) - z_j|``;
* :func:`summary` — the short description the tools print after a fit.
"""

import numpy as np


def coincident(latent, names, length_scale, tol=1e-2):
    """Names of the materials whose nearest latent point lies within ``tol * length_scale``."""
    d2 = ((latent[:, None] - latent[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    return [names[i] for i in np.flatnonzero(np.sqrt(d2.min(axis=1)) < tol * length_scale)]


def bound_terms(x, latent, length_scale, cond_K, gram=None):
    """Terms of Eq. 7 for points ``x`` (M, q): ``|z(x) - z_j| <= e^{-1/2} sqrt(2N) / l * cond(K)
    * |Z|_F * |x - x_j|`` with ``j`` the nearest latent point; ``|Z|_F`` from the Gram matrix
    (NaN without it). Returns a dict of arrays (M,) and scalars.
    """
    dist = np.linalg.norm(x[:, None, :] - latent[None], axis=-1)
    j = dist.argmin(axis=1)
    const = np.exp(-0.5) * np.sqrt(2 * len(latent)) / length_scale
    z_norm = float(np.sqrt(max(np.trace(gram), 0.0))) if gram is not None else float("nan")
    near = dist[np.arange(len(x)), j]
    return {
        "nearest": j,
        "distance": near,
        "constant": const,
        "cond_K": cond_K,
        "Z_norm": z_norm,
        "bound": const * cond_K * z_norm * near,
    }


def summary(m):
    """Short human-readable description of manifold ``m``."""
    rec = m.record
    params = ", ".join(
        f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
        for k, v in m.interpolant.params().items()
        if k not in ("kind", "length_scale", "noise")
    )
    lines = [
        f"Manifold: {m.n} materials, q={m.q}, l={m.length_scale:g}, mu={m.noise:g}, "
        f"features={m.features}, preset={rec.preset or 'paper'}",
        f"  interpolant: {m.interpolant.kind}" + (f" ({params})" if params else ""),
        f"  database: {m.database}",
        f"  cond(K) = {m.condition_number():.3g}",
        f"  weight jump next to a training point (max |w(x_i+) - e_i|_1): {m.discontinuity():.3g}",
    ]
    close = m.coincident()
    if close:
        lines.append(
            f"  warning: {len(close)} materials share their latent point with another (within "
            f"0.01 l), e.g. {', '.join(close[:4])}; interpolation cannot tell them apart"
            + ("; try features='log'" if m.features == "raw" else "")
        )
    if rec.log_likelihood is not None:
        fit_s = rec.timings.fit_s if rec.timings.fit_s is not None else float("nan")
        lines.append(
            f"  log-likelihood L = {rec.log_likelihood:.6g} "
            f"({rec.method}, {len(rec.history)} iterations, {fit_s:.2f} s)"
        )
    return "\n".join(lines)
