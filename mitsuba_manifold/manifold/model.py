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
q = 4 dimensions, with a stress term that asks latent distances to follow the materials'
perceptual distances (:mod:`mitsuba_manifold.gp.stress`), and interpolates with convex,
continuous, local weights
(:class:`interpolant.ShepardWeights`): still a linear combination of the tables (so blends
of images stay exact), but never negative, without a jump next to the training points, and
a point between two neighbours is a blend of those two. The choice is measured by
``tools/bench.py space`` (README, "The material space").

:class:`Manifold` is one class: its fit (:func:`fit_database`), names and weight text, pruning
and combination (:meth:`Manifold.prune`, ``prune_report``, ``combine``), diagnostics and
summary are its methods here. It calls the algorithms that are concepts of their own: the
GP (kernel, factorisation of K, variance) in :mod:`mitsuba_manifold.gp`, the weights ``w(x)``
of its interpolant (:mod:`.interpolant`), the pruning algorithms (:mod:`.pruning`), the
tables read and checked once (:class:`~.tables.TrainingTables`), projection
(:mod:`.projection`), and the ``.npz`` file (:mod:`.io`).
"""

from __future__ import annotations

import numbers
import os
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import cachetools
import numpy as np

from .._util.blas import one_thread
from .._util.checks import weight_sum
from .._util.float32 import weights32
from .._util.moved import renamed_argument
from .._util.names import is_name
from ..data import gram as gram_mod
from ..data.database import FEATURES, Database, albedo_weights, recorded_spec
from ..errors import FormatError, InputError, did_you_mean
from ..gp.gplvm import FitResult
from ..gp.kernel import Kernel
from ..gp.likelihood import log_likelihood
from . import adding, paths, pruning
from . import interpolant as interpolants
from . import projection as projection_mod
from .file import io as manifold_file
from .file import schema
from .file.fit_record import FitRecord, Timings
from .file.shipped import resolve_manifold
from .presets import (
    PRESETS,
    canonical_order,
    fit_layout,
    make_interpolant,
    settings,
    stress_distances,
    stress_of,
)
from .pruning import DEFAULT_PRUNE, DEFAULT_RULE, RULES, PruneReport
from .tables import TrainingTables

if TYPE_CHECKING:
    from typing import Any

    from .adding import Added
    from .projection import Projection


#: Names other modules import from here (the presets, the pruning default, the result types).
__all__ = [
    "Manifold",
    "Weights",
    "Pruned",
    "Combination",
    "FitRecord",
    "PRESETS",
    "DEFAULT_PRUNE",
    "DEFAULT_RULE",
    "PruneReport",
    "FORMAT_VERSION",
    "settings",
    "fit_layout",
    "make_interpolant",
    "InputError",
    "is_name",
]

FORMAT_VERSION = manifold_file.FORMAT_VERSION

#: Answers of :meth:`Manifold.prune` kept (the newest): the explorer prunes each point for its
#: frame, its table and its description.
PRUNE_MEMO = 8


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


@dataclass
class DatabaseFit:
    """What :func:`fit_database` learned: the layout, the record, and the tables' statistics."""

    names: list
    hashes: list
    result: FitResult
    record: FitRecord
    gram: np.ndarray
    table_gram: np.ndarray
    albedos: np.ndarray
    tables: np.ndarray
    cos_gram: np.ndarray = None


def fit_database(db, names, cfg, preset, init=None, progress=False, **options) -> DatabaseFit:
    """Fit the materials ``names`` (default all) of :class:`Database` ``db`` with settings ``cfg``
    (:func:`presets.settings` of ``preset``); ``options`` go to :func:`gplvm.fit_latent`.

    Reads the tables once, computes in one pass over them the Gram matrix ``S`` of the fit's
    features, the raw tables' ``T T^T``, their cosine-weighted ``T diag(q) T^T`` (pruning,
    :mod:`.pruning`) and the albedos (``q``: :func:`albedo_weights`), fits the GPLVM layout
    of the settings (:func:`presets.fit_layout`) and records what it did (:class:`FitRecord`).
    """
    names = db.names if names is None else list(names)
    if len(names) < 2:
        raise InputError("a manifold needs at least 2 materials")
    t0 = time.perf_counter()
    tables = db.stack(names, progress=progress)
    t_load = time.perf_counter() - t0
    if cfg["features"] not in FEATURES:
        raise FormatError(f"`features` must be one of {FEATURES}, got {cfg['features']!r}")
    t0 = time.perf_counter()
    g = gram_mod.gram(
        tables, cfg["features"], centre=True, raw=True, weights=albedo_weights(db.dims).reshape(-1)
    )
    stress = stress_of(cfg)
    with one_thread():  # the same sums, whatever the number of BLAS threads
        distances = stress_distances(tables, db.dims) if stress.active else None
    t_gram = time.perf_counter() - t0  # with the stress term's distances
    hashes = db.hashes(names)
    result = fit_layout(
        g.S,
        tables.shape[1],
        cfg,
        init=init,
        distances=distances,
        order=canonical_order(hashes, names),
        **options,
    )
    extra = {}
    if stress.active:  # the stress term's settings and outcome, in the saved info
        extra = {
            "stress": stress.weight,
            "stress_neighbours": stress.neighbours,
            "stress_value": float(result.stress),
        }
    record = FitRecord(
        method=cfg["method"],
        preset=preset,
        q=int(cfg["q"]),
        d=int(tables.shape[1]),
        dims=db.dims,
        log_likelihood=float(result.log_likelihood),
        n_evaluations=int(result.n_evaluations),
        converged=bool(result.converged),
        n_iterations=int(result.n_iterations),
        grad_norm=None if result.grad_norm is None else float(result.grad_norm),
        stop=str(result.message),
        history=result.history,
        timings=Timings(t_load, t_gram, float(result.time_s)),
        extra=extra,
    )
    return DatabaseFit(
        names,
        hashes,
        result,
        record,
        g.S,
        g.raw,
        g.sums,
        tables,
        g.weighted,
    )


