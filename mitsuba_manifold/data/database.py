"""Material databases: the built-in surrogate of MERL, folders of tables, the Gram matrix.

The real MERL files cannot be shipped, so the package tabulates the Shifted Gamma
Distribution (SGD) fits of the 100 MERL materials (Bagher et al. 2012, parameters in
``data/merl_sgd_fits.json``, model in ``data/SGD_MODEL.md``) on the MERL grid and writes
them as MERL ``.binary`` files. Everything downstream reads a :class:`Database`, a
folder of ``<name>.binary`` files: real MERL files work the same way.
"""

import functools
import json
import os
import zlib

import numpy as np

from . import merl
from .._util import checks as validate
from .._util.locking import FolderLock
from .._util.ownership import owned_tables, write_table_record
from .._util.cache import adopt_hash, file_hash, file_identity, key_hash, npy_cache
from ..errors import FormatError, MissingFileError, NumericalError, UnknownMaterialError, did_you_mean

FITS_PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "merl_sgd_fits.json")
SGD_FIELDS = ("rho_d", "rho_s", "alpha", "p", "f0", "f1", "kap", "lambda", "c", "k", "theta0")
CACHE_NAME = ".manifold-cache"
FEATURES = ("raw", "log")


# ------------------------------------------------------------------ SGD surrogate

def load_sgd_fits(path=None):
    """SGD parameters per material: ``{name: {field: float64 array (3,)}}``, in file order."""
    path = path or FITS_PATH
    with open(path) as f:
        data = json.load(f)
    fits = {}
    for m in data["materials"]:
        params = {k: np.asarray(m[k], dtype=np.float64) for k in SGD_FIELDS}
        bad = [k for k, v in params.items() if v.shape != (3,) or not np.isfinite(v).all()]
        if bad:
            raise FormatError(f"{path}: material {m.get('name')!r} has invalid fields {bad}")
        fits[m["name"]] = params
    return fits


def _shadowing(theta, params):
    """SGD shadowing G1 for elevations ``theta`` (..., 1), per channel, overflow-safe.

    G1 = clamp(1 + lambda (1 - exp(c t^k)), 0, 1) with t = max(0, theta - theta0),
    evaluated as 1 + lambda - exp(log(lambda) + c t^k) so that huge exponents saturate
    to the intended limit instead of producing inf * 0.
    """
    t = np.maximum(theta - params["theta0"], 0.0)
    with np.errstate(divide="ignore", over="ignore"):
        log_ctk = np.log(params["c"]) + params["k"] * np.log(t)  # -inf where t == 0
        expo = np.exp(np.minimum(log_ctk, 700.0))                 # c t^k, 0 where t == 0
        big = np.exp(np.minimum(np.log(params["lambda"]) + expo, 700.0))  # lambda exp(c t^k)
    return np.clip(1.0 + params["lambda"] - big, 0.0, 1.0)


def sgd_reflectance(params, wi, wo):
    """SGD BRDF values (1/sr) for direction pairs.

    Parameters
    ----------
    params : dict
        One material's SGD fields, each of shape (3,).
    wi, wo : ndarray (..., 3)
        Unit directions in the local frame (normal = +z).

    Returns
    -------
    ndarray (..., 3)
        Reflectance per RGB channel, 0 where either direction is below the horizon.
    """
    return _sgd_values(params, _pair_geometry(wi, wo))


def _pair_geometry(wi, wo):
    """The material-independent terms of the SGD model for direction pairs (..., 3)."""
    wi, wo = np.asarray(wi, dtype=np.float64), np.asarray(wo, dtype=np.float64)
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    cos_h = np.clip(h[..., 2:3], 1e-300, 1.0)
    cos_i, cos_o = wi[..., 2:3], wo[..., 2:3]
    valid = (cos_i > 0) & (cos_o > 0)
    g = {"valid": valid, "cos_d": np.clip(np.sum(wi * h, axis=-1, keepdims=True), 0.0, 1.0),
         "tan2": np.maximum(1.0 - cos_h * cos_h, 0.0) / (cos_h * cos_h), "log_cos_h": np.log(cos_h),
         "theta_i": np.arccos(np.clip(cos_i, -1, 1)), "theta_o": np.arccos(np.clip(cos_o, -1, 1)),
         "inv_io": 1.0 / (np.where(valid, cos_i, 1.0) * np.where(valid, cos_o, 1.0))}
    for v in g.values():
        v.setflags(write=False)
    return g


