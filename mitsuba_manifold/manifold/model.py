"""The material manifold: latent points, interpolation weights, interpolated tables.

A fitted :class:`Manifold` places each of N measured materials at a latent point
``x_i`` (paper Sec. 3). With ``preset="paper"``, for any latent point ``x`` the GP gives

    b(x) = K_inv k(x)                       (paper Eq. 4; K_inv: inverse covariance of the
                                             latent points, k(x): covariance of x with them)
    table(x) = mean + b^T Z = sum_i w_i table_i,   w = b + (1 - sum(b)) / N

so every interpolated material is an affine combination (weights ``w`` summing to 1) of
the measured tables: training materials are reproduced exactly, and far from every
latent point ``b -> 0`` and the material tends to the mean BRDF. That is ``preset="paper"``.

The default preset keeps the GPLVM layout but fits it on ``log(1 + rho)`` features in
q = 3 dimensions and interpolates with convex, continuous, local weights
(:class:`interpolant.ShepardWeights`): still a linear combination of the tables (so blends
of images stay exact), but never negative, without a jump next to the training points, and
a point between two neighbours is a blend of those two. The choice is measured by
``tools/bench.py space`` (README, "The material space").
"""

import os
import time
from typing import NamedTuple

import numpy as np
from ..gp import gplvm, kernel
from . import io as manifold_file, pruning
from . import interpolant as interpolants
from . import projection as projection_mod
from .presets import PRESETS, fit_layout, make_interpolant, settings  # noqa: F401 (re-exported)
from ..data.database import FEATURES, Database
from ..errors import InputError, NotPositiveDefiniteError, did_you_mean
from .pruning import DEFAULT_PRUNE
from .._util.checks import weight_sum

FORMAT_VERSION = manifold_file.FORMAT_VERSION



class Weights(NamedTuple):
    """:meth:`Manifold.weights`: ``b`` (Eq. 4's ``K^-1 k(x)`` for GP weights, else ``w - 1/N``) and weights ``w``."""

    b: np.ndarray
    w: np.ndarray


class Pruned(NamedTuple):
    """:meth:`Manifold.prune`: materials kept, their rescaled weights, the ``|w|`` dropped."""

    keep: np.ndarray
    w_kept: np.ndarray
    dropped: float


class Combination(NamedTuple):
    """:meth:`Manifold.combine`: the combined table, the materials used, the ``|w|`` dropped."""

    table: np.ndarray
    keep: np.ndarray
    dropped: float


