"""Material databases: sets of measured materials, read (:class:`Database`) and written.

Everything downstream reads a :class:`Database`: a typed set of sources (:mod:`.sources`), one
per material, each making its table at the database's resolution. A database is named by a
built-in set (``merl``, the default, ``rgl``, ``nielsen``, ``all``, ``sgd``: tables made on
demand into a cache, no files) or by a folder of MERL ``.binary`` files, Mitsuba ``measured``
files and NBRDF networks in any mix, plus what its ``sources.json`` names (:class:`SourceList`).
:func:`make_database` writes the SGD surrogate's tables as ``.binary`` files (with noise, for
the scaling benchmarks); :func:`write_database` writes a database of any sources. The Gram
matrix of the tables is :mod:`.gram`'s (:meth:`Database.gram`).
"""

import json
import os
import re
import zlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, ClassVar, Literal, Optional

import numpy as np
from pydantic import AfterValidator, Field, Strict

from .._util import checks
from .._util.atomic import sweep, write_bytes
from .._util.cache import (
    Eviction,
    adopt_hash,
    file_hash,
    file_identity,
    key_hash,
    npy_cache,
    read_npy_into,
)
from .._util.locking import FolderLock
from .._util.memory import prefaulted
from .._util.ownership import owned_tables, pending_tables, write_table_record
from .._util.schema import FileSchema
from .._util.workers import owned_pool
from ..errors import FormatError, InputError, MissingFileError, UnknownMaterialError, did_you_mean
from . import gram as gram_matrix
from . import merl
from .sources import BUILTIN_PREFIX, SET_NAMES, builtin, builtin_set, combine, folder_sources
from .surrogate import (
    FITS_PATH,
    SGD_FIELDS,
    bin_geometry,
    load_sgd_fits,
    sgd_reflectance,
    tabulate_sgd,
)

if TYPE_CHECKING:
    from typing import Any


__all__ = [
    "Database",
    "make_database",
    "cache_folder",
    "albedo_weights",
    "CACHE_NAME",
    "FEATURES",
    "SourceList",
    "TableRows",
    "write_database",
    "open_spec",
    "split_spec",
    "database_cache",
    "canonical_spec",
    "recorded_spec",
    "builtin_cache",
    "MADE_DTYPE",
    "FITS_PATH",
    "SGD_FIELDS",
    "load_sgd_fits",
    "sgd_reflectance",
    "tabulate_sgd",
]

CACHE_NAME = ".manifold-cache"
#: Feature transforms of a manifold's fit (:data:`gram.FEATURES` has the metrics' ``coslog`` too).
FEATURES = ("raw", "log")


def make_database(
    out_dir, dims=merl.MERL_DIMS, materials=None, noise=0.0, seed=0, progress=False, force=False
) -> list:
    """Write the built-in surrogate database: one ``<name>.binary`` per material.

    Parameters
    ----------
    out_dir : path
        Folder to create or complete. It is locked (:class:`FolderLock`) while written;
        its ``database.json`` records the settings, the tables this function made and, while
        it runs, the ones it is writing (``pending``): the same call after a kill (SIGKILL,
        SIGTERM, Ctrl-C) at any moment resumes to the same folder as an uninterrupted run.
        The worker processes of big tables end with this process (:func:`owned_pool`).
    dims : tuple of 3 int
        Table resolution ``(n_theta_h, n_theta_d, n_phi_d)``, checked against the format's
        limit and the memory available before anything is written.
    materials : list of str, optional
        Subset of material names (default: all 100).
    noise : float
        Standard deviation of multiplicative log-normal measurement noise (0: none).
    seed : int
        Seed of the noise; each material's noise depends on (seed, name) only.
    progress : bool
        Show a progress bar.
    force : bool
        Overwrite ``.binary`` files in ``out_dir`` that this function did not make.

    Returns
    -------
    list of str
        Paths of the tables written (existing valid tables are kept, not rewritten).

    Raises
    ------
    FormatError, InputError
        Unknown material names, bad dims, noise or seed.
    ForeignFileError
        A folder made with other settings, or tables in it this function did not make (no ``force``).
    """
    fits = load_sgd_fits()
    names = (
        list(fits) if materials is None else list(dict.fromkeys(materials))
    )  # a repeated name: one table
    unknown = [n for n in names if n not in fits]
    if unknown:
        raise FormatError(
            f"unknown material(s) {unknown}{did_you_mean(unknown[0], fits)}; known: {', '.join(fits)}"
        )
    workers = min(len(names), os.cpu_count() or 1)
    dims = merl.table_resolution(dims, "`dims`", workers=workers)
    if not (np.isfinite(noise) and noise >= 0):
        raise FormatError(f"`noise` must be a finite value >= 0, got {noise}")
    seed = checks.seed("`seed`", seed)
    out_dir = os.fspath(out_dir)
    settings = {"source": "sgd", "dims": list(dims), "noise": float(noise), "seed": int(seed)}
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise FormatError(f"database folder {out_dir} is a file")
    if os.path.isdir(out_dir):  # refuse before locking: a refused run adds nothing to the folder
        owned_tables(out_dir, settings, names, force)
    with FolderLock(out_dir, "database folder"):
        for folder in (
            out_dir,
            cache_folder(out_dir),
        ):  # temporaries of killed writers (a killed run's)
            sweep(folder)
        made, was_pending = owned_tables(out_dir, settings, names, force), pending_tables(out_dir)
        paths = [os.path.join(out_dir, name + ".binary") for name in names]
        todo = [
            (name, path)
            for name, path in zip(names, paths)
            if name not in made
            or not _valid_table(path, dims)
            or (name in was_pending and not _has_reflectance(path, cache_folder(out_dir)))
        ]
        made -= {name for name, _ in todo}
        pending = {
            name for name, _ in todo
        }  # listed before they are written: a killed run's are its own
        write_table_record(out_dir, settings, made, pending)
        jobs = [
            (fits[name], path, dims, float(noise), int(seed), name, cache_folder(out_dir))
            for name, path in todo
        ]
        _tabulate(
            jobs,
            workers,
            made,
            lambda: write_table_record(out_dir, settings, made, pending - made),
            len(names),
            progress,
        )
    return paths