def _sgd_values(params, g):
    """SGD values from :func:`_pair_geometry` terms (broadcast over the channels of ``params``)."""
    alpha, p = params["alpha"], params["p"]
    a = alpha + g["tan2"] / alpha
    with np.errstate(divide="ignore", over="ignore"):
        log_d = np.log(params["kap"]) - a - p * np.log(a) - np.log(np.pi) - 4.0 * g["log_cos_h"]
        d = np.exp(np.minimum(log_d, 700.0))
    cos_d = g["cos_d"]
    fresnel = params["f0"] - cos_d * params["f1"] + (1.0 - cos_d) ** 5 * (1.0 - params["f0"])
    shadow = _shadowing(g["theta_i"], params) * _shadowing(g["theta_o"], params)
    spec = params["rho_s"] * fresnel * d * shadow * g["inv_io"]
    f = (params["rho_d"] + spec) / np.pi
    return np.where(g["valid"], f, 0.0)


def tabulate_sgd(params, dims=merl.MERL_DIMS):
    """Stored MERL values of an SGD material at bin centres (``phi_h = 0``).

    Bins whose directions lie below the horizon are marked :data:`merl.NOT_MEASURED`.
    Returns float64 of shape ``(3,) + dims``.
    """
    if isinstance(params, str):
        params = _fit_named(params)
    above, geometry = _bin_geometry(tuple(int(v) for v in dims))
    refl = np.zeros((3,) + tuple(dims))
    for c in range(3):  # per channel keeps the temporaries at one bin-count each
        one = {k: v[c:c + 1] for k, v in params.items()}
        refl[c][above] = _sgd_values(one, geometry)[:, 0]
    if not np.isfinite(refl).all():  # guards the model's extreme fits; should never trigger
        raise NumericalError("SGD tabulation produced non-finite values")
    raw = merl.to_stored(refl)
    raw[:, ~above] = merl.NOT_MEASURED
    return raw


@functools.lru_cache(maxsize=2)
def _bin_geometry(dims):
    """The bins above the horizon and the SGD terms of their centres (once per process and resolution)."""
    th, td, pd = merl.bin_centres(dims)
    above = merl.above_horizon(dims)
    above.setflags(write=False)
    return above, _pair_geometry(*merl.directions(th[above], td[above], pd[above]))


def _fit_named(name):
    fits = load_sgd_fits()
    if name not in fits:
        raise UnknownMaterialError(f"unknown material {name!r}: the built-in database has {len(fits)} materials "
                       f"(e.g. {', '.join(list(fits)[:5])}, ...)")
    return fits[name]


def make_database(out_dir, dims=merl.MERL_DIMS, materials=None, noise=0.0, seed=0, progress=False,
                  force=False):
    """Write the built-in surrogate database: one ``<name>.binary`` per material.

    Parameters
    ----------
    out_dir : path
        Folder to create or complete. It is locked (:class:`FolderLock`) while written;
        its ``database.json`` records the settings and the tables this function made.
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
        Unknown material names, bad dims or noise.
    ForeignFileError
        A folder made with other settings, or tables in it that this function did not make
        (without ``force``).
    """
    fits = load_sgd_fits()
    names = list(fits) if materials is None else list(dict.fromkeys(materials))   # a repeated name: one table
    unknown = [n for n in names if n not in fits]
    if unknown:
        raise FormatError(f"unknown material(s) {unknown}{did_you_mean(unknown[0], fits)}; known: {', '.join(fits)}")
    workers = min(len(names), os.cpu_count() or 1)
    dims = merl.table_resolution(dims, "resolution", workers=workers)
    if not (np.isfinite(noise) and noise >= 0):
        raise FormatError(f"noise must be a finite value >= 0, got {noise}")
    out_dir = os.fspath(out_dir)
    settings = {"source": "sgd", "dims": list(dims), "noise": float(noise), "seed": int(seed)}
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise FormatError(f"database folder {out_dir} is a file")
    if os.path.isdir(out_dir):  # refuse before locking: a refused run adds nothing to the folder
        owned_tables(out_dir, settings, names, force)
    with FolderLock(out_dir, "database folder"):
        made = owned_tables(out_dir, settings, names, force)
        paths = [os.path.join(out_dir, name + ".binary") for name in names]
        todo = [(name, path) for name, path in zip(names, paths)
                if name not in made or not _valid_table(path, dims)]
        made -= {name for name, _ in todo}
        write_table_record(out_dir, settings, made)
        jobs = [(fits[name], path, dims, float(noise), int(seed), name, cache_folder(out_dir)) for name, path in todo]
        _tabulate(jobs, workers, made, lambda: write_table_record(out_dir, settings, made), len(names), progress)
    return paths


