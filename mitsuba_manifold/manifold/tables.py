"""The training tables of a manifold: opened and checked, loaded once, measured for pruning.

Every material a manifold gives is ``sum_i w_i table_i`` over its N measured tables (paper
Eq. 4). :class:`TrainingTables` holds the data that needs: opening the database the manifold
was fit on (each table checked against the SHA-256 recorded at the fit), the ``(N, d)`` stack
kept in memory once loaded, and what pruning measures exactly (:mod:`.pruning`: the raw
tables' Gram matrix ``G = T T^T``, the cosine-weighted ``C = T diag(q) T^T`` and the albedos,
each computed from the tables on first use when a manifold file lacks it). The pruning and
the combination are :class:`~.model.Manifold`'s methods.
"""

import os

import numpy as np

from .._util.cache import key_hash, npy_cache
from ..data import merl
from ..data.database import Database, albedo_weights
from ..data.sources import BinaryFile
from ..errors import FormatError, InputError
from . import pruning
from .file import schema


def _float64(a):
    return None if a is None else np.asarray(a, dtype=np.float64)


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
        for name, value in (("gram", gram), ("cos_gram", cos_gram), ("albedos", albedos)):
            self.set_matrix(name, value)
        self.loaded = None

    def set_matrix(self, name, value):
        """Set ``gram``, ``cos_gram`` or ``albedos`` (as float64; None: computed on first use)."""
        setattr(self, name, _float64(value))

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
        recorded_hash = dict(zip(self.names, self.hashes))
        for name in names:
            recorded = recorded_hash[name]
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