def write_database(
    out_dir,
    sources=("merl",),
    dims=merl.MERL_DIMS,
    materials=None,
    export=False,
    progress=False,
    force=False,
) -> "Database":
    """Write a database folder taking its materials from ``sources`` (built-in set names and folders).

    Without ``export`` the folder gets a ``sources.json`` (:class:`SourceList`) naming them and
    no table files: the tables are made on demand into its cache (:meth:`Database.reflectance`).
    With ``export`` every material (or those of ``materials``) is written as ``<name>.binary``,
    and the folder is a plain MERL database. Returns the :class:`Database` of the folder.

    Raises (before anything is written): unknown sets or folders, names given twice, unknown
    materials, bad ``dims``; :class:`ForeignFileError` for files in ``out_dir`` this function
    would replace and did not write (without ``force``).
    """
    from .._util.ownership import check_replaceable, record

    dims = merl.table_resolution(dims, "`dims`")
    out_dir = os.path.abspath(os.fspath(out_dir))
    sets = tuple(
        dict.fromkeys(
            builtin_set(s, what="source") or os.path.abspath(os.fspath(s))
            for s in dict.fromkeys(sources)
        )
    )
    if not sets:
        raise InputError(
            "give at least one source (a built-in set or a folder) to make a database from"
        )
    groups = {s: builtin(s) if s in SET_NAMES else open_spec(s, dims).sources for s in sets}
    found = combine(groups) if len(groups) > 1 else list(next(iter(groups.values())))
    available = {s.name: s for s in found}
    names = list(available) if materials is None else list(dict.fromkeys(materials))
    unknown = [n for n in names if n not in available]
    if unknown:
        raise UnknownMaterialError(
            f"unknown material(s) {unknown}{did_you_mean(unknown[0], list(available))} "
            f"in {', '.join(sets)}"
        )
    if materials is not None and not export:
        raise InputError(
            "`materials` selects the tables to export; without `export` a database holds every "
            "material of its sources (choose them when fitting)"
        )
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise FormatError(f"database folder {out_dir} is a file")
    listing = os.path.join(out_dir, SOURCES_NAME)
    targets = [os.path.join(out_dir, n + ".binary") for n in names] if export else [listing]
    for path in targets:
        check_replaceable(path, force, "database file")
    os.makedirs(out_dir, exist_ok=True)
    with FolderLock(out_dir, "database folder"):
        if not export:
            SourceList(sets=sets, dims=dims).write(listing)
            record([listing], "make_database")
        else:
            for name, path in zip(_progress(names, progress, "exporting"), targets):
                table = available[name].table(dims)
                merl.write_binary(path, merl.to_stored(table))
                record([path], "make_database")
    return Database(out_dir, None if not export else names)


@dataclass(frozen=True)
class DatabaseRequest:
    """A database folder to make: the plan of ``make_database.py``.

    Parameters
    ----------
    out : str
        The folder (created or completed).
    sources : tuple of str
        Built-in set names (:func:`~mitsuba_manifold.data.sources.builtin_set`) and folders.
    resolution : tuple of int
        MERL bins ``(theta_h, theta_d, phi_d)``.
    materials : tuple of str, optional
        The materials to export (implies ``export``); each made once.
    export : bool
        Write every material as a MERL ``.binary`` file (else only ``sources.json``).
    noise, seed : float, int
        Multiplicative log-normal noise of noisy copies of the SGD fits (``sources`` ``sgd``).
    force : bool
        Replace files this package did not make.
    """

    out: str
    sources: tuple = ("merl",)
    resolution: tuple = tuple(merl.MERL_DIMS)
    materials: Optional[tuple] = None
    export: bool = False
    noise: float = 0.0
    seed: int = 0
    force: bool = False

    def checked(self) -> "DatabaseRequest":
        """The request with its set names read (:func:`builtin_set`) and each material once;
        raises :class:`InputError` for a bad noise or seed, or noise without ``sgd``.
        """
        from dataclasses import replace

        sources = tuple(builtin_set(s, what="`sources`") or s for s in self.sources or ["merl"])
        materials = None if self.materials is None else tuple(dict.fromkeys(self.materials))
        checks.finite("`noise`", self.noise, 0.0, 10.0)
        checks.seed("`seed`", self.seed)
        out = replace(self, sources=sources, materials=materials)
        if self.noise > 0 and not out.sgd_copies:
            raise InputError("`noise` applies to `sources` sgd only (noisy copies of the SGD fits)")
        return out

    @property
    def sgd_copies(self) -> bool:
        """Whether the tables are (noisy) copies of the SGD fits, tabulated here
        (:func:`make_database`), rather than a folder of sources (:func:`write_database`).
        """
        return list(self.sources) == ["sgd"] and bool(
            self.export or self.materials or self.noise > 0
        )


