"""The training tables of a manifold: opened and checked, loaded once, pruned and combined.

Every material a manifold gives is ``sum_i w_i table_i`` over its N measured tables (paper
Eq. 4). :class:`TrainingTables` owns what that needs: opening the database the manifold was
fit on (each table checked against the SHA-256 recorded at the fit), the ``(N, d)`` stack
kept in memory once loaded, what pruning measures exactly (:mod:`.pruning`: the raw tables'
Gram matrix ``G = T T^T``, the cosine-weighted ``C = T diag(q) T^T`` and the albedos, each
computed from the tables on first use when a manifold file lacks it),
and the combination itself, reading only the kept tables.
"""

import numbers
import os
from typing import NamedTuple

import numpy as np

from .._util.cache import key_hash, npy_cache
from .._util.fifo_cache import Recent
from ..data import merl
from ..data.database import Database, albedo_weights
from ..data.sources import BinaryFile
from ..errors import FormatError, InputError
from . import materials, pruning, schema
from .pruning import DEFAULT_RULE, RULES

#: Answers of :meth:`TrainingTables.prune` kept (the newest).
PRUNE_MEMO = 8


class Pruned(NamedTuple):
    """:meth:`TrainingTables.prune`: materials kept, their rescaled weights, the ``|w|`` dropped."""

    keep: np.ndarray
    w_kept: np.ndarray
    dropped: float


class Combination(NamedTuple):
    """:meth:`TrainingTables.combine`: the combined table, the materials used, the ``|w|`` dropped."""

    table: np.ndarray
    keep: np.ndarray
    dropped: float


def _float64(a):
    return None if a is None else np.asarray(a, dtype=np.float64)


def stored(name, doc):
    """A property of the owner's ``_store`` (a :class:`TrainingTables`) attribute ``name``, set as float64."""

    def set_(self, value):
        setattr(self._store, name, _float64(value))
        self._store.pruned.clear()  # pruning answers made with the old matrices

    return property(lambda self: getattr(self._store, name), set_, doc=doc)


class WithAdded(Database):
    """A :class:`Database` whose materials ``names`` include tables at other paths (``added``:
    ``{name: path}``); everything else (folder, cache, resolution) is the database ``base``'s.
    """

    def __init__(self, base, names, added):  # noqa: D107 -- no Database.__init__: base is already read
        self.__dict__.update(base.__dict__)
        self.names = list(names)
        self.sources = dict(base.sources)
        for name, path in dict(added).items():
            if not os.path.isfile(path):
                raise InputError(
                    f"the table of added material {name!r}, {path}, does not exist; "
                    "put it back or add the material again"
                )
            dims = merl.read_header(path)
            if tuple(dims) != tuple(self.dims):
                raise FormatError(
                    f"the table of added material {name!r}, {path}, has resolution "
                    f"{tuple(dims)}, the database {self.label} has {tuple(self.dims)}"
                )
            self.sources[name] = BinaryFile(name, path)
        self.sources = {n: self.sources[n] for n in self.names}
        self.files_only = all(s.kind == "binary" for s in self.sources.values())


