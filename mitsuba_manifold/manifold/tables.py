"""The training tables of a manifold: opened and checked, loaded once, pruned and combined.

Every material a manifold gives is ``sum_i w_i table_i`` over its N measured tables (paper
Eq. 4). :class:`TrainingTables` owns what that needs: opening the database the manifold was
fit on (each table checked against the SHA-256 recorded at the fit), the ``(N, d)`` stack
kept in memory once loaded, the raw tables' Gram matrix ``G = T T^T`` for exact pruning
errors (:mod:`.pruning`), and the combination itself, reading only the kept tables.
"""

from typing import NamedTuple

import numpy as np

from . import materials, pruning
from ..data.database import Database
from ..errors import InputError


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


class TrainingTables:
    """The N tables of materials ``names`` whose files had SHA-256 ``hashes`` at the fit.

    Parameters
    ----------
    names, hashes : list of str
    gram : (N, N) array, optional
        ``T T^T`` of the raw tables (computed from the tables on first use when absent).

    Attributes
    ----------
    gram : ndarray or None
    loaded : (N, d) float32 ndarray or None
        The stack of all tables, once read (:meth:`stack`).
    """

    def __init__(self, names, hashes, gram=None):
        self.names, self.hashes = names, hashes
        self.gram = None if gram is None else np.asarray(gram, dtype=np.float64)
        self.loaded = None

    def open(self, folder, names=None):
        """The :class:`Database` in ``folder``, its tables of ``names`` (default all) checked
        against the recorded hashes."""
        names = self.names if names is None else list(names)
        try:
            db = Database(folder, names)
        except FileNotFoundError as e:
            raise InputError(f"database for this manifold: {e} (if it moved, give its folder as "
                             "`database`)") from None
        except KeyError as e:
            raise InputError(f"database for this manifold: {e}") from None
        for name in names:
            recorded = self.hashes[materials.index(self.names, name)]
            if db.hash(name) != recorded:
                raise InputError(
                    f"database {db.folder}: table {name!r} differs from the one the manifold was fit on "
                    f"(hash {db.hash(name)[:12]} != {recorded[:12]})")
        return db

    def stack(self, folder):
        """All N tables as float32 ``(N, d)`` (read from ``folder`` once, then kept)."""
        if self.loaded is None:
            self.loaded = self.open(folder).stack(self.names)
        return self.loaded

    def raw_gram(self, folder):
        """:attr:`gram`, computed from the tables in ``folder`` when absent (manifolds of the previous release)."""
        if self.gram is None:
            self.gram = pruning.raw_gram(self.stack(folder))
        return self.gram

    def prune(self, w, budget, folder):
        """Materials kept by pruning weights ``w`` within the relative L2 ``budget``.

        Drops the materials of smallest contribution ``|w_i| |table_i|`` for as long as the
        table changes by at most ``budget`` of its L2 norm; the kept weights are rescaled to
        sum to ``sum(w)`` so the combination stays affine. The change is computed exactly from
        the tables' Gram matrix (:func:`pruning.prune`), rescaling included; ``budget = 0``
        keeps every non-zero weight.

        Returns
        -------
        Pruned
            ``keep`` (ndarray of int), ``w_kept`` (ndarray), ``dropped`` (float: sum of
            ``|w_i|`` over the dropped materials).
        """
        w = np.asarray(w, dtype=np.float64)
        n = len(self.names)
        if w.shape != (n,) or not np.isfinite(w).all():
            raise InputError(f"weights must be {n} finite values, got shape {w.shape}")
        if not 0 <= budget < 1:
            raise InputError(f"`prune` must be in [0, 1), got {budget}")
        return Pruned(*pruning.prune(w, self.raw_gram(folder), budget))

    def combine(self, w, budget, folder, dims, database=None):
        """The table ``sum_i w_i table_i`` of shape ``(3,) + dims`` over the materials :meth:`prune` keeps.

        Uses the tables in memory when they are (and ``database`` is None); otherwise reads
        only the kept ones from ``database`` (default ``folder``).
        """
        keep, w_kept, dropped = self.prune(w, budget, folder)
        n = len(self.names)
        if self.loaded is not None and database is None and dims is not None:
            shape = (3,) + tuple(dims)
            if 2 * len(keep) > n:  # one (multithreaded) matrix-vector product over all tables
                full = np.zeros(n, dtype=np.float32)
                full[keep] = w_kept
                return Combination((full @ self.loaded).reshape(shape), keep, dropped)
            flat = pruning.weighted_sum((self.loaded[i] for i in keep), w_kept, self.loaded.shape[1])
            return Combination(flat.reshape(shape), keep, dropped)
        db = self.open(database or folder, [self.names[i] for i in keep])
        flat = pruning.weighted_sum((db.reflectance(self.names[i]).reshape(-1) for i in keep), w_kept,
                                    3 * int(np.prod(db.dims)))
        return Combination(flat.reshape((3,) + db.dims), keep, dropped)