def build_database(request: DatabaseRequest, progress=True) -> int:
    """Make the folder of a checked ``request`` (:meth:`DatabaseRequest.checked`): SGD copies
    by :func:`make_database`, else :func:`write_database`. Returns the number of tables or
    materials it holds.
    """
    materials = None if request.materials is None else list(request.materials)
    if request.sgd_copies:
        n = len(materials) if materials else 100
        merl.table_resolution(
            request.resolution, "`resolution`", workers=min(n, os.cpu_count() or 1)
        )
        paths = make_database(
            request.out,
            request.resolution,
            materials,
            request.noise,
            request.seed,
            progress=progress,
            force=request.force,
        )
        return len(paths)
    merl.table_resolution(request.resolution, "`resolution`")
    db = write_database(
        request.out,
        list(request.sources),
        request.resolution,
        materials,
        export=request.export or request.materials is not None,
        progress=progress,
        force=request.force,
    )
    return len(db.names)


def _tabulate(jobs, workers, made, record, total, progress) -> None:
    """Run the table jobs (one process per core for big tables), adding each finished table's name
    to ``made`` and calling ``record()``; if interrupted, also the tables finished meanwhile.
    """
    from tqdm import tqdm

    dims = jobs[0][2] if jobs else None
    before = {job[5]: _inode(job[1]) for job in jobs}
    with tqdm(
        total=total,
        initial=total - len(jobs),
        desc="tabulating",
        unit="table",
        disable=not progress,
    ) as bar:
        try:
            if len(jobs) > 1 and workers > 1 and np.prod(dims) >= 1 << 16:
                with owned_pool(min(workers, len(jobs))) as pool:  # workers end with this process
                    for name, path, identity, digest in pool.imap_unordered(_write_sgd_table, jobs):
                        adopt_hash(path, identity, digest)
                        made.add(name)
                        record()
                        bar.update()
            else:
                for job in jobs:
                    made.add(_write_sgd_table(job)[0])
                    record()
                    bar.update()
        finally:
            finished = {
                job[5]
                for job in jobs
                if job[5] not in made
                and _inode(job[1]) != before[job[5]]
                and _valid_table(job[1], dims)
                and _has_reflectance(job[1], job[6])
            }
            if finished:
                made |= finished
                record()


def _has_reflectance(
    path, cache
) -> bool:  # else a worker stopped in between: the next run makes it again
    return os.path.exists(os.path.join(cache, f"{file_hash(path)}.refl.npy"))


def _inode(path) -> "int | None":
    try:
        return os.stat(path).st_ino
    except FileNotFoundError:
        return None


def _valid_table(path, dims):
    """True when ``path`` is a MERL file of resolution ``dims`` (a corrupt leftover is not)."""
    try:
        return os.path.exists(path) and merl.read_header(path) == dims
    except merl.FormatError:
        return False


def _write_sgd_table(job) -> tuple:
    """Tabulate one SGD material, add its measurement noise, write it (a worker's task).

    Also writes its float32 reflectance cache (keyed by the file's hash, as :meth:`Database.reflectance`),
    so that loading needs no conversion; returns ``(name, path, file identity, hash)`` (:func:`cache.adopt_hash`).
    """
    params, path, dims, noise, seed, name, cache = job
    raw = tabulate_sgd(params, dims)
    if noise > 0:
        rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
        factor = np.exp(noise * rng.standard_normal(raw.shape) - 0.5 * noise * noise)
        raw = np.where(raw >= 0, raw * factor, raw)
    merl.write_binary(path, raw)
    digest = file_hash(path)
    npy_cache(
        os.path.join(cache, f"{digest}.refl.npy"),
        lambda: _filled(raw, dims),
        shape=(3,) + tuple(dims),
        dtype=np.float32,
    )
    return name, path, file_identity(path), digest


def _filled(raw, dims) -> "np.ndarray":
    """:func:`merl.filled_reflectance` of a table measured in every bin above the horizon (as tabulated
    ones are), without its search for missing bins (used when some are missing).
    """
    above = bin_geometry(tuple(int(v) for v in dims))[0]
    refl = merl.reflectance(raw, dtype=np.float32)
    if (refl[:, above] < 0).any():
        return merl.filled_reflectance(raw)
    return np.where(above, np.maximum(refl, 0.0), np.float32(0.0)).astype(np.float32)


