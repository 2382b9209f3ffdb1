"""PCA benchmark: reconstruction error of the training tables by PCA against the manifold's exact reproduction."""

import numpy as np

from mitsuba_manifold.data.database import Database
from mitsuba_manifold.manifold.model import Manifold


def pca_errors(S, table_norms, components):
    """Relative reconstruction error of each training table with k principal components.

    The error of material i with k components is ``sqrt(sum_{j>k} lambda_j U_ij^2) / |t_i|``
    where ``S = U diag(lambda) U^T`` (the Gram matrix of the mean-subtracted tables) and
    ``t_i`` is the raw table; computed from the Gram matrix alone.
    """
    lam, U = np.linalg.eigh(S)
    order = np.argsort(lam)[::-1]
    lam, U = np.maximum(lam[order], 0), U[:, order]
    energy = U**2 * lam[None, :]
    errors = {}
    for k in components:
        errors[k] = np.sqrt(energy[:, k:].sum(axis=1)) / table_norms
    return errors


def run(folder, components=(5, 20, 40, 60), q=2, names=None, focus="color-changing-paint3"):
    """PCA reconstruction error of the training tables against the manifold's exact reproduction (Fig. 8)."""
    db = Database(folder, names)
    tables = db.stack()
    _, S = db.gram(tables=tables)
    norms = np.linalg.norm(tables.astype(np.float64), axis=1)
    errs = pca_errors(S, norms, [k for k in components if k < len(db.names)])
    m = Manifold.fit(db, q=q)
    m._tables = tables
    manifold_err = np.array(
        [
            np.linalg.norm(m.interpolate(m.latent[i], prune=0.0)[0].reshape(-1) - tables[i])
            / norms[i]
            for i in range(m.n)
        ]
    )
    out = {
        "n_materials": len(db.names),
        "dims": list(db.dims),
        "pca": {},
        "manifold_q": q,
        "manifold_max_relative_error": float(manifold_err.max()),
    }
    fi = db.names.index(focus) if focus in db.names else None
    for k, e in errs.items():
        out["pca"][str(k)] = {
            "mean": float(e.mean()),
            "median": float(np.median(e)),
            "max": float(e.max()),
            "worst_material": db.names[int(e.argmax())],
        }
        if fi is not None:
            out["pca"][str(k)][focus] = float(e[fi])
    return out
