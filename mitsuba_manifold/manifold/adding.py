"""A new measured material placed in a fitted manifold without a refit.

:func:`add` gives the new material the latent point that maximises the GPLVM likelihood (paper Eq.
6) of all N + 1 tables with the N fitted points held (:func:`gp.placement.place_point`, started
next to the points of its closest materials, closest in ``log(1 + rho)`` on a random subset of
bins, and at their mean weighted by closeness). The other points, the kernel and the interpolant's
parameters do not change; the interpolant is rebuilt over the N + 1 points, so the new material is
reproduced exactly at its point (every interpolant has ``w(x_i) = e_i``).

The Gram matrix of the fit's features grows by one row. The N x N block is the stored one
re-centred on the new mean; the products with the new table are taken on a random subset of
:data:`FEATURE_BINS` bins scaled to all bins (exact when the tables have no more values): the
features of all N tables are never computed again. The raw and cosine-weighted Gram matrices
(pruning) and the albedo grow exactly, from one pass over the tables.

Each added material keeps its :class:`Provenance` (where its table came from, the file the
manifold reads it from and that file's SHA-256), saved with the manifold.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass

import numpy as np

from .._util.cache import file_hash, key_hash
from ..data import merl
from ..data.database import albedo_weights, database_cache
from ..data.sources import material_name, material_table
from ..errors import FormatError, InputError, MissingFileError
from ..gp.placement import place_point
from . import projection as projection_mod

#: Values (bins x channels) on which the new table's feature products are taken.
FEATURE_BINS = 1 << 18
#: Columns per block of the pass over the tables.
BLOCK = 1 << 16
#: Kinds of :attr:`Provenance.source`.
SOURCES = ("file", "table")


@dataclass(frozen=True)
class Provenance:
    """Where an added material came from.

    Attributes
    ----------
    name : str
        The material's name in the manifold.
    source : str
        ``"file"`` (a table file given by path) or ``"table"`` (an array, written to
        :attr:`path`); anything given as ``origin`` is kept beside it.
    path : str
        Absolute path of the ``.binary`` file the manifold reads the table from.
    hash : str
        SHA-256 of that file (checked whenever the table is read).
    origin : str or None
        What the caller said the table is (e.g. ``"rgl:paper_white"``, a file it was imported from).
    """

    name: str
    source: str
    path: str
    hash: str
    origin: str = None

    def as_dict(self):
        """JSON-able dict (the manifold file's ``added`` entries)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d):
        """Inverse of :meth:`as_dict` (fields checked by :mod:`.schema`)."""
        return cls(d["name"], d["source"], d["path"], d["hash"], d.get("origin"))


@dataclass
class Added:
    """:meth:`Manifold.add`: the new material's point, provenance and how long it took."""

    name: str
    x: np.ndarray
    provenance: Provenance
    nearest: str
    log_likelihood: float
    time_s: float


def check_additions(paths, names=()) -> None:
    """Raise :class:`InputError` unless every path names a material a manifold can add
    (:func:`~mitsuba_manifold.data.sources.material_source`) and ``names`` gives at most one
    name per path.
    """
    from ..data.sources import material_source
    from ..errors import MitsubaManifoldError, one_line

    if len(names) > len(paths):
        raise InputError(
            f"`name` given {len(names)} times for {len(paths)} `add`; give one `name` per `add`"
        )
    for path in paths:
        try:
            material_source(path)
        except MitsubaManifoldError as e:
            raise InputError(f"`add` {path}: {one_line(e)}") from None


def read_table(path, dims):
    """Reflectance table of a MERL ``.binary`` file, flat float32, checked against ``dims``."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(
            f"material to add: {path} is not a file; give a MERL .binary table (or an array)"
        )
    try:
        header = merl.read_header(path)
        if dims is not None and tuple(header) != tuple(dims):
            raise InputError(
                f"material to add: {path} has resolution {tuple(header)}, the manifold's tables "
                f"have {tuple(dims)}; tabulate it at {tuple(dims)}"
            )
        return merl.filled_reflectance(merl.read_binary(path)).reshape(-1)
    except merl.FormatError as e:
        raise InputError(f"material to add: {e}") from None
    except ValueError as e:
        raise InputError(f"material to add: {path}: {e}") from None


def _check_name(name, names):
    if not isinstance(name, str) or not name or "/" in name or os.sep in name or "\0" in name:
        raise InputError(
            f"`name` {name!r} of the material to add must be a non-empty name without '/'"
        )
    if name.startswith(".") or name != name.strip() or not name.isprintable():
        raise InputError(
            f"`name` {name!r} of the material to add must not start with '.', have spaces at "
            "either end or hold control characters (such a name cannot be selected by the "
            "tools): give another `name`"
        )
    if name in names:
        raise InputError(f"the manifold already has a material named {name!r}; give another `name`")


def _stored_table(table, folder, name):
    """Write an array table as a ``.binary`` file under the cache of the database ``folder`` (a
    folder's own cache, or the user's cache for a built-in set), named by its content.
    """
    cache = database_cache(folder)
    if cache is None:
        raise MissingFileError(
            f"database folder {folder} does not exist: the added table has no "
            "cache to be written to (give a manifold whose database is present)"
        )
    out = os.path.join(cache, "added")
    os.makedirs(out, exist_ok=True)
    from .._util.names import escape

    path = os.path.join(out, f"{escape(name)}-{key_hash(table, length=16)}.binary")
    if not os.path.exists(path):
        merl.write_binary(path, merl.to_stored(table))
    return path


def _check_reflects(table, what):
    """Refuse a table with NaN or Inf values, or one that reflects nothing (zero everywhere above
    the horizon): its Gram rows would be zero, and no manifold with it could be read again
    (every Gram matrix of a manifold has a positive diagonal, :mod:`.schema`).
    """
    if not np.isfinite(table).all():
        raise InputError(
            f"material to add: {what} has NaN or Inf values; give a reflectance table (1/sr)"
        )
    if not np.any(table > 0):
        raise InputError(
            f"material to add: {what} reflects nothing (its table is zero everywhere): a "
            "material that reflects no light has no place among measured materials; give a "
            "measured table"
        )


def cross_products(tables, t, weights):
    """``T t`` and ``T diag(q) t`` (float64) of the rows of ``tables`` with ``t``, by blocks."""
    n, d = tables.shape
    raw, cos = np.zeros(n), np.zeros(n)
    q = np.tile(np.asarray(weights, dtype=np.float32).reshape(-1), 3)
    for s in range(0, d, BLOCK):
        block = tables[:, s : s + BLOCK]
        raw += block @ t[s : s + BLOCK]
        cos += block @ (t[s : s + BLOCK] * q[s : s + BLOCK])
    tt = float(np.dot(t.astype(np.float64), t.astype(np.float64)))
    tq = float(np.dot(t.astype(np.float64), (t * q).astype(np.float64)))
    return raw, cos, tt, tq


def grown_gram(S, tables, t, features, n_bins=FEATURE_BINS, seed=0):
    """Gram matrix ``S'`` (N + 1) of the mean-subtracted features with table ``t`` added.

    ``S`` is the N tables' centred Gram matrix. With ``u = f(t) - m`` (``m`` the N tables'
    mean feature table), the re-centred rows are ``z_i - u / (N + 1)`` and the new one
    ``u N / (N + 1)``; the products ``z_i . u`` and ``u . u`` are taken on ``n_bins`` random
    values (all when there are no more) and scaled to all of them.
    """
    n, d = tables.shape
    cols = projection_mod.search_bins(d, n_bins, seed)
    F = np.array(tables[:, cols], dtype=np.float64)
    f = np.array(t[cols], dtype=np.float64)
    if features == "log":
        F, f = np.log1p(np.maximum(F, 0.0)), np.log1p(np.maximum(f, 0.0))
    mean = F.mean(axis=0)
    u = f - mean
    scale = d / len(cols)
    zu = scale * ((F - mean) @ u)
    uu = scale * float(u @ u)
    S2 = np.empty((n + 1, n + 1))
    S2[:n, :n] = S - (zu[:, None] + zu[None, :]) / (n + 1) + uu / (n + 1) ** 2
    S2[:n, n] = S2[n, :n] = (zu - uu / (n + 1)) * n / (n + 1)
    S2[n, n] = uu * n * n / (n + 1) ** 2
    return 0.5 * (S2 + S2.T)


def _starts(latent, length_scale, own, n_starts, seed=0):
    """Starting points: a tenth of ``l`` from each of the ``n_starts`` closest materials (``own``:
    each material's distance to the new table), and their mean weighted by ``own^-2``.
    """
    order = np.argsort(own)[:n_starts]
    steps = np.random.default_rng(seed).standard_normal((len(order), latent.shape[1]))
    out = latent[order] + 0.1 * length_scale * steps / np.linalg.norm(steps, axis=1, keepdims=True)
    w = 1.0 / np.maximum(own[order], 1e-12) ** 2
    return np.vstack([out, (w @ latent[order]) / w.sum()]), order


def add(m, table_or_path, name=None, *, origin=None, n_starts=8):
    """Place a new material in manifold ``m``: the keyword arguments of the grown ``Manifold`` and :class:`Added`.

    See :meth:`Manifold.add` (which applies them to the manifold).
    """
    t0 = time.perf_counter()
    if m.gram is None or m.record.d is None:
        raise InputError(
            "this manifold was saved without its Gram matrix; refit it to add materials to it"
        )
    dims = m.dims
    if isinstance(table_or_path, (str, os.PathLike)) and not os.fspath(table_or_path).endswith(
        ".binary"
    ):  # any other source (.bsdf, .h5, .npz, SET:NAME): its table, kept as an array's
        spec = os.fspath(table_or_path)
        found, table_or_path = material_table(spec, dims, what="material to add")
        name = found.name if name is None else name
        if origin is None:
            origin = os.path.abspath(spec) if os.path.exists(spec) else spec
    if isinstance(table_or_path, (str, os.PathLike)):
        path = os.path.abspath(os.fspath(table_or_path))
        name = name if name is not None else material_name(path)
        _check_name(name, m.names)
        table = read_table(path, dims)
        source = "file"
    else:
        if name is None:
            raise InputError("`name` is needed to add a material given as an array")
        _check_name(name, m.names)
        table = np.asarray(table_or_path, dtype=np.float32).reshape(-1)
        want = 3 * int(np.prod(dims)) if dims is not None else table.size
        if table.size != want:
            raise InputError(
                f"table to add has {table.size} values; this manifold's tables have {want} "
                f"(dims {dims} x RGB)"
            )
        if not np.isfinite(table).all() or (table < 0).any():
            raise InputError(
                "table to add has NaN, Inf or negative values; give a reflectance table (1/sr)"
            )
        path, source = None, "table"
    _check_reflects(table, path if source == "file" else "table to add")
    tables = m.tables()
    if table.size != tables.shape[1]:
        raise FormatError(
            f"table to add has {table.size} values; the manifold's tables have {tables.shape[1]}"
        )
    if path is None:
        path = _stored_table(table.reshape((3,) + tuple(dims)), m.database, name)
    digest = file_hash(path)
    bins = projection_mod.search_bins(tables.shape[1])
    own = projection_mod.log_rms(tables[:, bins], np.log1p(table[bins]))
    starts, order = _starts(m.latent, m.length_scale, own, n_starts)
    raw, cos, tt, tq = cross_products(tables, table, albedo_weights(dims))
    if not (tt > 0 and tq > 0):  # e.g. values below the horizon only: no light reflected
        _check_reflects(np.zeros(1), path if source == "file" else "table to add")
    S2 = grown_gram(m.gram, tables, table, m.features)
    placed = place_point(
        m.latent, S2, m.record.d, starts, length_scale=m.length_scale, noise=m.noise
    )
    x = placed.x
    nearest = float(np.min(np.linalg.norm(m.latent - x, axis=1)))
    if (
        nearest < 1e-6 * m.length_scale
    ):  # on a training point: the weights could not tell the two apart
        x = x + 1e-3 * m.length_scale * np.eye(m.q)[0]

    def grow(a, row, corner):
        out = np.empty((len(a) + 1, len(a) + 1))
        out[:-1, :-1], out[:-1, -1], out[-1, :-1], out[-1, -1] = a, row, row, corner
        return out

    provenance = Provenance(name, source, path, digest, None if origin is None else str(origin))
    q = albedo_weights(dims).reshape(-1)
    albedo = table.reshape(3, -1).astype(np.float64) @ q
    kwargs = {
        "names": m.names + [name],
        "latent": np.vstack([m.latent, x]),
        "database": m.database,
        "hashes": m.hashes + [digest],
        "length_scale": m.length_scale,
        "noise": m.noise,
        "features": m.features,
        "albedos": None if m.albedos is None else np.vstack([m.albedos, albedo]),
        "gram": S2,
        "record": m.record,
        "interpolant": m.interpolant.params(),
        "table_gram": None if m.table_gram is None else grow(m.table_gram, raw, tt),
        "cos_gram": None if m.cos_gram is None else grow(m.cos_gram, cos, tq),
        "added": list(getattr(m, "added", ())) + [provenance],
    }
    tables_grown = np.concatenate([tables, table[None, :]], axis=0)
    info = Added(
        name, x, provenance, m.names[order[0]], placed.log_likelihood, time.perf_counter() - t0
    )
    return kwargs, tables_grown, info