def cache_folder(folder) -> str:
    """``<folder>/.manifold-cache``, or under ``~/.cache/mitsuba_manifold`` if the folder is read-only (created)."""
    folder = os.path.abspath(os.fspath(folder))
    local = os.path.join(folder, CACHE_NAME)
    try:
        os.makedirs(local, exist_ok=True)
        if os.access(local, os.W_OK):
            return local
    except OSError:
        pass
    key = key_hash(folder, length=16)
    home = os.path.join(os.path.expanduser("~"), ".cache", "mitsuba_manifold", key)
    os.makedirs(home, exist_ok=True)
    return home


def _progress(items, enabled, desc):
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc=desc, unit="table")


# ----------------------------------------------------------------------- albedo


def albedo_weights(dims=merl.MERL_DIMS) -> "np.ndarray":
    """Quadrature weights ``q`` over bins such that ``sum(q * f)`` is the bihemispherical albedo.

    albedo = 1/pi * int int f cos(theta_i) cos(theta_o) dw_i dw_o, with
    dw_i dw_o = 4 cos(theta_d) sin(theta_h) sin(theta_d) dtheta_h dphi_h dtheta_d dphi_d;
    phi_h integrates to 2 pi and phi_d over [0, 2 pi) is twice the stored [0, pi).
    A Lambertian f = rho/pi gives rho (up to quadrature error). Shape ``dims``.
    """
    n_h, n_d, n_p = dims
    edges_h = (np.arange(n_h + 1) / n_h) ** 2 * (np.pi / 2)
    dth = np.diff(edges_h)
    th, td, pd = merl.bin_centres(dims)
    wi, wo = merl.directions(th, td, pd)
    cos = np.clip(wi[..., 2], 0, None) * np.clip(wo[..., 2], 0, None)
    jac = 4.0 * np.cos(td) * np.sin(th) * np.sin(td)
    area = dth[:, None, None] * (np.pi / 2 / n_d) * (np.pi / n_p)
    return cos * jac * area * (2.0 * np.pi) * 2.0 / np.pi


# ---------------------------------------------------------------- what a database is

#: Precision of the cached tables made from sources other than ``.binary`` files (networks,
#: fits, measured files): half the disk of float32 (``docs/`` has the measured effect).
MADE_DTYPE = np.float16
#: Environment variable naming the cache folder of the built-in sets (default
#: ``~/.cache/mitsuba_manifold``).
CACHE_ENV = "MITSUBA_MANIFOLD_CACHE"
#: A database folder's list of other sources (:class:`SourceList`).
SOURCES_NAME = "sources.json"
_SPEC_DIMS = re.compile(r"^(?P<base>.+)@(?P<h>\d+)x(?P<d>\d+)x(?P<p>\d+)$")


def _size(dims) -> str:
    return "x".join(map(str, dims))


def builtin_cache() -> str:
    """Cache folder of the built-in sets' tables: ``$MITSUBA_MANIFOLD_CACHE/builtin`` or
    ``~/.cache/mitsuba_manifold/builtin`` (created).
    """
    given = os.environ.get(CACHE_ENV)
    root = given or os.path.join(os.path.expanduser("~"), ".cache", "mitsuba_manifold")
    folder = os.path.join(root, "builtin")
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as e:
        where = f"${CACHE_ENV} ({root})" if given else root
        raise OSError(
            e.errno,
            f"the cache of the built-in sets cannot be made in {where}: "
            f"{e.strerror or e}; set {CACHE_ENV} to a folder that can be written",
        ) from None
    return folder


def finite_table(table, what) -> "np.ndarray":
    """``table`` as float32, or a :class:`FormatError` naming ``what`` (the material and where it
    comes from) when it holds NaN or Inf values: nothing is cached from it.
    """
    table = np.asarray(table, dtype=np.float32)
    if not np.isfinite(table).all():
        bad = int(np.size(table) - np.count_nonzero(np.isfinite(table)))
        raise FormatError(
            f"{what}: its table has {bad} NaN or Inf values (of {table.size}); the source is "
            "damaged or not a reflectance table: replace it, or leave the material out"
        )
    return table


def made_table(cache_dir, digest, build, shape, out=None, what="table") -> "np.ndarray":
    """A table made from a source (not a file), cached as ``<digest>.refl16.npy`` (:data:`MADE_DTYPE`)
    or, where its values exceed that range, ``<digest>.refl.npy`` (float32); returned as float32, as cached
    (rounded to the cache's precision when just made).

    ``out``: a float32 array of the table's size to fill (and return, in ``shape``) instead of
    a new array; a cached half-precision table is then read straight into it. A cache file
    whose checksum or values are wrong is reported (one line naming it) and made again
    (:func:`~.._util.cache.npy_cache`); a table with NaN or Inf values is refused, naming
    ``what`` (:func:`finite_table`).
    """
    half = os.path.join(cache_dir, f"{digest}.refl16.npy")
    full = os.path.join(cache_dir, f"{digest}.refl.npy")
    if out is not None:
        # the checksum alone (the writers refuse NaN and Inf: a sealed file holds none unless its
        # bytes changed since); a damaged file is said by npy_cache below as it is made again
        if not os.path.exists(full) and read_npy_into(
            half, out, shape=shape, dtype=MADE_DTYPE, on_rebuild=None
        ):
            return out.reshape(shape)
        np.copyto(out, made_table(cache_dir, digest, build, shape, what=what).reshape(out.shape))
        return out.reshape(shape)

    def build_full() -> "np.ndarray":
        return finite_table(build(), what)

    if os.path.exists(full):
        return npy_cache(full, build_full, shape=shape, dtype=np.float32, mmap=True, finite=True)
    made = []

    def build_half() -> "np.ndarray":
        table = build_full()
        made.append(table)
        if not np.all(np.abs(table) <= np.finfo(MADE_DTYPE).max):
            raise OverflowError
        return table.astype(MADE_DTYPE)

    try:
        value = npy_cache(half, build_half, shape=shape, dtype=MADE_DTYPE, finite=True)
    except OverflowError:
        return npy_cache(
            full, lambda: made[0], shape=shape, dtype=np.float32, mmap=True, finite=True
        )
    return value.astype(
        np.float32
    )  # the cached precision, also when just made: the same values every run