class Manifold:
    """A fitted latent space of measured materials (scikit-learn style: fit, then use).

    Attributes
    ----------
    names : list of str
        Material names, in the order of the latent points.
    latent : ndarray (N, q)
        Latent points ``x_i``.
    database : str
        Folder of the tables the manifold was fit on.
    hashes : list of str
        SHA-256 of each table file, to detect a mismatched database.
    length_scale, noise : float
        Kernel hyperparameters ``l`` and ``mu``.
    features : str
        Feature transform used for the fit only (``raw`` or ``log``).
    albedos : ndarray (N, 3)
        Bihemispherical albedo of each material (for :meth:`albedo`).
    history : ndarray
        Log-likelihood per optimiser iteration.
    info : dict
        Fit details (method, times, final log-likelihood, d, dims, preset, ...).
    interpolant : interpolant.Interpolant
        The weight function ``w(x)`` (built from the ``interpolant`` parameters; default the
        paper's GP weights on ``length_scale`` and ``noise``).
    table_gram : ndarray (N, N) or None
        ``T T^T`` of the raw tables (exact pruning errors); computed on first use when absent.
    """

    def __init__(self, names, latent, database, hashes, length_scale=1.0, noise=1e-4,
                 features="raw", albedos=None, gram=None, history=(), info=None, interpolant=None,
                 table_gram=None):
        latent = np.asarray(latent, dtype=np.float64)
        if latent.ndim != 2 or latent.shape[0] != len(names):
            raise InputError(f"latent points must have shape (N={len(names)}, q), got {latent.shape}")
        if not np.isfinite(latent).all():
            raise InputError("latent points contain NaN or Inf")
        if features not in FEATURES:
            raise InputError(f"unknown feature transform {features!r}")
        self.names = list(names)
        self.latent = latent
        self.database = os.fspath(database)
        self.hashes = list(hashes)
        self.length_scale = float(length_scale)
        self.noise = float(noise)
        self.features = features
        self.albedos = None if albedos is None else np.asarray(albedos, dtype=np.float64)
        self.gram = None if gram is None else np.asarray(gram, dtype=np.float64)
        self.history = np.asarray(history, dtype=np.float64)
        self.info = dict(info or {})
        self.table_gram = None if table_gram is None else np.asarray(table_gram, dtype=np.float64)
        self._factorise()
        self.interpolant = make_interpolant(self.latent, {
            "length_scale": self.length_scale, "noise": self.noise,
            "interpolant": interpolant or {"kind": "gp", "exact": True}})
        self._tables = None

    # ------------------------------------------------------------------ fit
    @classmethod
    def fit(cls, database, q=None, names=None, method=None, length_scale=None, noise=None,
            features=None, init=None, progress=False, preset="default", interpolant=None, **options):
        """Fit latent points to the tables of ``database`` (paper Sec. 3).

        ``Manifold.fit(database)`` fits the default preset; ``preset="paper"`` the paper's
        exact formulation. Any other argument given overrides the preset's value.

        Parameters
        ----------
        database : Database or path
        q : int
            Latent dimension (1 to 8).
        names : list of str, optional
        method : {"hooke-jeeves", "lbfgs"}
        length_scale, noise : float
            ``l`` and ``mu`` of the kernel ``mu delta + exp(-|x-x'|^2 / 2 l^2)``.
        features : {"raw", "log"}
            Transform of the tables for the fit only; interpolation always combines raw tables.
        init : ndarray (N, q), optional
            Starting latent points (default: PCA).
        preset : {"default", "paper"}
            See :data:`PRESETS`.
        interpolant : dict, optional
            Weight function, e.g. ``{"kind": "gp", "exact": True}`` (see :mod:`interpolant`).
        **options
            Passed to :func:`gplvm.fit_latent` (``max_iter``, ``tol``, ...).
        """
        cfg = settings(preset, q=q, method=method, length_scale=length_scale, noise=noise,
                       features=features, interpolant=interpolant)
        db = database if isinstance(database, Database) else Database(database, names)
        names = db.names if names is None else list(names)
        if len(names) < 2:
            raise InputError("a manifold needs at least 2 materials")
        t0 = time.perf_counter()
        tables = db.stack(names, progress=progress)
        t_load = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, S, table_gram = db.gram(names, features=cfg["features"], tables=tables, raw=True)
        t_gram = time.perf_counter() - t0
        d = tables.shape[1]
        result = fit_layout(S, d, cfg, init=init, **options)
        albedos = db.albedo(names, tables=tables)
        info = {"method": cfg["method"], "d": int(d), "dims": list(db.dims), "q": int(cfg["q"]),
                "preset": preset, "log_likelihood": float(result.log_likelihood), "time_load_s": t_load,
                "time_gram_s": t_gram, "time_fit_s": float(result.time_s),
                "n_evaluations": int(result.n_evaluations)}
        m = cls(names, result.latent, db.folder, db.hashes(names), cfg["length_scale"], cfg["noise"],
                cfg["features"], albedos, S, result.history, info, cfg["interpolant"], table_gram)
        m._tables = tables
        return m

    def _factorise(self):
        K = kernel.kernel_matrix(self.latent, length_scale=self.length_scale, noise=self.noise)
        try:
            self._factor = kernel.factorise(K)
        except NotPositiveDefiniteError:
            raise InputError(
                f"the covariance K of the {len(self.names)} latent points is not positive definite "
                f"(noise mu={self.noise:g} too small for coincident points?)") from None
        self.K = K

    @property
    def q(self):
        """Latent dimension."""
        return self.latent.shape[1]

    @property
    def n(self):
        """Number of materials."""
        return len(self.names)

    # ------------------------------------------------------------- weights
    def _points(self, x):
        return interpolants.points(x, self.q)

    def weights(self, x):
        """Weights of the interpolant at ``x``: ``b`` and the affine weights ``w`` (sum to 1).

        Parameters
        ----------
        x : array_like (q,) or (M, q)

        Returns
        -------
        Weights
            ``(b, w)``, each ndarray (N,) or (M, N).
            ``sum_i w_i table_i = mean + b^T Z`` exactly. For the paper's GP weights ``b`` is
            Eq. 4's ``K_inv k(x)`` (at a training point the noise term ``mu delta(x, x_i)``
            applies, so ``w = e_i``); for other interpolants ``b = w - 1/N``.
        """
        x, single = self._points(x)
        ip = self.interpolant
        if isinstance(ip, interpolants.GaussianProcessWeights):
            b = ip.gp_weights(x)
            w = ip.affine(b)
        else:
            w = ip.weights(x)
            b = w - 1.0 / self.n
        return Weights(b[0], w[0]) if single else Weights(b, w)

    def weights_jacobian(self, x):
        """``dw/dx`` of the interpolant, analytic: ``(N, q)`` for one point, ``(M, N, q)`` for M.

        GP weights: ``(I - 1 1^T / N) K_inv dk/dx`` (Eq. 4 differentiated; at a training point
        the smooth part's). Shepard: :class:`interpolant.ShepardWeights`. Columns sum to 0.
        """
        x, single = self._points(x)
        J = self.interpolant.jacobian(x)
        return J[0] if single else J

    def _cross(self, x):
        """GP covariances ``k(x)`` (M, N) with the noise term where x equals a latent point."""
        k = kernel.kernel_matrix(x, self.latent, length_scale=self.length_scale)
        hits = np.nonzero((x[:, None, :] == self.latent[None, :, :]).all(-1))
        k[hits] += self.noise
        return k, hits

    def _smooth_gradients(self, x):
        """``K_inv k(x)`` (M, N) of the smooth kernel (no noise term) and ``dk/dx`` (M, N, q)."""
        k = kernel.kernel_matrix(x, self.latent, length_scale=self.length_scale)
        dk = -k[:, :, None] * (x[:, None, :] - self.latent[None]) / self.length_scale ** 2
        return self._factor.solve(k.T).T, dk

    def variance(self, x):
        """GP predictive variance (paper Eq. 2): ``c(x, x) - k^T K_inv k``."""
        x, single = self._points(x)
        k, _ = self._cross(x)
        v = 1.0 + self.noise - np.einsum("mn,mn->m", k, self._factor.solve(k.T).T)
        return v[0] if single else v

    def variance_gradient(self, x):
        """Gradient of the smooth part of :meth:`variance`: ``-2 (dk/dx)^T K_inv k``, (q,) or (M, q)."""
        x, single = self._points(x)
        b, dk = self._smooth_gradients(x)
        g = -2.0 * np.einsum("mnq,mn->mq", dk, b)
        return g[0] if single else g

    def material_weights(self, name):
        """One-hot weights of a training material."""
        w = np.zeros(self.n)
        w[self.index(name)] = 1.0
        return w

    def index(self, name):
        try:
            return self.names.index(name)
        except ValueError:
            raise InputError(f"unknown material {name!r}{did_you_mean(name, self.names)}: this manifold has {self.n} materials "
                                f"({', '.join(self.names[:6])}{', ...' if self.n > 6 else ''})") from None

    def parse_weights(self, text):
        """Weights from ``"name:w, name:w"`` (unnamed materials get 0).

        Raises
        ------
        InputError
            Unknown names, malformed entries, non-finite values or weights summing to 0.
        """
        w = np.zeros(self.n)
        entries = [e.strip() for e in str(text).split(",") if e.strip()]
        if not entries:
            raise InputError(f"weights {text!r}: expected 'name:weight, name:weight'")
        for e in entries:
            name, sep, value = e.rpartition(":")
            try:
                v = float(value)
            except ValueError:
                v = None
            if not sep or v is None or not np.isfinite(v) or ":" in name:
                raise InputError(f"weights {text!r}: entry {e!r} is not 'name:number' (commas separate entries)")
            w[self.index(name.strip())] += v
        try:
            weight_sum(w)
        except InputError as e:
            raise InputError(f"weights {text!r}: {e}") from None
        return w

    # ------------------------------------------------------- interpolation
    def open_database(self, folder=None, names=None):
        """The database of this manifold (or ``folder``), checked against the recorded hashes.

        Only the materials in ``names`` (default: all) are read and checked.
        """
        folder = folder or self.database
        names = self.names if names is None else list(names)
        try:
            db = Database(folder, names)
        except FileNotFoundError as e:
            raise InputError(f"database for this manifold: {e} (if it moved, give its folder: --database "
                                "for the tools, the 'database' parameter of manifold_brdf)") from None
        except KeyError as e:
            raise InputError(f"database for this manifold: {e}") from None
        for name in names:
            if db.hash(name) != self.hashes[self.index(name)]:
                raise InputError(
                    f"database {db.folder}: table {name!r} differs from the one the manifold was fit on "
                    f"(hash {db.hash(name)[:12]} != {self.hashes[self.index(name)][:12]})")
        return db

    def table_norms(self):
        """L2 norm of each raw table (from :attr:`table_gram`)."""
        return np.sqrt(np.maximum(np.diag(self._table_gram()), 0.0))

    def _table_gram(self):
        if self.table_gram is None:  # manifolds saved by the previous release
            self.table_gram = pruning.raw_gram(self.tables())
        return self.table_gram

    def prune(self, w, prune=DEFAULT_PRUNE):
        """Materials kept by pruning and the weight dropped.

        Drops the materials of smallest contribution ``|w_i| |table_i|`` for as long as the
        table changes by at most ``prune`` of its L2 norm; the kept weights are rescaled to
        sum to ``sum(w)`` so the combination stays affine. The change is computed exactly from
        the tables' Gram matrix (:func:`pruning.prune`), rescaling included; ``prune = 0``
        keeps every non-zero weight.

        Returns
        -------
        Pruned
            ``keep`` (ndarray of int), ``w_kept`` (ndarray), ``dropped`` (float: sum of
            ``|w_i|`` over the dropped materials).
        """
        w = np.asarray(w, dtype=np.float64)
        if w.shape != (self.n,) or not np.isfinite(w).all():
            raise InputError(f"weights must be {self.n} finite values, got shape {w.shape}")
        if not 0 <= prune < 1:
            raise InputError(f"prune must be in [0, 1), got {prune}")
        return Pruned(*pruning.prune(w, self._table_gram(), prune))

    def prune_error(self, w, keep):
        """Relative L2 change of the table ``sum w_i table_i`` when only ``keep`` is kept (rescaled)."""
        return pruning.error(np.asarray(w, dtype=np.float64), keep, self._table_gram())

    def tables(self, database=None):
        """All N tables in memory as float32 ``(N, d)`` (loaded once, then kept)."""
        if self._tables is None:
            self._tables = self.open_database(database).stack(self.names)
        return self._tables

    def combine(self, w, prune=DEFAULT_PRUNE, database=None):
        """The table ``sum_i w_i table_i`` over the materials kept by :meth:`prune`.

        Reads only the kept materials' tables (unless all tables are already in memory).

        Returns
        -------
        Combination
            ``table`` (ndarray float32 ``(3, n_theta_h, n_theta_d, n_phi_d)``), ``keep``
            (indices of the materials used), ``dropped`` (float).
        """
        keep, w_kept, dropped = self.prune(w, prune)
        if self._tables is not None and database is None:
            shape = (3,) + tuple(self.info["dims"])
            if 2 * len(keep) > self.n:  # one (multithreaded) matrix-vector product over all tables
                full = np.zeros(self.n, dtype=np.float32)
                full[keep] = w_kept
                return Combination((full @ self._tables).reshape(shape), keep, dropped)
            flat = pruning.weighted_sum((self._tables[i] for i in keep), w_kept, self._tables.shape[1])
            return Combination(flat.reshape(shape), keep, dropped)
        db = self.open_database(database, [self.names[i] for i in keep])
        flat = pruning.weighted_sum((db.reflectance(self.names[i]).reshape(-1) for i in keep), w_kept,
                             3 * int(np.prod(db.dims)))
        return Combination(flat.reshape((3,) + db.dims), keep, dropped)

    def interpolate(self, x, prune=DEFAULT_PRUNE, database=None):
        """The interpolated table at latent point ``x``; see :meth:`combine` for the outputs."""
        if np.ndim(x) > 1:
            raise InputError(f"interpolate takes one latent point ({self.q} numbers), got shape {np.shape(x)}; "
                                "call it once per point")
        _, w = self.weights(x)
        return self.combine(w, prune, database)

    def negative_fraction(self, x, prune=DEFAULT_PRUNE, database=None):
        """Fraction of the interpolated table's values below 0 at ``x``.

        ``manifold_brdf`` clamps them to 0, a blend of images cannot: where this is not
        small, a blend and a render of the material differ by more than L2+.
        """
        table, _, _ = self.interpolate(x, prune, database)
        return float((table < 0).mean())

    def mean(self, database=None):
        """The mean table (the far-field limit of the interpolant)."""
        return self.combine(np.full(self.n, 1.0 / self.n), prune=0.0, database=database)[0]

    def albedo(self, x):
        """Bihemispherical albedo (RGB) of the interpolated material, by linearity."""
        if self.albedos is None:
            raise InputError("this manifold has no per-material albedos")
        _, w = self.weights(x)
        return w @ self.albedos

    def project(self, table, **options):
        """The latent point whose material is closest to ``table`` (any MERL table).

        ``table``: a reflectance table of this manifold's resolution (as :meth:`Database.reflectance`,
        or flat) or the path of a MERL ``.binary`` file; ``options`` go to :func:`projection.project`.
        Returns a :class:`projection.Projection`: ``x``, ``error`` (RMS of ``log(1 + rho)``
        differences over all bins), ``weights``, the nearest training material and its error.
        """
        table = projection_mod.as_table(table, 3 * int(np.prod(self.info.get("dims", (0,)))), self.info.get("dims"))
        return projection_mod.project(self.interpolant, self.tables(), table, names=self.names, **options)

    # ----------------------------------------------------------- diagnostics
    def condition_number(self):
        """2-norm condition number of K."""
        ev = np.linalg.eigvalsh(self.K)
        return float(ev[-1] / ev[0])

    def bound_terms(self, x):
        """Terms of the paper's Eq. 7 bound on ``|z(x) - z_j|`` for the nearest latent point j.

        ``|z(x) - z_j| <= e^{-1/2} sqrt(2N) / l * cond(K) * |Z|_F * |x - x_j|``.
        """
        x, single = self._points(x)
        dist = np.linalg.norm(x[:, None, :] - self.latent[None], axis=-1)
        j = dist.argmin(axis=1)
        const = np.exp(-0.5) * np.sqrt(2 * self.n) / self.length_scale
        kappa = self.condition_number()
        z_norm = float(np.sqrt(max(np.trace(self.gram), 0.0))) if self.gram is not None else float("nan")
        bound = const * kappa * z_norm * dist[np.arange(len(x)), j]
        out = {"nearest": j, "distance": dist[np.arange(len(x)), j], "constant": const,
               "cond_K": kappa, "Z_norm": z_norm, "bound": bound}
        if single:
            out = {k: (v[0] if isinstance(v, np.ndarray) else v) for k, v in out.items()}
        return out

    def log_likelihood(self):
        """Paper Eq. 6 at the stored latent points (needs the Gram matrix)."""
        if self.gram is None:
            raise InputError("this manifold was saved without its Gram matrix")
        return gplvm.log_likelihood(self.latent, self.gram, self.info["d"], self.length_scale, self.noise)

    def discontinuity(self):
        """Largest jump of the weights when leaving a training point, ``max_i |w(x_i+) - e_i|_1``.

        See :meth:`interpolant.Interpolant.jump`: up to ~2 for the paper's GP weights when
        latent points are close compared with ``l``, ~0 for the continuous Shepard weights.
        """
        return self.interpolant.jump()

    def coincident(self, tol=1e-2):
        """Materials whose nearest latent point lies within ``tol * l`` (indistinguishable to the GP).

        Interpolating between such materials is not possible: near them the weights spread
        over the whole group. A fit on ``raw`` features collapses materials whose tables differ
        little compared with the spikiest ones; ``features="log"`` separates them.
        """
        d2 = ((self.latent[:, None] - self.latent[None]) ** 2).sum(-1)
        np.fill_diagonal(d2, np.inf)
        return [self.names[i] for i in np.flatnonzero(np.sqrt(d2.min(axis=1)) < tol * self.length_scale)]

    def summary(self):
        """Short human-readable description."""
        params = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                           for k, v in self.interpolant.params().items() if k not in ("kind", "length_scale", "noise"))
        lines = [f"Manifold: {self.n} materials, q={self.q}, l={self.length_scale:g}, mu={self.noise:g}, "
                 f"features={self.features}, preset={self.info.get('preset', 'paper')}",
                 f"  interpolant: {self.interpolant.kind}" + (f" ({params})" if params else ""),
                 f"  database: {self.database}",
                 f"  cond(K) = {self.condition_number():.3g}"]
        lines.append(f"  weight jump next to a training point (max |w(x_i+) - e_i|_1): {self.discontinuity():.3g}")
        close = self.coincident()
        if close:
            lines.append(f"  warning: {len(close)} materials share their latent point with another (within "
                         f"0.01 l), e.g. {', '.join(close[:4])}; interpolation cannot tell them apart"
                         + ("; try features='log'" if self.features == "raw" else ""))
        if "log_likelihood" in self.info:
            lines.append(f"  log-likelihood L = {self.info['log_likelihood']:.6g} "
                         f"({self.info.get('method')}, {len(self.history)} iterations, "
                         f"{self.info.get('time_fit_s', float('nan')):.2f} s)")
        return "\n".join(lines)

    # ------------------------------------------------------------ save/load
    def save(self, path):
        """Write to ``.npz`` (no pickle), atomically (:func:`manifold_file.write`)."""
        manifold_file.write(self, path)

    @classmethod
    def load(cls, path):
        """Read a manifold written by :meth:`save` (:func:`manifold_file.read`).

        Files of format version 1 (the previous release) load with the paper's GP weights on
        their stored ``l`` and ``mu`` (what they were used with); refit for the default.

        Raises
        ------
        InputError
            Missing, corrupt or foreign files.
        """
        m = cls(**manifold_file.read(path))
        m.file = os.fspath(path)   # where it was read from (``path`` is the method of paths)
        return m

    # ------------------------------------------------------------ perceptual paths
    def distance(self, x, y, stride=(1, 1, 1)):
        """[PR12] distance between the tables ``sum_i w_i table_i`` at ``x`` and ``y`` (names, points
        ``(q,)`` or stacks ``(M, q)``: a float, ``(M,)`` or ``(M, K)``); :func:`paths.latent_distance`."""
        from . import paths
        return paths.latent_distance(self, x, y, stride)

    def path(self, a, b, steps=21, kind=None):
        """``steps`` latent points from ``a`` to ``b`` of ``kind`` (default the best measured); :func:`paths.path`."""
        from . import paths
        return paths.path(self, a, b, steps, kind or paths.DEFAULT_KIND)
