"""Material databases: folders of MERL tables, read (:class:`Database`) and written (:func:`make_database`).

Everything downstream reads a :class:`Database`, a folder of ``<name>.binary`` files: real
MERL files work the same way. :func:`make_database` writes the built-in surrogate of MERL
(the SGD fits of :mod:`.surrogate`, re-exported here) into such a folder. The Gram matrix
of the tables is :mod:`.gram`'s (:meth:`Database.gram`).
"""

import os
import zlib

import numpy as np

from . import gram as gram_matrix, merl
from .surrogate import FITS_PATH, SGD_FIELDS, bin_geometry, load_sgd_fits, sgd_reflectance, tabulate_sgd
from .._util import checks
from .._util.atomic import sweep
from .._util.locking import FolderLock
from .._util.ownership import owned_tables, pending_tables, write_table_record
from .._util.workers import owned_pool
from .._util.cache import adopt_hash, file_hash, file_identity, key_hash, npy_cache
from ..errors import FormatError, MissingFileError, UnknownMaterialError, did_you_mean

__all__ = ["Database", "make_database", "cache_folder", "albedo_weights", "CACHE_NAME", "FEATURES",
           "FITS_PATH", "SGD_FIELDS", "load_sgd_fits", "sgd_reflectance", "tabulate_sgd"]

CACHE_NAME = ".manifold-cache"
#: Feature transforms of a manifold's fit (:data:`gram.FEATURES` has the metrics' ``coslog`` too).
FEATURES = ("raw", "log")


def make_database(out_dir, dims=merl.MERL_DIMS, materials=None, noise=0.0, seed=0, progress=False,
                  force=False):
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
    names = list(fits) if materials is None else list(dict.fromkeys(materials))   # a repeated name: one table
    unknown = [n for n in names if n not in fits]
    if unknown:
        raise FormatError(f"unknown material(s) {unknown}{did_you_mean(unknown[0], fits)}; known: {', '.join(fits)}")
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
        for folder in (out_dir, cache_folder(out_dir)):   # temporaries of killed writers (a killed run's)
            sweep(folder)
        made, was_pending = owned_tables(out_dir, settings, names, force), pending_tables(out_dir)
        paths = [os.path.join(out_dir, name + ".binary") for name in names]
        todo = [(name, path) for name, path in zip(names, paths) if name not in made or not _valid_table(path, dims)
                or (name in was_pending and not _has_reflectance(path, cache_folder(out_dir)))]
        made -= {name for name, _ in todo}
        pending = {name for name, _ in todo}   # listed before they are written: a killed run's are its own
        write_table_record(out_dir, settings, made, pending)
        jobs = [(fits[name], path, dims, float(noise), int(seed), name, cache_folder(out_dir)) for name, path in todo]
        _tabulate(jobs, workers, made, lambda: write_table_record(out_dir, settings, made, pending - made),
                  len(names), progress)
    return paths


def _tabulate(jobs, workers, made, record, total, progress):
    """Run the table jobs (one process per core for big tables), adding each finished table's name
    to ``made`` and calling ``record()``; if interrupted, also the tables finished meanwhile."""
    from tqdm import tqdm

    dims = jobs[0][2] if jobs else None
    before = {job[5]: _inode(job[1]) for job in jobs}
    with tqdm(total=total, initial=total - len(jobs), desc="tabulating", unit="table", disable=not progress) as bar:
        try:
            if len(jobs) > 1 and workers > 1 and np.prod(dims) >= 1 << 16:
                with owned_pool(min(workers, len(jobs))) as pool:   # workers end with this process
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
            finished = {job[5] for job in jobs if job[5] not in made and _inode(job[1]) != before[job[5]]
                        and _valid_table(job[1], dims) and _has_reflectance(job[1], job[6])}
            if finished:
                made |= finished
                record()


def _has_reflectance(path, cache):   # else a worker stopped in between: the next run makes it again
    return os.path.exists(os.path.join(cache, f"{file_hash(path)}.refl.npy"))


def _inode(path):
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


def _write_sgd_table(job):
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
    npy_cache(os.path.join(cache, f"{digest}.refl.npy"), lambda: _filled(raw, dims),
              shape=(3,) + tuple(dims), dtype=np.float32)
    return name, path, file_identity(path), digest


def _filled(raw, dims):
    """:func:`merl.filled_reflectance` of a table measured in every bin above the horizon (as tabulated
    ones are), without its search for missing bins (used when some are missing)."""
    above = bin_geometry(tuple(int(v) for v in dims))[0]
    refl = merl.reflectance(raw, dtype=np.float32)
    if (refl[:, above] < 0).any():
        return merl.filled_reflectance(raw)
    return np.where(above, np.maximum(refl, 0.0), np.float32(0.0)).astype(np.float32)


def cache_folder(folder):
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

def albedo_weights(dims=merl.MERL_DIMS):
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


# --------------------------------------------------------------------- database