def _source_name(name: str) -> str:
    if name not in SET_NAMES and not os.path.isabs(name):
        raise ValueError(
            f"names the source {name!r}, neither a built-in set ({', '.join(SET_NAMES)}) nor an "
            "absolute folder path"
        )
    return name


_Dim = Annotated[int, Strict(), Field(ge=1)]


class SourceList(FileSchema):
    """``sources.json`` of a database folder: the built-in sets and folders it takes materials
    from besides its own files, and the resolution of its tables.

    The file, as declared::

        {"format": "mitsuba-manifold-sources", "version": 1,
         "from": [set name or absolute folder, ...], "dims": [n_h, n_d, n_p]}

    Every release wrote version 1; a file without ``version`` reads as version 1.

    Attributes
    ----------
    sets : tuple of str
        Built-in set names and absolute folder paths, in order (the JSON key ``from``).
    dims : tuple of 3 int
    """

    VERSION: ClassVar[int] = 1
    VERSIONS: ClassVar[str] = "1: every release so far (a file without version reads as 1)."
    FIX: ClassVar[str] = "remake it with tools/make_database.py"

    format: Literal["mitsuba-manifold-sources"] = Field(
        "mitsuba-manifold-sources", description="'mitsuba-manifold-sources' (a source list)"
    )
    version: int = Field(1, description="the format version (1)")
    sets: tuple[Annotated[str, AfterValidator(_source_name)], ...] = Field(
        alias="from",
        strict=False,
        description="a list of built-in set names and absolute folder paths",
    )
    dims: tuple[_Dim, _Dim, _Dim] = Field(
        merl.MERL_DIMS,
        strict=False,
        description="the tables' resolution [n_theta_h, n_theta_d, n_phi_d] (positive integers)",
    )

    #: The ``format`` of the file.
    FORMAT: ClassVar[str] = "mitsuba-manifold-sources"

    def check(self, where: str) -> "SourceList":
        """Return this list, its resolution one this package tabulates (:class:`FormatError`)."""
        try:
            merl.table_resolution(self.dims, f"{where}: dims")
        except InputError as e:
            raise FormatError(f"{e}; {self.FIX}") from None
        return self

    @classmethod
    def read(cls, path: str) -> "SourceList":
        """The list in ``path``, checked (:class:`FormatError` naming the file and the field)."""
        try:
            with open(path, encoding="utf-8") as f:
                data = json.load(f)
        except (OSError, ValueError, RecursionError) as e:
            why = "nested too deeply" if isinstance(e, RecursionError) else e
            raise FormatError(f"{path}: not a database's source list ({why}); {cls.FIX}") from None
        return cls.checked(data, path).check(path)

    def write(self, path: str) -> None:
        """Write the list to ``path`` atomically."""
        text = json.dumps(self.model_dump(mode="json", by_alias=True), indent=1)
        write_bytes(path, (text + "\n").encode())


@dataclass(frozen=True)
class DatabaseSpec:
    """What :func:`open_spec` found: the sources of a database and where its caches go."""

    key: str
    label: str
    sources: tuple
    dims: tuple
    directory: object = None  # the folder, or None for a built-in set

    def cache_dir(self) -> str:
        return cache_folder(self.directory) if self.directory else builtin_cache()


def split_spec(spec, recorded=True) -> "tuple[Any, tuple[int, int, int] | None]":
    """``(base, dims or None)`` of a database spec ``base[@NHxNDxNP]`` (an existing path is taken
    whole). Unless ``recorded``, a path that exists and also reads as a set at a resolution
    (a folder ``merl@45x45x90``) is refused as ambiguous, as :func:`~.sources.builtin_set` does.
    """
    spec = os.fspath(spec)
    m = _SPEC_DIMS.match(spec)
    if m and not os.path.exists(spec):
        return m.group("base"), (int(m.group("h")), int(m.group("d")), int(m.group("p")))
    if m and not recorded and m.group("base") in SET_NAMES:
        base = m.group("base")
        raise InputError(
            f"database {spec!r} is ambiguous: the built-in set {base} at "
            f"{m.group('h')}x{m.group('d')}x{m.group('p')} and the "
            f"{'folder' if os.path.isdir(spec) else 'file'} {os.path.abspath(spec)}; say ./{spec} "
            f"for the {'folder' if os.path.isdir(spec) else 'file'} or {BUILTIN_PREFIX}{spec} for the set"
        )
    return spec, None


