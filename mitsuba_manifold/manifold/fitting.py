"""The fit of a manifold to a database of tables (paper Sec. 3), before it becomes a :class:`Manifold`.

:func:`fit_database` reads the tables once, computes in one pass over them the Gram matrix
``S`` of the fit's features, the raw tables' ``T T^T`` and their cosine-weighted
``T diag(q) T^T`` (pruning, :mod:`.pruning`), fits the GPLVM layout
of the settings (:func:`presets.fit_layout`) and records what it did (:class:`FitRecord`).
"""

import time
from dataclasses import dataclass

import numpy as np

from ..data import gram
from ..data.database import FEATURES, albedo_weights
from ..errors import FormatError, InputError
from ..gp.gplvm import FitResult
from .fit_record import FitRecord, Timings
from .presets import fit_layout


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


def fit_database(db, names, cfg, preset, init=None, progress=False, **options):
    """Fit the materials ``names`` (default all) of :class:`Database` ``db`` with settings ``cfg``
    (:func:`presets.settings` of ``preset``); ``options`` go to :func:`gplvm.fit_latent`.
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
    g = gram.gram(
        tables, cfg["features"], centre=True, raw=True, weights=albedo_weights(db.dims).reshape(-1)
    )
    t_gram = time.perf_counter() - t0
    result = fit_layout(g.S, tables.shape[1], cfg, init=init, **options)
    record = FitRecord(
        method=cfg["method"],
        preset=preset,
        q=int(cfg["q"]),
        d=int(tables.shape[1]),
        dims=db.dims,
        log_likelihood=float(result.log_likelihood),
        n_evaluations=int(result.n_evaluations),
        history=result.history,
        timings=Timings(t_load, t_gram, float(result.time_s)),
    )
    return DatabaseFit(
        names,
        db.hashes(names),
        result,
        record,
        g.S,
        g.raw,
        db.albedo(names, tables=tables),
        tables,
        g.weighted,
    )