class Database:
    """A folder of MERL ``.binary`` tables.

    Parameters
    ----------
    folder : path
        Folder holding ``<name>.binary`` files.
    names : list of str, optional
        Materials to use, in this order (default: every table in the folder, sorted).

    Notes
    -----
    Derived data (content hashes, float32 reflectance tables, sampling densities) is
    cached in ``<folder>/.manifold-cache`` (or under ``~/.cache/mitsuba_manifold`` when
    the folder is read-only), keyed by each table's content hash.
    """

    def __init__(self, folder, names=None):
        folder = os.path.abspath(os.fspath(folder))
        if os.path.isfile(folder):
            raise FormatError(f"database {folder} is a file, not a folder; pass the folder "
                              f"holding the .binary tables ({os.path.dirname(folder)})")
        if not os.path.isdir(folder):
            raise MissingFileError(f"database folder {folder} does not exist")
        available = merl.table_names(folder)
        if names is None:
            names = available
            if not names:
                raise FormatError(f"database folder {folder} holds no .binary tables")
        else:
            if isinstance(names, str):   # "chrome, steel": a comma-separated list
                names = [n.strip() for n in names.split(",") if n.strip()]
            names = list(names)
            if not names:
                raise FormatError(f"database {folder}: `names` is empty; give at least one material name "
                                  "(or None for every table of the folder)")
            bad = [n for n in names if not isinstance(n, str) or not n or "/" in n or os.sep in n or "\0" in n]
            if bad:
                raise FormatError(f"database {folder}: material names {bad} are not file names in the folder "
                                  "(a name is '<name>' of '<name>.binary', without '/')")
            missing = [n for n in names if n not in available]
            if missing:
                raise UnknownMaterialError(f"`names`: database {folder} has no table for {missing}"
                                           f"{did_you_mean(missing[0], available)}")
            if len(set(names)) != len(names):
                raise FormatError(f"database {folder}: material names repeat in {names}")
        self.folder = folder
        self.names = names
        dims = {n: merl.read_header(self.path(n)) for n in names}
        if len(set(dims.values())) > 1:
            raise FormatError(f"database {folder}: {merl.resolution_mismatch(dims)}")
        self.dims = next(iter(dims.values()))
        self.cache_dir = self._make_cache_dir()

    # -- files and caches
    def path(self, name):
        """Path of a material's ``.binary`` file."""
        return os.path.join(self.folder, name + ".binary")

    def index(self, name):
        """Position of ``name`` in :attr:`names` (KeyError naming the database otherwise)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise UnknownMaterialError(f"unknown material {name!r} in database {self.folder} "
                           f"({len(self.names)} materials)") from None

    def _make_cache_dir(self):
        return cache_folder(self.folder)

    def hash(self, name):
        """SHA-256 of a table's file (hashed once per process, see :func:`cache.file_hash`)."""
        return file_hash(self.path(name))

    def hashes(self, names=None):
        return [self.hash(n) for n in (self.names if names is None else names)]

    # -- tables
    def reflectance(self, name, mmap=True):
        """Filled reflectance table, float32 of shape ``(3,) + dims`` (see merl.filled_reflectance).

        Converted once from the ``.binary`` file and cached as ``.npy`` keyed by its hash;
        returned memory-mapped read-only when ``mmap``.
        """
        self.index(name)

        def build():
            raw = merl.read_binary(self.path(name))  # format errors name the file
            try:
                return merl.filled_reflectance(raw)
            except ValueError as e:
                raise FormatError(f"{self.path(name)}: {e}") from None

        cached = os.path.join(self.cache_dir, f"{self.hash(name)}.refl.npy")
        return npy_cache(cached, build, shape=(3,) + tuple(self.dims), dtype=np.float32, mmap=mmap)

    def stack(self, names=None, progress=False):
        """Tables of ``names`` as one float32 matrix ``(N, d)``, rows = RGB-concatenated tables."""
        names = self.names if names is None else list(names)
        d = 3 * int(np.prod(self.dims))
        out = np.empty((len(names), d), dtype=np.float32)
        for i, name in enumerate(_progress(names, progress, "loading")):
            out[i] = self.reflectance(name).reshape(-1)
        return out

    def material_rows(self, names=None, pad=16, keep=2):
        """Tables of ``names`` interleaved by bin: float32 ``(bins, 3, n_pad)``, read-only memmap.

        ``rows[b, c, k]`` is channel ``c`` of material ``names[k]`` at flat bin ``b``, so
        that every material's value at a bin is one contiguous read; ``n_pad`` is
        ``len(names)`` rounded up to a multiple of ``pad`` (extra columns are 0). Built once
        and cached in :attr:`cache_dir`, keyed by the tables' hashes; only the ``keep``
        most recently used such caches are kept (each is ``bins * 3 * n_pad * 4`` bytes).
        """
        names = self.names if names is None else list(names)
        for n in names:
            self.index(n)
        bins = int(np.prod(self.dims))
        n_pad = -(-len(names) // pad) * pad
        key = key_hash("\n".join([f"{self.dims}:{pad}"] + self.hashes(names)), length=40)
        path = os.path.join(self.cache_dir, f"{key}.rows-v1-{len(names)}x{n_pad}.npy")

        def write(tmp):
            out = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float32, shape=(bins, 3, n_pad))
            tables = [self.reflectance(n).reshape(3, bins) for n in names]
            step = 1 << 15
            block = np.zeros((3, n_pad, step), dtype=np.float32)
            for start in range(0, bins, step):
                stop = min(bins, start + step)
                for k, t in enumerate(tables):
                    block[:, k, :stop - start] = t[:, start:stop]
                out[start:stop] = block[:, :, :stop - start].transpose(2, 0, 1)
            out.flush()
            del out

        return npy_cache(path, write=write, shape=(bins, 3, n_pad), dtype=np.float32, mmap=True,
                         touch=True, keep=keep, marker=".rows-v1-")

    def albedo(self, names=None, tables=None):
        """Bihemispherical albedo per material and channel, shape ``(N, 3)``.

        ``tables`` (the :meth:`stack` of ``names``) avoids reading the tables again.
        """
        q = albedo_weights(self.dims).reshape(-1)
        names = self.names if names is None else list(names)
        rows = tables if tables is not None else (self.reflectance(n) for n in names)
        return np.stack([np.asarray(t).reshape(3, -1) @ q for t in rows])

    def gram(self, names=None, features="raw", block=1 << 16, tables=None, progress=False, raw=False):
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