class TrainingTables:
    """The N tables of materials ``names`` whose files had SHA-256 ``hashes`` at the fit.

    Parameters
    ----------
    names, hashes : list of str
    gram : (N, N) array, optional
        ``T T^T`` of the raw tables (computed from the tables on first use when absent).
    cos_gram : (N, N) array, optional
        ``T diag(q) T^T``, ``q`` the bins' cosine-weighted solid angles (likewise).
    albedos : (N, 3) array, optional
        Bihemispherical albedo of each material (likewise).
    added : dict, optional
        ``{name: path}`` of materials whose tables are files outside the database folder
        (materials added to a fitted manifold, :mod:`.adding`).

    Attributes
    ----------
    gram, cos_gram, albedos : ndarray or None
    loaded : (N, d) float32 ndarray or None
        The stack of all tables, once read (:meth:`stack`).
    """

    def __init__(self, names, hashes, gram=None, cos_gram=None, albedos=None, added=None):
        self.names, self.hashes = names, hashes
        self.added = dict(added or {})
        self.gram, self.cos_gram, self.albedos = (
            _float64(gram),
            _float64(cos_gram),
            _float64(albedos),
        )
        self.loaded = None
        self.pruned = Recent(
            PRUNE_MEMO
        )  # the explorer prunes each point for frame, table and description

    def open(self, folder, names=None):
        """The :class:`Database` in ``folder``, its tables of ``names`` (default all) checked
        against the recorded hashes.
        """
        names = self.names if names is None else list(names)
        base = [n for n in names if n not in self.added]
        try:
            db = Database(folder, base or [n for n in self.names if n not in self.added][:1])
            if len(base) < len(names):
                db = WithAdded(db, names, {n: self.added[n] for n in names if n in self.added})
        except FileNotFoundError as e:
            raise InputError(
                f"database for this manifold: {e} (if it moved, give its folder as `database`)"
            ) from None
        except KeyError as e:
            raise InputError(f"database for this manifold: {e}") from None
        for name in names:
            recorded = self.hashes[materials.index(self.names, name)]
            if db.hash(name) != recorded:
                raise InputError(
                    f"database {db.folder}: table {name!r} differs from the one the manifold was fit on "
                    f"(hash {db.hash(name)[:12]} != {recorded[:12]})"
                )
        return db

    def stack(self, folder):
        """All N tables as float32 ``(N, d)`` (read from ``folder`` once, then kept)."""
        if self.loaded is None:
            db = self.open(folder)
            tables = db.stack(self.names)
            q = np.tile(albedo_weights(db.dims).reshape(-1), 3)  # the same weight in each channel
            wrong = schema.check_grams(tables, self.gram, self.cos_gram, q)
            if wrong:
                raise FormatError(
                    f"the manifold's {wrong} is not the Gram matrix of its tables in {db.folder} "
                    "(the manifold file is damaged); refit it with tools/fit_manifold.py"
                )
            self.loaded = tables
        return self.loaded

    def raw_gram(self, folder):
        """:attr:`gram`, computed from the tables in ``folder`` when the manifold file holds none."""
        if self.gram is None:
            self.gram = pruning.raw_gram(self.stack(folder))
        return self.gram

    def cosine_gram(self, folder):
        """:attr:`cos_gram`, computed from the tables in ``folder`` when absent (with :attr:`gram`
        in the same pass when that is absent too), once per database: cached in its cache
        folder, named by the tables' hashes (a manifold file without it, which
        cannot be rewritten without changing the hash its bases record, reads the tables
        only the first time).
        """
        if self.cos_gram is None:
            db = self.open(folder, self.names[:1])
            n = len(self.names)
            path = os.path.join(
                db.cache_dir, key_hash("cos-gram-v1", *self.hashes, length=40) + ".cosgram-v1.npy"
            )

            def build():
                return np.stack(
                    pruning.cos_grams(self.stack(folder), albedo_weights(db.dims).reshape(-1))
                )

            G, self.cos_gram = npy_cache(
                path, build, shape=(2, n, n), dtype=np.float64, finite=True
            )
            if self.gram is None:
                self.gram = np.array(G)
            self.cos_gram = np.array(self.cos_gram)
        return self.cos_gram

    def albedo(self, folder):
        """:attr:`albedos`, computed from the tables in ``folder`` when absent."""
        if self.albedos is None:
            db = self.open(folder, self.names[:1])
            self.albedos = np.asarray(
                db.albedo(self.names, tables=self.stack(folder)), dtype=np.float64
            )
        return self.albedos

    def _checked(self, w, budget, rule):
        w = np.asarray(w, dtype=np.float64)
        n = len(self.names)
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

    def prune(self, w, budget, folder, rule=DEFAULT_RULE):
        """Materials kept by pruning weights ``w`` within ``budget`` under ``rule``.

        ``"image"`` (the default): each albedo channel changes by at most
        ``pruning.ALBEDO_SHARE * budget``, the cosine-weighted table by at most ``budget`` of its
        norm and the raw table by at most ``pruning.RAW_SHARE * budget`` of its L2 norm
        (:func:`pruning.prune_image`). ``"raw-l2"``: the raw table by at most ``budget``
        of its L2 norm (:func:`pruning.prune`). The kept weights
        are rescaled to sum to ``sum(w)`` so the combination stays affine; the changes are
        computed exactly from Gram matrices, rescaling included; ``budget = 0`` keeps every
        non-zero weight.

        Returns
        -------
        Pruned
            ``keep`` (ndarray of int), ``w_kept`` (ndarray), ``dropped`` (float: sum of
            ``|w_i|`` over the dropped materials).
        """
        w = self._checked(w, budget, rule)
        key = (w.tobytes(), float(budget), rule, None if folder is None else os.fspath(folder))
        hit = self.pruned.get(
            key, lambda: self._prune(w, budget, folder, rule)
        )  # cleared when a matrix is set
        return Pruned(
            hit.keep.copy(), hit.w_kept.copy(), hit.dropped
        )  # the caller may change its arrays

    def _prune(self, w, budget, folder, rule):
        if rule == "raw-l2":
            return Pruned(*pruning.prune(w, self.raw_gram(folder), budget))
        return Pruned(
            *pruning.prune_image(
                w, self.cosine_gram(folder), self.albedo(folder), budget, G=self.raw_gram(folder)
            )
        )

    def error(self, w, keep, folder, rule=DEFAULT_RULE):
        """The relative L2 change of the table in the norm of ``rule`` (cosine-weighted for
        ``"image"``, raw for ``"raw-l2"``) when only ``keep`` is kept (rescaled).
        """
        w = self._checked(w, 0.0, rule)
        return pruning.error(
            w, keep, self.raw_gram(folder) if rule == "raw-l2" else self.cosine_gram(folder)
        )

    def report(self, w, budget, folder, rule=DEFAULT_RULE, keep=None):
        """:class:`pruning.PruneReport` of :meth:`prune`: what was kept, the albedo change of each
        channel and the cosine-weighted and raw table errors reached (``keep``: what :meth:`prune`
        kept of the same ``w``, when the caller has it, instead of pruning again).
        """
        keep = self.prune(w, budget, folder, rule).keep if keep is None else keep
        return pruning.report(
            w,
            keep,
            rule,
            budget,
            G=self.raw_gram(folder),
            C=self.cosine_gram(folder),
            albedos=self.albedo(folder),
            names=self.names,
        )

    def combine(self, w, budget, folder, dims, database=None, rule=DEFAULT_RULE):
        """The table ``sum_i w_i table_i`` of shape ``(3,) + dims`` over the materials :meth:`prune` keeps.

        Uses the tables in memory when they are (and ``database`` is None); otherwise reads
        only the kept ones from ``database`` (default ``folder``).
        """
        keep, w_kept, dropped = self.prune(w, budget, folder, rule)
        n = len(self.names)
        if self.loaded is not None and database is None and dims is not None:
            shape = (3,) + tuple(dims)
            if 2 * len(keep) > n:  # one (multithreaded) matrix-vector product over all tables
                full = np.zeros(n, dtype=np.float32)
                full[keep] = w_kept
                return Combination((full @ self.loaded).reshape(shape), keep, dropped)
            flat = pruning.weighted_sum(
                (self.loaded[i] for i in keep), w_kept, self.loaded.shape[1]
            )
            return Combination(flat.reshape(shape), keep, dropped)
        db = self.open(database or folder, [self.names[i] for i in keep])
        flat = pruning.weighted_sum(
            (db.reflectance(self.names[i]).reshape(-1) for i in keep),
            w_kept,
            3 * int(np.prod(db.dims)),
        )
        return Combination(flat.reshape((3,) + db.dims), keep, dropped)