def _tabulate(jobs, workers, made, record, total, progress):
    """Run the table jobs (one process per core for big tables), adding each finished table's
    name to ``made`` and calling ``record()``; if interrupted, the tables the workers finished
    meanwhile (each a new file) are added too."""
    from tqdm import tqdm

    dims = jobs[0][2] if jobs else None
    before = {job[5]: _inode(job[1]) for job in jobs}
    with tqdm(total=total, initial=total - len(jobs), desc="tabulating", unit="table", disable=not progress) as bar:
        try:
            if len(jobs) > 1 and workers > 1 and np.prod(dims) >= 1 << 16:
                from concurrent.futures import ProcessPoolExecutor
                with ProcessPoolExecutor(min(workers, len(jobs))) as pool:
                    for name, path, identity, digest in pool.map(_write_sgd_table, jobs):
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
                        and _valid_table(job[1], dims)}
            if finished:
                made |= finished
                record()


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
    above = _bin_geometry(tuple(int(v) for v in dims))[0]
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
        if not os.path.isdir(folder):
            raise MissingFileError(f"database folder {folder} does not exist")
        available = sorted(f[:-7] for f in os.listdir(folder) if f.endswith(".binary"))
        if names is None:
            names = available
            if not names:
                raise FormatError(f"database folder {folder} holds no .binary tables")
        else:
            names = list(names)
            bad = [n for n in names if not isinstance(n, str) or not n or "/" in n or os.sep in n or "\0" in n]
            if bad:
                raise FormatError(f"database {folder}: material names {bad} are not file names in the folder "
                                    "(a name is '<name>' of '<name>.binary', without '/')")
            missing = [n for n in names if n not in available]
            if missing:
                raise UnknownMaterialError(f"database {folder} has no table for {missing}")
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
        """Mean table and Gram matrix of the mean-subtracted observations.

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
            Also return ``G = T T^T`` of the raw tables (:func:`pruning.raw_gram`), same pass.

        Returns
        -------
        mean : ndarray (d,) float32
            Mean table in the feature space.
        S, G : ndarray (N, N) float64 (``G`` only with ``raw``)
        """
        if features not in FEATURES:
            raise FormatError(f"features must be one of {FEATURES}, got {features!r}")
        names = self.names if names is None else list(names)
        if tables is None:
            tables = self.stack(names, progress=progress)
        from threadpoolctl import threadpool_limits
        n, d = tables.shape
        mean = np.empty(d, dtype=np.float32)
        S = np.zeros((n, n))
        G = np.zeros((n, n)) if raw else None
        # Small products (N x block): one BLAS thread is as fast as two on an idle machine
        # and 10-20x faster when another process competes for the cores.
        with threadpool_limits(1, user_api="blas"):
            for start in range(0, d, block):
                z = tables[:, start:start + block].astype(np.float64)
                if raw:
                    G += z @ z.T
                if features == "log":
                    np.log1p(z, out=z)
                m = z.mean(axis=0)
                mean[start:start + block] = m
                z -= m
                S += z @ z.T
        S = 0.5 * (S + S.T)
        return (mean, S, 0.5 * (G + G.T)) if raw else (mean, S)