def open_spec(spec, dims=None, recorded=False) -> "DatabaseSpec":
    """The sources of a database: a built-in set's name or a folder, with an optional ``@dims``.

    Names are read by :func:`~.sources.builtin_set`: ``builtin:merl`` is the set, a bare built-in
    name (``merl``, ``rgl``, ``nielsen``, ``all``, ``sgd``) is the set unless a file or folder of
    that name exists in the current folder (then refused as ambiguous, naming both: ``./merl``
    is the folder), except where ``recorded`` (a manifold's record). Raises one-line errors
    naming the spec: no such set or folder, files that cannot be read, names given twice.
    """
    base, suffix = split_spec(spec, recorded=recorded)
    if dims is not None and suffix is not None and tuple(dims) != suffix:
        raise InputError(
            f"database {spec}: its resolution suffix and `dims` {_size(dims)} differ; give one"
        )
    dims = tuple(int(v) for v in dims) if dims is not None else suffix
    base = builtin_set(base, recorded=recorded) or base
    if base in SET_NAMES:
        dims = merl.table_resolution(dims or merl.MERL_DIMS, f"database {spec}: resolution")
        key = base if dims == merl.MERL_DIMS else f"{base}@{_size(dims)}"
        return DatabaseSpec(key, key, tuple(builtin(base)), dims)
    folder = os.path.abspath(base)
    if not os.path.isdir(folder):
        if os.path.exists(folder):
            raise MissingFileError(f"database folder {folder} is a file, not a folder of tables")
        raise MissingFileError(
            f"database folder {folder} does not exist (built-in databases: {', '.join(SET_NAMES)})"
        )
    own = folder_sources(folder)
    listed = os.path.join(folder, SOURCES_NAME)
    groups, natural = {folder: own}, merl.MERL_DIMS
    if os.path.exists(listed):
        record = SourceList.read(listed)
        natural = record.dims
        for s in record.sets:
            groups[s] = builtin(s) if s in SET_NAMES else folder_sources(s)
    found = combine(groups) if len(groups) > 1 else own
    binary = {s.native_dims() for s in found if s.kind == "binary"}
    if len(binary) > 1:
        raise FormatError(
            f"database {folder}: "
            + merl.resolution_mismatch(
                {s.name: s.native_dims() for s in found if s.kind == "binary"}
            )
        )
    if binary:
        natural = binary.pop()
    dims = merl.table_resolution(dims or natural, f"database {spec}: resolution")
    key = folder if dims == natural else f"{folder}@{_size(dims)}"
    return DatabaseSpec(key, folder, tuple(found), dims, folder)


def recorded_spec(spec) -> str:
    """A database spec as this package records it (a manifold's ``database``: a set's name or an
    absolute folder, with ``@dims``), written so that it opens as what was recorded whatever
    the current folder holds: a set's name as ``builtin:NAME`` (:func:`~.sources.builtin_set`).
    """
    spec = os.fspath(spec)
    base, _ = split_spec(spec)
    return BUILTIN_PREFIX + spec if base in SET_NAMES else spec


def canonical_spec(spec, what="database") -> str:
    """The spec a user gave (``merl``, ``builtin:merl@45x45x90``, ``./merl``, ``tables``) as a
    manifold records it: the set's name, or the folder's absolute path, with its ``@dims``
    suffix; an ambiguous name is refused (:func:`~.sources.builtin_set`).
    """
    base, suffix = split_spec(spec, recorded=False)
    name = builtin_set(base, what=what)
    out = name if name is not None else os.path.abspath(base)
    return out if suffix is None else f"{out}@{_size(suffix)}"


def database_cache(spec) -> "str | None":
    """The cache folder of the database ``spec`` (as a manifold records it), or None when it is
    a folder that is gone (creating it would make an empty database folder).
    """
    base, _ = split_spec(spec)
    if builtin_set(base, recorded=True) is not None:
        return builtin_cache()
    if not os.path.isdir(base):
        return None
    try:
        return cache_folder(base)
    except OSError:
        return None


# --------------------------------------------------------------------- database


class TableRows(np.ndarray):
    """Interleaved tables made in memory (:meth:`Database.material_rows` of a built-in set);
    ``key``: the content hash that names them (a cached file's name otherwise).
    """

    key = None