def _stored(name, doc):
    """A property of the manifold's :class:`TrainingTables` attribute ``name``, set as float64."""

    def set_(self, value) -> None:
        self._store.set_matrix(name, value)
        with self._pruned_lock:  # pruning answers made with the old matrices
            self._pruned.clear()

    return property(lambda self: getattr(self._store, name), set_, doc=doc)


class Manifold:
    """A fitted latent space of measured materials (scikit-learn style: fit, then use).

    The constructor takes the whole learned state of a manifold (14 parameters, the last six
    keyword-only): :meth:`fit` and :meth:`load` make one (``Manifold.load("merl")``: the shipped
    default), a user rarely does.

    Parameters
    ----------
    names, latent, database, hashes
        See the attributes.
    length_scale, noise : float
        The kernel's hyperparameters ``l`` and ``mu`` (:attr:`kernel`).
    features : {"raw", "log"}
    albedos : (N, 3) array, optional
    gram, table_gram, cos_gram : (N, N) arrays, optional
        See the attributes.
    interpolant : dict, optional
        The weight function's parameters (default the paper's GP weights on ``l`` and ``mu``).
    record : FitRecord, optional
        What the fit did (default: nothing recorded).
    added : list of adding.Provenance or dict, optional
        Where the materials added after the fit (:meth:`add`) came from.

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
    kernel : gp.kernel.Kernel
        The covariance function (``length_scale`` and ``noise``, also attributes here).
    features : str
        Feature transform used for the fit only (``raw`` or ``log``).
    albedos : ndarray (N, 3) or None
        Bihemispherical albedo of each material (for :meth:`albedo` and pruning; computed
        from the tables when pruning needs it and it is absent).
    gram : ndarray (N, N) or None
        ``S = Z Z^T`` the latent points were fit to (:meth:`log_likelihood`, Eq. 7's ``|Z|``).
    table_gram : ndarray (N, N) or None
        ``T T^T`` of the raw tables (exact "raw-l2" pruning errors); computed on first use when absent.
    cos_gram : ndarray (N, N) or None
        ``T diag(q) T^T``, ``q`` each bin's ``cos(theta_i) cos(theta_o) dw_i dw_o`` (exact "image"
        pruning errors, :mod:`.pruning`); computed on first use when absent.
    interpolant : interpolant.Interpolant
        The weight function ``w(x)``.
    record : FitRecord
        What the fit did: method, preset, ``d``, ``dims``, final log-likelihood, history, timings.
    added : list of adding.Provenance
        The materials placed by :meth:`add` after the fit (the last ``len(added)`` names), with
        where each table came from and the file (and its SHA-256) the manifold reads it from.
    """

    def __init__(  # noqa: PLR0913  one parameter per attribute, as load() reads them back
        self,
        names,
        latent,
        database,
        hashes,
        length_scale=1.0,
        noise=1e-4,
        features="raw",
        albedos=None,
        *,
        gram=None,
        table_gram=None,
        cos_gram=None,
        interpolant=None,
        record=None,
        added=None,
    ) -> None:
        """The manifold's learned state, one parameter per attribute (see the class): the
        fields :meth:`load` reads back from a saved manifold.
        """
        latent = np.asarray(latent, dtype=np.float64)
        if latent.ndim != 2 or latent.shape[0] != len(names):
            raise InputError(
                f"latent points must have shape (N={len(names)}, q), got {latent.shape}"
            )
        if not np.isfinite(latent).all():
            raise InputError("latent points contain NaN or Inf")
        if features not in FEATURES:
            raise InputError(
                f"unknown feature transform `features` = {features!r}; use one of {FEATURES}"
            )
        self.names = list(names)
        self.latent = latent
        self.database = os.fspath(database)
        self.hashes = list(hashes)
        self.kernel = Kernel(length_scale, noise)
        self.features = features
        self.gram = None if gram is None else np.asarray(gram, dtype=np.float64)
        self.record = record or FitRecord()
        self.added = [
            a if isinstance(a, adding.Provenance) else adding.Provenance.from_dict(a)
            for a in added or ()
        ]
        self._store = TrainingTables(
            self.names,
            self.hashes,
            table_gram,
            cos_gram,
            albedos,
            {a.name: a.path for a in self.added},
        )
        self._pruned: cachetools.FIFOCache
        self._pruned, self._pruned_lock = cachetools.FIFOCache(PRUNE_MEMO), threading.Lock()
        self.interpolant = make_interpolant(
            self.latent,
            {
                "length_scale": self.length_scale,
                "noise": self.noise,
                "interpolant": interpolant or {"kind": "gp", "exact": True},
            },
        )
        ip = self.interpolant
        if isinstance(ip, interpolants.ShepardWeights):  # its continuation beyond the data
            ip.attach(self)
        same = isinstance(ip, interpolants.GaussianProcessWeights) and ip.gp.kernel == self.kernel
        self._gp = (
            ip.gp if same else interpolants.posterior(self.latent, self.kernel)
        )  # K factorised once

    # ------------------------------------------------------------------ fit
    @classmethod
    def fit(  # noqa: PLR0913  the fit's settings as keywords, scikit-learn style
        cls,
        database,
        *,
        q=None,
        names=None,
        method=None,
        length_scale=None,
        noise=None,
        features=None,
        init=None,
        progress=False,
        preset="default",
        interpolant=None,
        stress=None,
        stress_neighbours=None,
        **options,
    ) -> Manifold:
        """Fit latent points to the tables of ``database`` (paper Sec. 3).

        ``Manifold.fit(database)`` fits the default preset; ``preset="paper"`` the paper's
        exact formulation. Any other argument given overrides the preset's value.

        Parameters
        ----------
        database : Database or path
        q : int
            Latent dimension (1 to 8).
        names : list of str, optional
        method : {"newton", "lbfgs", "hooke-jeeves"}
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
        stress : float
            Weight ``lambda >= 0`` of the layout's stress term towards the tables' perceptual
            distances (:mod:`gp.stress`, :func:`presets.stress_distances`; needs
            ``method="newton"`` or ``"lbfgs"``); 0: none. Saved in :attr:`info` when on.
        stress_neighbours : int, optional
            The pairs the stress term covers: each material with its ``k`` perceptually nearest;
            None: every pair.
        **options
            The optimiser's ``max_iter``, ``tol``, ``initial_step`` (:func:`gplvm.optimiser_options`)
            and the fit's ``callback`` (:meth:`gplvm.GPLVM.fit`).
        """
        cfg = settings(
            preset,
            q=q,
            method=method,
            length_scale=length_scale,
            noise=noise,
            features=features,
            interpolant=interpolant,
            stress=stress,
            stress_neighbours=stress_neighbours,
        )
        if isinstance(names, str):  # "chrome, steel": the names of a comma-separated list
            names = [n.strip() for n in names.split(",") if n.strip()]
        db = database if isinstance(database, Database) else Database(database, names)
        if int(np.prod(db.dims)) < 2:
            raise InputError(
                f"database {db.folder}: tables of {'x'.join(map(str, db.dims))} bins "
                "hold one value per channel, too little to place materials apart; use "
                "tables of more bins (MERL's are 90x90x180; tools/make_database.py "
                "--resolution 16,16,32 for a quick one)"
            )
        f = fit_database(db, names, cfg, preset, init=init, progress=progress, **options)
        same = schema.coincident_latent(f.result.latent, f.hashes, f.names, cfg["length_scale"])
        if same:
            raise InputError(
                f"database {db.folder}: the fit placed the different materials "
                f"{same[0]!r} and {same[1]!r} at one latent point (their tables are "
                "too alike for the fit to tell apart); leave one of them out "
                "(`names`) or use tables of more bins"
            )
        m = cls(
            f.names,
            f.result.latent,
            db.folder,
            f.hashes,
            cfg["length_scale"],
            cfg["noise"],
            cfg["features"],
            f.albedos,
            gram=f.gram,
            record=f.record,
            interpolant=cfg["interpolant"],
            table_gram=f.table_gram,
            cos_gram=f.cos_gram,
        )
        m._tables = f.tables
        return m

    # ------------------------------------------------------------ learned state
    @property
    def length_scale(self) -> float:
        """The kernel's length scale ``l``."""
        return self.kernel.length_scale

    @property
    def noise(self) -> float:
        """The kernel's noise ``mu``."""
        return self.kernel.noise

    @property
    def K(self) -> np.ndarray:
        """Covariance matrix of the latent points (:class:`gp.posterior.Posterior`)."""
        return self._gp.K

    @property
    def history(self) -> np.ndarray:
        """Log-likelihood per optimiser iteration (:attr:`record`)."""
        return self.record.history

    @property
    def info(self) -> dict:
        """The fit's record as the saved ``info`` dict (a new dict: assign one to replace it)."""
        return self.record.as_info()

    @info.setter
    def info(self, value) -> None:
        self.record = FitRecord.from_info(value, self.record.history)

    @property
    def dims(self) -> tuple[int, int, int]:
        """Table resolution ``(n_theta_h, n_theta_d, n_phi_d)`` of the fit (None if not recorded)."""
        return self.record.dims

    @property
    def _tables(self) -> np.ndarray | None:
        return self._store.loaded

    @_tables.setter
    def _tables(self, tables) -> None:
        self._store.loaded = tables

    @property
    def q(self) -> int:
        """Latent dimension."""
        return self.latent.shape[1]

    @property
    def n(self) -> int:
        """Number of materials."""
        return len(self.names)

    # ------------------------------------------------------------- weights
    def _points(self, x) -> tuple[np.ndarray, bool]:
        return interpolants.points(x, self.q)

    def weights(self, x) -> Weights:
        """Weights of the interpolant at ``x`` ((q,) or (M, q)): a :class:`Weights` ``(b, w)``,
        each (N,) or (M, N); ``w`` sums to 1 and ``sum_i w_i table_i = mean + b^T Z`` exactly.

        For the paper's GP weights ``b`` is Eq. 4's ``K_inv k(x)`` (at a training point the
        noise term ``mu delta(x, x_i)`` applies, so ``w = e_i``); for other interpolants
        ``b = w - 1/N``.
        """
        x, single = self._points(x)
        b, w = self.interpolant.b_and_w(x)
        return Weights(b[0], w[0]) if single else Weights(b, w)

    def weights_jacobian(self, x) -> np.ndarray:
        """``dw/dx`` of the interpolant, analytic: ``(N, q)`` for one point, ``(M, N, q)`` for M.

        GP weights: ``(I - 1 1^T / N) K_inv dk/dx`` (Eq. 4 differentiated; at a training point
        the smooth part's). Shepard: :class:`interpolant.ShepardWeights`. Columns sum to 0.
        """
        x, single = self._points(x)
        J = self.interpolant.jacobian(x)
        return J[0] if single else J

    def variance(self, x) -> np.ndarray:
        """GP predictive variance (paper Eq. 2): ``c(x, x) - k^T K_inv k``."""
        x, single = self._points(x)
        v = self._gp.variance(x)
        return v[0] if single else v

    def variance_gradient(self, x) -> np.ndarray:
        """Gradient of the smooth part of :meth:`variance`: ``-2 (dk/dx)^T K_inv k``, (q,) or (M, q)."""
        x, single = self._points(x)
        g = self._gp.variance_gradient(x)
        return g[0] if single else g

    def material_weights(self, name) -> np.ndarray:
        """One-hot weights of a training material."""
        w = np.zeros(self.n)
        w[self.index(name)] = 1.0
        return w

    def index(self, name) -> int:
        """Position of material ``name``; :class:`InputError` with the closest names otherwise."""
        try:
            return self.names.index(name)
        except ValueError:
            n, names = self.n, self.names
            raise InputError(
                f"unknown material {name!r}{did_you_mean(name, names)}: this manifold has {n} "
                f"materials ({', '.join(names[:6])}{', ...' if n > 6 else ''})"
            ) from None

    def point(self, x, what="`x`") -> np.ndarray:
        """One latent point ``(q,)`` float64 from a material's name (its latent point) or ``q``
        numbers (a sequence, an array or text ``"0.3, -1.2"``); ``what`` names the parameter in
        the messages. A word that does not start like a number is a name.
        """
        from .._util.checks import latent_point

        if isinstance(x, str) and is_name(x):
            return self.latent[self.index(x.strip())].astype(np.float64)
        return latent_point(what, x, self.q)

    def parse_weights(self, text) -> np.ndarray:
        """Weights of a combination of the training materials (``sum_i w_i table_i``, paper
        Eq. 4) from ``"name:w, name:w"`` (unnamed materials get 0), ``(N,)`` float64.

        Raises
        ------
        InputError
            Unknown names, a name given twice, malformed entries, non-finite values or weights
            summing to 0.
        """
        w, seen = np.zeros(self.n), set()
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
                raise InputError(
                    f"weights {text!r}: entry {e!r} is not 'name:number' (commas separate entries)"
                )
            i = self.index(name.strip())
            if i in seen:
                raise InputError(
                    f"weights {text!r}: {self.names[i]} is named twice; give each material once "
                    "with its whole weight"
                )
            seen.add(i)
            w[i] = v
        try:
            weight_sum(w)
        except InputError as e:
            raise InputError(f"weights {text!r}: {e}") from None
        return w

    # ------------------------------------------------------- tables, interpolation
    def open_database(self, folder=None, names=None) -> Database:
        """The database of this manifold (or ``folder``), checked against the recorded hashes.

        Only the materials in ``names`` (default: all) are read and checked.
        """
        if names is not None:
            names = list(names)
            for name in names:
                self.index(name)  # an unknown name: InputError with the closest ones
        return self._store.open(self._source(folder), names)

    def _source(self, database=None) -> str:
        """``database`` (a user's), else the recorded one, opened as recorded (a set's name is the
        set whatever the current folder holds: :func:`~..data.database.recorded_spec`).
        """
        return database or recorded_spec(self.database)

    def tables(self, database=None) -> np.ndarray:
        """All N tables in memory as float32 ``(N, d)`` (loaded once, then kept)."""
        return self._store.stack(self._source(database))

    def interpolate(self, x, prune=DEFAULT_PRUNE, database=None, rule=DEFAULT_RULE) -> Combination:
        """The interpolated table at latent point ``x``; see :meth:`combine` for the outputs."""
        if np.ndim(x) > 1:
            raise InputError(
                f"interpolate takes one latent point ({self.q} numbers), got shape {np.shape(x)}; "
                "call it once per point"
            )
        _, w = self.weights(x)
        return self.combine(w, prune, database, rule)

    def negative_fraction(self, x, prune=DEFAULT_PRUNE, database=None) -> float:
        """Fraction of the interpolated table's values below 0 at ``x``.

        ``manifold_brdf`` clamps them to 0, a blend of images cannot: where this is not
        small, a blend and a render of the material differ by more than L2+.
        """
        table, _, _ = self.interpolate(x, prune, database)
        return float((table < 0).mean())

    def mean(self, database=None) -> np.ndarray:
        """The mean table (the far-field limit of the interpolant)."""
        return self.combine(np.full(self.n, 1.0 / self.n), prune=0.0, database=database)[0]

    def albedo(self, x) -> np.ndarray:
        """Bihemispherical albedo (RGB) of the interpolated material, by linearity."""
        if self.albedos is None:
            raise InputError("this manifold has no per-material albedos")
        _, w = self.weights(x)
        return w @ self.albedos

    def project(self, table, *, beyond=False, **options) -> Projection:
        """The latent point whose material is closest to ``table`` (any MERL table).

        ``table``: a reflectance table of this manifold's resolution (as :meth:`Database.reflectance`,
        or flat), or a material as the tools take one (:func:`~mitsuba_manifold.data.sources.material_source`):
        a MERL ``.binary`` file, a Mitsuba ``measured`` ``.bsdf`` file (after ``import
        mitsuba_manifold.render``, which reads them), an NBRDF ``.h5`` or ``.npz`` file, or
        ``SET:NAME`` of a built-in set (``"rgl:paper_white"``); ``options`` go to :func:`projection.project`.
        Returns a :class:`projection.Projection`: ``x``, ``error`` (RMS of ``log(1 + rho)``
        differences over all bins), ``weights``, the nearest training material and its error.

        ``beyond=True`` also finds the best *plausible* combination beyond the data
        (:func:`projection.beyond`: weights outside the simplex, no negative bin, directional
        albedo at most 1 at every incidence), in :attr:`Projection.beyond`: its ``weights``
        render with ``manifold_brdf``'s ``weights`` and blend like any others.
        """
        table = projection_mod.as_table(table, 3 * int(np.prod(self.dims or (0,))), self.dims)
        p = projection_mod.project(
            self.interpolant, self.tables(), table, names=self.names, **options
        )
        if beyond:
            p = projection_mod.beyond(p, self.tables(), table, dims=self.dims)
        return p

    def add(self, table_or_path, name=None, *, origin=None) -> Added:
        """Place a new measured material in this manifold without a refit (:mod:`.adding`).

        Its latent point maximises the GPLVM likelihood (paper Eq. 6) of all N + 1 tables with
        the fitted points held, started next to its closest materials; the other points, the
        kernel and the interpolant's parameters stay as they are, and the new material is
        reproduced exactly at its point. The manifold changes in place once everything is
        computed (nothing changes on an error); :meth:`save` then writes it with the
        material's :class:`adding.Provenance`.

        Parameters
        ----------
        table_or_path : path, str or array
            A MERL ``.binary`` file of this manifold's resolution (read from where it is, and
            checked by its SHA-256 whenever read again); any other material as the tools take
            one (:func:`~mitsuba_manifold.data.sources.material_source`: a ``.bsdf`` file after
            ``import mitsuba_manifold.render``, an ``.h5`` or ``.npz`` network, ``SET:NAME``),
            tabulated at this manifold's resolution; or a reflectance table (1/sr,
            ``(3,) + dims`` or flat). A table that is not a ``.binary`` file is written as
            one into the database's cache.
        name : str, optional
            The material's name (default: the file's name without its extension and a
            trailing ``_rgb``/``_spec``, as in a database folder; ``NAME`` of ``SET:NAME``).
        origin : str, optional
            What the table is, kept in the provenance (default for a source other than a
            ``.binary`` file: its absolute path, or ``SET:NAME``).

        Returns
        -------
        adding.Added
            The name, latent point ``x``, provenance, the closest training material, the
            log-likelihood of the N + 1 points and the time taken.
        """
        kwargs, tables, info = adding.add(self, table_or_path, name, origin=origin)
        grown = type(self)(**kwargs)
        grown._tables = tables
        file = getattr(self, "file", None)
        self.__dict__.update(grown.__dict__)
        if isinstance(self.interpolant, interpolants.ShepardWeights):  # its limit: this manifold
            self.interpolant.attach(self)
        if file is not None:
            self.file = file
        return info

    # ------------------------------------------------------------- pruning
    table_gram = _stored("gram", "``T T^T`` of the raw tables (:attr:`TrainingTables.gram`).")
    cos_gram = _stored("cos_gram", "``T diag(q) T^T`` (:attr:`TrainingTables.cos_gram`).")
    albedos = _stored(
        "albedos", "Albedo of each material, (N, 3) (:attr:`TrainingTables.albedos`)."
    )

    def table_norms(self) -> np.ndarray:
        """L2 norm of each raw table (from :attr:`table_gram`)."""
        return np.sqrt(np.maximum(np.diag(self._store.raw_gram(self._source())), 0.0))

    def _checked(self, w, budget, rule) -> np.ndarray:
        w = np.asarray(w, dtype=np.float64)
        n = self.n
        if w.shape != (n,) or not np.isfinite(w).all():
            raise InputError(f"weights must be {n} finite values, got shape {w.shape}")
        if (
            isinstance(budget, (bool, np.bool_))
            or not isinstance(budget, numbers.Real)
            or not 0 <= budget < 1
        ):
            raise InputError(f"`prune` must be in [0, 1), got {budget!r}")
        if rule not in RULES:
            raise InputError(f"`rule` must be one of {', '.join(map(repr, RULES))}, got {rule!r}")
        return w

    def prune(self, w, prune=DEFAULT_PRUNE, rule=DEFAULT_RULE) -> Pruned:
        """Materials kept by pruning weights ``w`` within the budget ``prune`` under ``rule``.

        ``rule="image"`` (the default): each albedo channel changes by at most
        ``pruning.ALBEDO_SHARE * prune``, the cosine-weighted table by at most ``prune`` of its
        norm and the raw table by at most ``pruning.RAW_SHARE * prune`` of its L2 norm
        (:func:`pruning.prune_image`). ``"raw-l2"``: the raw table by at most ``prune``
        of its L2 norm (:func:`pruning.prune`). The kept weights
        are rescaled to sum to ``sum(w)`` so the combination stays affine; the changes are
        computed exactly from Gram matrices, rescaling included; ``prune = 0`` keeps every
        non-zero weight.

        Returns
        -------
        Pruned
            ``keep`` (ndarray of int), ``w_kept`` (ndarray), ``dropped`` (float: sum of
            ``|w_i|`` over the dropped materials).
        """
        hit = self._prune(self._checked(w, prune, rule), float(prune), rule)
        return Pruned(
            hit.keep.copy(), hit.w_kept.copy(), hit.dropped
        )  # the caller may change its arrays

    @cachetools.cachedmethod(
        lambda self: self._pruned,  # the newest answers, cleared when a matrix is set
        key=lambda self, w, budget, rule: (w.tobytes(), budget, rule, self.database),
        lock=lambda self: self._pruned_lock,
    )
    def _prune(self, w, budget, rule) -> Pruned:
        folder, store = self._source(), self._store
        if rule == "raw-l2":
            return Pruned(*pruning.prune(w, store.raw_gram(folder), budget))
        return Pruned(
            *pruning.prune_image(
                w,
                store.cosine_gram(folder),
                store.albedo(folder),
                budget,
                G=store.raw_gram(folder),
            )
        )

    def prune_error(self, w, keep, rule=DEFAULT_RULE) -> float:
        """Relative L2 change of the table ``sum w_i table_i`` when only ``keep`` is kept (rescaled),
        in the norm ``rule`` bounds: cosine-weighted (``"image"``) or raw (``"raw-l2"``).
        """
        w = self._checked(w, 0.0, rule)
        folder, store = self._source(), self._store
        return pruning.error(
            w, keep, store.raw_gram(folder) if rule == "raw-l2" else store.cosine_gram(folder)
        )

    def prune_report(self, w, prune=DEFAULT_PRUNE, rule=DEFAULT_RULE, keep=None) -> PruneReport:
        """What :meth:`prune` keeps and the bounds it reaches: a :class:`pruning.PruneReport` (materials
        kept and their names, albedo change per channel, cosine-weighted and raw table errors,
        the budgets; ``str()`` of it is one line for ``print(bsdf)`` and the explorer). ``keep``:
        what :meth:`prune` kept of the same ``w`` (not pruned again).
        """
        keep = self.prune(w, prune, rule).keep if keep is None else keep
        folder, store = self._source(), self._store
        return pruning.report(
            w,
            keep,
            rule,
            prune,
            G=store.raw_gram(folder),
            C=store.cosine_gram(folder),
            albedos=store.albedo(folder),
            names=self.names,
        )

    def combine(self, w, prune=DEFAULT_PRUNE, database=None, rule=DEFAULT_RULE) -> Combination:
        """The table ``sum_i w_i table_i`` over the materials kept by :meth:`prune`: a
        :class:`Combination` ``(table (3, n_theta_h, n_theta_d, n_phi_d) float32, keep, dropped)``.

        Uses the tables in memory when they are (and ``database`` is None): one matrix-vector
        product over the contiguous ``(N, d)`` stack when more than half the materials are kept,
        else a sum over the kept rows; otherwise reads only the kept ones from ``database``
        (default the manifold's). The weights are float32 with subnormal values set to 0
        (:func:`~mitsuba_manifold._util.float32.weights32`).
        """
        keep, w_kept, dropped = self.prune(w, prune, rule)
        w32 = weights32(w_kept)
        loaded = self._store.loaded
        if loaded is not None and database is None and self.dims is not None:
            shape = (3,) + tuple(self.dims)
            if 2 * len(keep) > self.n:  # one (multithreaded) matrix-vector product over all tables
                full = np.zeros(self.n, dtype=np.float32)
                full[keep] = w32
                return Combination((full @ loaded).reshape(shape), keep, dropped)
            flat = pruning.weighted_sum((loaded[i] for i in keep), w32, loaded.shape[1])
            return Combination(flat.reshape(shape), keep, dropped)
        db = self._store.open(self._source(database), [self.names[i] for i in keep])
        flat = pruning.weighted_sum(
            (db.reflectance(self.names[i]).reshape(-1) for i in keep),
            w32,
            3 * int(np.prod(db.dims)),
        )
        return Combination(flat.reshape((3,) + db.dims), keep, dropped)

    # ----------------------------------------------------------- diagnostics
    def condition_number(self) -> float:
        """2-norm condition number of K."""
        return self._gp.condition_number()

    def bound_terms(self, x) -> dict[str, Any]:
        """Terms of the paper's Eq. 7 bound on ``|z(x) - z_j|`` for the nearest latent point j.

        ``|z(x) - z_j| <= e^{-1/2} sqrt(2N) / l * cond(K) * |Z|_F * |x - x_j|`` with ``j`` the
        nearest latent point; ``|Z|_F`` from the Gram matrix (NaN without it). Returns a dict
        (``nearest``, ``distance``, ``constant``, ``cond_K``, ``Z_norm``, ``bound``) of arrays
        (M,) and scalars for points (M, q), of scalars for one point (q,).
        """
        x, single = self._points(x)
        dist = np.linalg.norm(x[:, None, :] - self.latent[None], axis=-1)
        j = dist.argmin(axis=1)
        const = np.exp(-0.5) * np.sqrt(2 * self.n) / self.length_scale
        gram = self.gram
        z_norm = float(np.sqrt(max(np.trace(gram), 0.0))) if gram is not None else float("nan")
        near = dist[np.arange(len(x)), j]
        cond_K = self.condition_number()
        out = {
            "nearest": j,
            "distance": near,
            "constant": const,
            "cond_K": cond_K,
            "Z_norm": z_norm,
            "bound": const * cond_K * z_norm * near,
        }
        if single:
            out = {k: (v[0] if isinstance(v, np.ndarray) else v) for k, v in out.items()}
        return out

    def log_likelihood(self) -> float:
        """Paper Eq. 6 at the stored latent points (needs the Gram matrix)."""
        if self.gram is None or self.record.d is None:
            raise InputError("this manifold was saved without its Gram matrix")
        return log_likelihood(self.latent, self.gram, self.record.d, self.length_scale, self.noise)

    def discontinuity(self) -> float:
        """Largest jump of the weights when leaving a training point, ``max_i |w(x_i+) - e_i|_1``.

        See :meth:`interpolant.Interpolant.jump`: up to ~2 for the paper's GP weights when
        latent points are close compared with ``l``, ~0 for the continuous Shepard weights.
        """
        return self.interpolant.jump()

    def coincident(self, tol=1e-2) -> list:
        """Materials whose nearest latent point lies within ``tol * l`` (indistinguishable to the GP).

        Interpolating between such materials is not possible: near them the weights spread
        over the whole group. A fit on ``raw`` features collapses materials whose tables differ
        little compared with the spikiest ones; ``features="log"`` separates them.
        """
        latent = self.latent
        d2 = ((latent[:, None] - latent[None]) ** 2).sum(-1)
        np.fill_diagonal(d2, np.inf)
        close = np.sqrt(d2.min(axis=1)) < tol * self.length_scale
        return [self.names[i] for i in np.flatnonzero(close)]

    def summary(self) -> str:
        """Short human-readable description (what the tools print after a fit)."""
        rec = self.record
        params = ", ".join(
            f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
            for k, v in self.interpolant.params().items()
            if k not in ("kind", "length_scale", "noise")
        )
        lines = [
            f"Manifold: {self.n} materials, q={self.q}, l={self.length_scale:g}, "
            f"mu={self.noise:g}, features={self.features}, preset={rec.preset or 'paper'}",
            f"  interpolant: {self.interpolant.kind}" + (f" ({params})" if params else ""),
            f"  database: {self.database}",
            f"  cond(K) = {self.condition_number():.3g}",
            "  weight jump next to a training point (max |w(x_i+) - e_i|_1): "
            f"{self.discontinuity():.3g}",
        ]
        close = self.coincident()
        if close:
            lines.append(
                f"  warning: {len(close)} materials share their latent point with another (within "
                f"0.01 l), e.g. {', '.join(close[:4])}; interpolation cannot tell them apart"
                + ("; try features='log'" if self.features == "raw" else "")
            )
        if rec.log_likelihood is not None:
            fit_s = rec.timings.fit_s
            took = "" if fit_s is None or not np.isfinite(fit_s) else f", {fit_s:.2f} s"
            lines.append(f"  log-likelihood L = {rec.log_likelihood:.6g} ({rec.method}{took})")
        if rec.method is not None:
            lines.append(f"  fit: {rec.convergence()}")
        if self.info.get("stress"):
            lines.append(
                f"  stress term: weight {self.info['stress']:g}, normalised stress "
                f"{self.info.get('stress_value', float('nan')):.3g} (latent against perceptual "
                "distances)"
            )
        return "\n".join(lines)

    # ------------------------------------------------------------ save/load
    def save(self, file=None, *, path=None) -> None:
        """Write to the ``.npz`` ``file`` (no pickle), atomically (:func:`manifold_file.write`);
        ``path``, its former name, is read with a ``DeprecationWarning``.
        """
        given = {} if path is None else {"path": path}
        manifold_file.write(self, renamed_argument(file, given, "path", "file", "Manifold.save"))

    @classmethod
    def load(cls, file=None, *, path=None) -> Manifold:
        """Read a manifold written by :meth:`save` (:func:`manifold_file.read`); ``file`` may
        also name a shipped manifold (``"merl"``, ``"rgl"``, ``"nielsen"``, ``"all"``:
        :mod:`.shipped`), where no file of that name exists. ``path``, its former name, is read
        with a ``DeprecationWarning``.

        Files of format version 1 load with the paper's GP weights on
        their stored ``l`` and ``mu`` (what they were used with); refit for the default.

        Raises
        ------
        InputError
            Missing, corrupt or foreign files.
        """
        given = {} if path is None else {"path": path}
        file = resolve_manifold(renamed_argument(file, given, "path", "file", "Manifold.load"))
        m = cls(**manifold_file.read(file))
        m.file = file  # where it was read from (``path`` is the method of latent paths)
        return m

    # ------------------------------------------------------------ subsets
    def subset(self, names) -> Manifold:
        """The manifold of materials ``names`` alone, fit again on their Gram matrix.

        The sub-block of this manifold's Gram matrix is centred about the subset's own mean and
        its latent points are fit (Eq. 6) with this manifold's kernel, optimiser, latent
        dimension and stress term (towards the subset's perceptual distances, from its tables);
        the weights come from this manifold's interpolant (its kind and parameters,
        not the GP of Eq. 4 unless that is what this manifold uses). The result is not saved.

        Parameters
        ----------
        names : sequence of str
            Materials of this manifold, at least two, each once.

        Raises
        ------
        InputError
            An unknown or repeated name, fewer than two names, or a manifold without its Gram
            matrix.
        """
        from ..gp import gplvm

        names = list(names)
        keep = [self.index(name) for name in names]
        if len(set(keep)) != len(keep) or len(keep) < 2:
            raise InputError(
                f"a subset needs at least two distinct materials of the manifold, got {names}; "
                "name each material once"
            )
        if self.gram is None:
            raise InputError(
                "this manifold holds no Gram matrix to fit a subset on; refit it with Manifold.fit"
            )
        S = self.gram[np.ix_(keep, keep)]
        J = np.eye(len(keep)) - 1.0 / len(keep)
        S = J @ S @ J
        info = self.info
        stress = gplvm.Stress(info.get("stress", 0.0), info.get("stress_neighbours"))
        distances = None
        if stress.active:
            distances = stress_distances(self.tables()[keep], self.dims)
        method = self.record.method or "hooke-jeeves"
        fit = gplvm.GPLVM(self.q, self.kernel, method, gplvm.optimiser_options(method), stress).fit(
            S, self.record.d, distances=distances
        )
        if stress.active:
            info = {**info, "stress_value": float(fit.stress)}
        table_gram = None if self.table_gram is None else self.table_gram[np.ix_(keep, keep)]
        return type(self)(
            names,
            fit.latent,
            self.database,
            [self.hashes[i] for i in keep],
            self.length_scale,
            self.noise,
            self.features,
            None if self.albedos is None else self.albedos[keep],
            gram=S,
            interpolant=self.interpolant.params(),
            table_gram=table_gram,
            record=FitRecord.from_info(
                {
                    **info,
                    "log_likelihood": float(fit.log_likelihood),
                    "subset_of": getattr(self, "file", None),
                },
                fit.history,
            ),
        )

    # ------------------------------------------------------------ perceptual paths
    def distance(self, x, y, stride=(1, 1, 1)) -> Any:
        """[PR12] distance between the tables ``sum_i w_i table_i`` at ``x`` and ``y`` (names, points
        ``(q,)`` or stacks ``(M, q)``: a float, ``(M,)`` or ``(M, K)``); :func:`paths.latent_distance`.
        """
        return paths.latent_distance(self, x, y, stride)

    def path(self, a, b, steps=21, kind=None) -> np.ndarray:
        """``steps`` latent points from ``a`` to ``b`` of ``kind`` (default the best measured); :func:`paths.path`."""
        return paths.path(self, a, b, steps, kind or paths.DEFAULT_KIND)