class Database:
    """A set of measured materials: a folder of tables, a built-in set, or a mix of sources.

    Parameters
    ----------
    folder : str or path
        What :func:`open_spec` reads: a folder (its ``.binary``, ``.bsdf``, ``.h5`` + ``.json``
        and ``.npz`` files, plus the sets and folders its ``sources.json`` names), or a built-in
        set's name (:data:`sources.BUILTIN`: ``merl``, ``rgl``, ``nielsen``, ``all``, ``sgd``;
        ``builtin:merl`` always the set, a bare ``merl`` refused as ambiguous where the current
        folder holds a ``merl``: :func:`~.sources.builtin_set`); either with an optional
        resolution suffix ``@NHxNDxNP`` (``merl@45x45x90``).
    names : list of str, optional
        Materials to use, in this order (default: every material, sorted for folders and in
        the set's order for built-in sets).
    dims : tuple of 3 int, optional
        Table resolution (default: the ``.binary`` files', else the suffix's or ``sources.json``'s,
        else MERL's 90x90x180).

    Attributes
    ----------
    folder : str
        How to open this database again (what a manifold records): the folder's absolute path
        or the set's name, with ``@dims`` when not the default resolution.
    sources : dict
        ``{name: source}`` (:mod:`.sources`), the materials of ``names``.
    dims : tuple of int
        The table resolution.
    names : list of str
        The materials, in order.
    cache_dir : str
        Where derived data is cached (see Notes).

    Notes
    -----
    Derived data (content hashes, reflectance tables, sampling densities) is cached in
    ``<folder>/.manifold-cache`` (or under ``~/.cache/mitsuba_manifold`` when the folder is
    read-only; built-in sets: :func:`builtin_cache`), keyed by each table's content hash.
    Tables of ``.binary`` files are cached as float32 and memory-mapped; tables made from
    other sources (networks, fits, measured files) as :data:`MADE_DTYPE`.
    """

    def __init__(self, folder, names=None, dims=None) -> None:
        if isinstance(folder, (str, os.PathLike)) and os.path.isfile(folder):
            folder = os.path.abspath(os.fspath(folder))
            raise FormatError(
                f"database {folder} is a file, not a folder; pass the folder "
                f"holding the tables ({os.path.dirname(folder)})"
            )
        spec = open_spec(folder, dims)
        available = {s.name: s for s in spec.sources}
        if names is None:
            names = [s.name for s in spec.sources]
            if not names:
                raise FormatError(
                    f"database folder {spec.label} holds no tables (.binary, .bsdf, .h5 or .npz files)"
                )
        else:
            if isinstance(names, str):  # "chrome, steel": a comma-separated list
                names = [n.strip() for n in names.split(",") if n.strip()]
            names = list(names)
            label = spec.label
            if not names:
                raise FormatError(
                    f"database {label}: `names` is empty; give at least one material name "
                    "(or None for every material of the database)"
                )
            bad = [
                n
                for n in names
                if not isinstance(n, str) or not n or "/" in n or os.sep in n or "\0" in n
            ]
            if bad:
                raise FormatError(
                    f"database {label}: material names {bad} are not file names of materials "
                    "(a name is '<name>' of '<name>.binary', without '/')"
                )
            missing = [n for n in names if n not in available]
            if missing:
                raise UnknownMaterialError(
                    f"`names`: database {label} has no table for {missing}"
                    f"{did_you_mean(missing[0], list(available))}"
                )
            if len(set(names)) != len(names):
                raise FormatError(f"database {label}: material names repeat in {names}")
        self.names = names
        self.sources = {n: available[n] for n in names}
        self.dims = spec.dims
        self.folder = spec.key
        self.label = spec.label
        self.directory = spec.directory
        self.cache_dir = spec.cache_dir()
        self.files_only = all(s.kind == "binary" for s in self.sources.values())
        if not self.files_only:
            for s in self.sources.values():
                if s.kind == "binary" and s.native_dims() != self.dims:
                    raise FormatError(
                        f"database {self.label}: {s.path} is {_size(s.native_dims())}, the other "
                        f"tables {_size(self.dims)}; use tables of one resolution"
                    )

    # -- files and caches
    def path(self, name) -> str:
        """Where a material comes from: its file, or its set's name."""
        return self.sources[self.names[self.index(name)]].origin

    def index(self, name) -> int:
        """Position of ``name`` in ``names`` (KeyError naming the database otherwise)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise UnknownMaterialError(
                f"unknown material {name!r} in database {self.label} ({len(self.names)} materials)"
            ) from None

    def hash(self, name) -> str:
        """Content hash of a material's table: the SHA-256 of its ``.binary`` file, or of what the
        table is made from (network weights, fit, measured file) and the resolution.
        """
        self.index(name)
        return self.sources[name].digest(self.dims)

    def hashes(self, names=None) -> list:
        return [self.hash(n) for n in (self.names if names is None else names)]

    # -- tables
    def reflectance(self, name, mmap=True, out=None) -> "np.ndarray":
        """Filled reflectance table, float32 of shape ``(3,) + dims`` (see merl.filled_reflectance).

        Made once and cached as ``.npy`` keyed by its content hash (:meth:`hash`): a ``.binary``
        file's as float32, returned memory-mapped read-only when ``mmap``; any other source's as
        :data:`MADE_DTYPE` (float32 where a value exceeds its range), returned in memory.
        ``out``: a C-contiguous float32 array of the table's size to fill and return instead.
        """
        self.index(name)
        source = self.sources[name]
        shape = (3,) + tuple(self.dims)
        digest = self.hash(name)
        what = f"material {name!r} ({source.origin})"
        if source.kind == "binary":
            cached = os.path.join(self.cache_dir, f"{digest}.refl.npy")
            table = npy_cache(
                cached,
                lambda: finite_table(source.table(self.dims), what),
                shape=shape,
                dtype=np.float32,
                mmap=mmap or out is not None,
                finite=True,
            )
            if out is None:
                return table
            np.copyto(out, table.reshape(out.shape))
            return out.reshape(shape)
        return made_table(
            self.cache_dir, digest, lambda: source.table(self.dims), shape, out=out, what=what
        )

    def stack(self, names=None, progress=False) -> "np.ndarray":
        """Tables of ``names`` as one float32 matrix ``(N, d)``, rows = RGB-concatenated tables
        (each read from its cache straight into its row: :func:`~.._util.memory.prefaulted`).
        """
        names = self.names if names is None else list(names)
        d = 3 * int(np.prod(self.dims))
        out = prefaulted((len(names), d), np.float32)
        for i, name in enumerate(_progress(names, progress, "loading")):
            self.reflectance(name, out=out[i])
        return out

    def material_rows(self, names=None, pad=16, keep=2) -> "np.ndarray":
        """Tables of ``names`` interleaved by bin: float32 ``(bins, 3, n_pad)``, read-only memmap.

        ``rows[b, c, k]`` is channel ``c`` of material ``names[k]`` at flat bin ``b``, so
        that every material's value at a bin is one contiguous read; ``n_pad`` is
        ``len(names)`` rounded up to a multiple of ``pad`` (extra columns are 0). Built once
        and cached in :attr:`cache_dir`, keyed by the tables' hashes; only the ``keep``
        most recently used such caches are kept (each is ``bins * 3 * n_pad * 4`` bytes).
        A database with tables made from other sources than ``.binary`` files (a built-in set)
        builds the rows in memory instead: its tables are made quickly, and the disk is spared.
        """
        names = self.names if names is None else list(names)
        for n in names:
            self.index(n)
        bins = int(np.prod(self.dims))
        n_pad = -(-len(names) // pad) * pad
        key = key_hash("\n".join([f"{self.dims}:{pad}"] + self.hashes(names)), length=40)
        if not self.files_only:
            out = np.zeros((bins, 3, n_pad), dtype=np.float32).view(TableRows)
            for k, n in enumerate(names):
                out[:, :, k] = self.reflectance(n).reshape(3, bins).T
            out.key = key
            out.setflags(write=False)
            return out
        path = os.path.join(self.cache_dir, f"{key}.rows-v1-{len(names)}x{n_pad}.npy")

        def write(tmp) -> None:
            out = np.lib.format.open_memmap(
                tmp, mode="w+", dtype=np.float32, shape=(bins, 3, n_pad)
            )
            tables = [self.reflectance(n).reshape(3, bins) for n in names]
            step = 1 << 15
            block = np.zeros((3, n_pad, step), dtype=np.float32)
            for start in range(0, bins, step):
                stop = min(bins, start + step)
                for k, t in enumerate(tables):
                    block[:, k, : stop - start] = t[:, start:stop]
                out[start:stop] = block[:, :, : stop - start].transpose(2, 0, 1)
            out.flush()
            del out

        return npy_cache(
            path,
            write=write,
            shape=(bins, 3, n_pad),
            dtype=np.float32,
            mmap=True,
            eviction=Eviction(keep, ".rows-v1-"),
        )

    def albedo(self, names=None, tables=None) -> "np.ndarray":
        """Bihemispherical albedo per material and channel, shape ``(N, 3)``.

        ``tables`` (the :meth:`stack` of ``names``) avoids reading the tables again.
        """
        q = albedo_weights(self.dims).reshape(-1)
        names = self.names if names is None else list(names)
        rows = tables if tables is not None else (self.reflectance(n) for n in names)
        table = np.empty((3, q.size))  # each table in float64, in one reused buffer
        out = []
        for t in rows:
            np.copyto(table, np.asarray(t).reshape(3, -1))
            out.append(table @ q)
        return np.stack(out)

    def gram(
        self, names=None, features="raw", block=1 << 16, tables=None, progress=False, raw=False
    ) -> tuple:
        """Mean table and Gram matrix of the mean-subtracted observations (:func:`gram.gram`).

        ``S = Z Z^T`` where row i of ``Z`` is material i's table (in the feature space)
        minus the mean table. Computed over blocks of bins with float64 accumulation;
        ``Z`` is never held in float64 as a whole.

        Parameters
        ----------
        names : list of str, optional
        features : {"raw", "log"}
            ``raw`` (the paper's): reflectance; ``log``: ``log(1 + reflectance)``.
        block : int
            Bins per block.
        tables : ndarray (N, d) float32, optional
            Already-loaded :meth:`stack` (avoids reading the tables again).
        raw : bool
            Also return ``G = T T^T`` of the raw tables (for pruning), from the same pass.

        Returns
        -------
        mean : ndarray (d,) float32
            Mean table in the feature space.
        S, G : ndarray (N, N) float64 (``G`` only with ``raw``)
        """
        if features not in FEATURES:
            raise FormatError(f"`features` must be one of {FEATURES}, got {features!r}")
        names = self.names if names is None else list(names)
        if tables is None:
            tables = self.stack(names, progress=progress)
        g = gram_matrix.gram(tables, features, centre=True, raw=raw, block=block)
        return (g.mean, g.S, g.raw) if raw else (g.mean, g.S)
