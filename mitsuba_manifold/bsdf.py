"""The ``manifold_brdf`` Mitsuba BSDF: any point of a material manifold, rendered.

The material is the affine combination ``sum_i w_i table_i`` of measured MERL tables,
with weights ``w`` from a latent point ``x`` (:meth:`Manifold.weights`), a training
material, or given explicitly. The combination is computed once per material and kept
on the device as one table; evaluation looks it up with MERL's half/diff indexing.

Importance sampling follows the paper's Sec. 5.3: every measured material has, for a
grid of incident elevations, a tabulated unnormalised density of outgoing directions
(cached beside the database, keyed by the table's hash). By linearity the density of
the combination is ``sum_i w_i P_i``, clamped at 0, and Mitsuba's
``MarginalContinuous2D1`` samples it. Call :func:`register` after
``mi.set_variant(...)`` (``import mitsuba_manifold`` does it).
"""

import functools
import os

import drjit as dr
import mitsuba as mi
import numpy as np

from . import merl
from .manifold import Manifold, ManifoldError

PLUGIN_NAME = "manifold_brdf"

#: Sampling grid: incident elevations, half-vector azimuth vertices (over [0, pi]),
#: half-vector elevation vertices (uniform in ``u = sqrt(theta_h / (pi/2))``), and
#: sub-samples per axis averaged into each vertex.
SAMPLING_GRID = (32, 33, 65, 4)
#: Version of the cached sampling densities (bump when their definition changes).
SAMPLING_CACHE_VERSION = 2
#: Probability of sampling the cosine hemisphere instead of the tabulated density.
COSINE_FRACTION = 0.1
#: Default of the ``prune`` parameter (fraction of ``sum |w|``, as Manifold.prune).
DEFAULT_PRUNE = 1e-3

SAMPLING_MODES = ("cdf", "cosine")
INTERPOLATION_MODES = ("nearest", "linear")

_HALF_PI = 0.5 * np.pi
_U_FLOOR = 1e-4                                  # smallest u = sqrt(theta_h / (pi/2)) used by the pdf
_SIN_FLOOR = float(np.sin(_U_FLOOR ** 2 * _HALF_PI))


class ManifoldBRDFError(ValueError):
    """Bad parameters of a ``manifold_brdf`` (the message names the parameter)."""


# --------------------------------------------------------------- Dr.Jit lookups

def merl_angles(wi, wo):
    """Rusinkiewicz angles ``(theta_h, theta_d, phi_d)`` of direction pairs, in Dr.Jit.

    The same mapping as :func:`merl.half_diff` (``phi_d`` folded to ``[0, pi)``),
    written with ``atan2`` so that small angles keep full single precision: the first
    MERL ``theta_h`` bin is 2e-4 rad wide, below what ``acos`` resolves in float32.
    Works on scalar and JIT Mitsuba types.
    """
    h = wi + wo
    rh = dr.sqrt(dr.square(h.x) + dr.square(h.y))
    theta_h = dr.atan2(rh, h.z)
    inv_len = dr.rsqrt(dr.square(rh) + dr.square(h.z))
    # Frame of the half vector: rotate by -phi_h about z, then by -theta_h about y.
    has_az = rh > 0
    inv_rh = dr.select(has_az, dr.rcp(dr.select(has_az, rh, 1.0)), 0.0)
    cos_ph = dr.select(has_az, h.x * inv_rh, 1.0)
    sin_ph = dr.select(has_az, h.y * inv_rh, 0.0)
    cos_th = h.z * inv_len
    sin_th = rh * inv_len
    dx = (wi.x * cos_ph + wi.y * sin_ph) * cos_th - wi.z * sin_th
    dy = wi.y * cos_ph - wi.x * sin_ph
    dz = (wi.x * cos_ph + wi.y * sin_ph) * sin_th + wi.z * cos_th
    theta_d = dr.atan2(dr.sqrt(dr.square(dx) + dr.square(dy)), dz)
    phi_d = dr.atan2(dy, dx)
    phi_d = dr.select(phi_d < 0, phi_d + dr.pi, phi_d)
    phi_d = dr.select(phi_d >= dr.pi, phi_d - dr.pi, phi_d)
    return theta_h, theta_d, phi_d


def _clamp_index(c, n):
    return dr.clip(mi.Int32(dr.floor(c)), 0, n - 1)


def merl_bin(theta_h, theta_d, phi_d, dims):
    """Flat MERL bin index (as :func:`merl.flat_index`) of Rusinkiewicz angles, in Dr.Jit."""
    n_h, n_d, n_p = dims
    th = dr.clip(theta_h, 0.0, _HALF_PI)
    i_h = _clamp_index(dr.sqrt(th * (1.0 / _HALF_PI)) * n_h, n_h)
    i_d = _clamp_index(theta_d * (n_d / _HALF_PI), n_d)
    i_p = _clamp_index(phi_d * (n_p / np.pi), n_p)
    return mi.UInt32((i_h * n_d + i_d) * n_p + i_p)


def _linear_axis(c, n):
    """Neighbouring bins and weight of the upper one along a clamped axis."""
    c = dr.clip(c - 0.5, 0.0, float(n - 1))
    i0 = dr.minimum(mi.Int32(dr.floor(c)), n - 1)
    t = c - mi.Float(i0)
    return i0, dr.minimum(i0 + 1, n - 1), t


# --------------------------------------------------------- sampling densities

@functools.lru_cache(maxsize=4)
def _sampling_geometry(dims, grid=SAMPLING_GRID):
    """Bins and weights turning a table into its sampling densities.

    For each incident elevation ``theta_i`` (``wi`` in the xz plane) and grid vertex
    ``(v, u)``, ``s*s`` sub-samples of the half vector ``h`` (``theta_h = u^2 pi/2``,
    azimuth ``v pi``) spread over the vertex's cell: their MERL bin (of ``wo``, ``wi``
    reflected about ``h``) and weight ``cos(theta_o) J / s^2`` (0 below the horizon),
    where ``J = |d wo / d(u, v)|`` is taken at the vertex itself so that the density
    vanishes on the ``u = 0`` edge (the mirror direction) as the true one does.

    Returns
    -------
    theta_i : ndarray (n_t,)
    index : ndarray int32 (n_t, n_v, n_u, s*s)
    weight : ndarray float32 (n_t, n_v, n_u, s*s)
    """
    n_t, n_v, n_u, s = grid
    theta_i = np.linspace(0.0, _HALF_PI, n_t)
    off = (np.arange(s) + 0.5) / s - 0.5
    u = np.clip(np.arange(n_u)[:, None] / (n_u - 1) + off / (n_u - 1), 0.0, 1.0)   # (n_u, s)
    v = np.clip(np.arange(n_v)[:, None] / (n_v - 1) + off / (n_v - 1), 0.0, 1.0)   # (n_v, s)
    ti = theta_i[:, None, None, None, None]
    uu = u[None, None, None, :, :]
    vv = v[None, :, :, None, None]
    shape = (n_t, n_v, s, n_u, s)
    theta_h = np.broadcast_to(uu * uu * _HALF_PI, shape)
    phi = np.broadcast_to(vv * np.pi, shape)
    wi = np.stack(np.broadcast_arrays(np.sin(ti), 0.0 * ti, np.cos(ti)), axis=-1)
    wi = np.broadcast_to(wi, shape + (3,))
    h = np.stack([np.sin(theta_h) * np.cos(phi), np.sin(theta_h) * np.sin(phi), np.cos(theta_h)], axis=-1)
    cos_d = np.sum(wi * h, axis=-1)
    wo = 2.0 * cos_d[..., None] * h - wi
    valid = (wi[..., 2] > 0) & (wo[..., 2] > 1e-9) & (cos_d > 0)
    u_vertex = np.arange(n_u) / (n_u - 1)
    theta_v = u_vertex * u_vertex * _HALF_PI
    jac = np.broadcast_to((np.sin(theta_v) * u_vertex)[None, None, None, :, None], shape)
    jac = 4.0 * cos_d * jac * np.pi * np.pi
    weight = np.where(valid, wo[..., 2] * jac, 0.0) / (s * s)
    wo_safe = np.where(valid[..., None], wo, np.array([0.0, 0.0, 1.0]))
    wi_safe = np.where(valid[..., None], wi, np.array([0.0, 0.0, 1.0]))
    index = np.where(valid, merl.flat_index(wi_safe, wo_safe, dims), 0)
    order = (0, 1, 3, 2, 4)
    index = index.transpose(order).reshape(n_t, n_v, n_u, s * s).astype(np.int32)
    weight = weight.transpose(order).reshape(n_t, n_v, n_u, s * s).astype(np.float32)
    return theta_i, index, weight


def sampling_density(table, grid=SAMPLING_GRID):
    """Unnormalised sampling density of one table, float32 ``(n_t, n_v, n_u)``.

    The channel mean of ``f(wi, wo) cos(theta_o)`` times the Jacobian of the half-vector
    parameterisation, averaged over each vertex's neighbourhood; linear in ``table``.
    """
    table = np.asarray(table)
    _, index, weight = _sampling_geometry(tuple(table.shape[1:]), tuple(grid))
    mean = table.reshape(3, -1).mean(axis=0, dtype=np.float32)
    return np.einsum("tvus,tvus->tvu", mean[index], weight, dtype=np.float32)


def sampling_cache_path(database, name, grid=SAMPLING_GRID):
    """Cache file of a material's sampling density (keyed by the table's content hash)."""
    tag = f"v{SAMPLING_CACHE_VERSION}-{grid[0]}x{grid[1]}x{grid[2]}s{grid[3]}"
    return os.path.join(database.cache_dir, f"{database.hash(name)}.sampling-{tag}.npy")


def material_density(database, name, grid=SAMPLING_GRID, use_cache=True):
    """Sampling density of one material of ``database``, read from or written to the cache.

    A cache file of the wrong shape or with bad values is recomputed and replaced.
    """
    path = sampling_cache_path(database, name, grid)
    shape = tuple(grid[:3])
    if use_cache and os.path.exists(path):
        try:
            p = np.load(path, allow_pickle=False)
            if p.shape == shape and p.dtype == np.float32 and np.isfinite(p).all():
                return p
        except (OSError, ValueError):
            pass
        mi.Log(mi.LogLevel.Warn, f"{PLUGIN_NAME}: rebuilding damaged sampling cache {path}")
    p = sampling_density(database.reflectance(name), grid)
    if use_cache:
        merl.atomic_write(path, lambda f: np.save(f, p))
    return p


def combined_density(densities, weights, grid=SAMPLING_GRID):
    """``max(0, sum_i w_i P_i)`` with every incident slice usable by the sampler.

    A slice with no mass (always the one at grazing incidence, ``theta_i = pi/2``)
    takes the values of the nearest slice that has some; if none has (a black
    material), every slice becomes uniform in the half vector's solid angle. Either
    way the density vanishes at ``u = 0``, so that the solid-angle pdf grows no faster
    than ``1 / theta_h`` towards the mirror direction.

    Returns
    -------
    density : ndarray float32 (n_t, n_v, n_u)
    empty : int
        Number of slices that had no mass.
    """
    p = np.tensordot(np.asarray(weights, dtype=np.float64), np.asarray(densities, dtype=np.float64), axes=1)
    p = np.maximum(p, 0.0)
    good = np.flatnonzero(p.sum(axis=(1, 2)) > 0)
    empty = p.shape[0] - good.size
    if good.size == 0:
        u = np.arange(grid[2]) / (grid[2] - 1)
        p[:] = (np.sin(u * u * _HALF_PI) * u)[None, None, :]
    elif empty:
        for k in range(p.shape[0]):
            nearest = good[np.argmin(np.abs(good - k))]
            if nearest != k:
                p[k] = p[nearest]
    return p.astype(np.float32), int(empty)


# ------------------------------------------------------------------ the plugin

def _parse_floats(value, what):
    if isinstance(value, str):
        parts = [p for p in value.replace(",", " ").split() if p]
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: {what} {value!r} is not a list of numbers") from None
    elif isinstance(value, (int, float)):
        vals = [float(value)]
    else:
        try:
            vals = [float(v) for v in np.ravel(np.array(value, dtype=np.float64))]
        except (TypeError, ValueError):
            raise ManifoldBRDFError(
                f"{PLUGIN_NAME}: {what} of type {type(value).__name__} is not a list of numbers") from None
    vals = np.asarray(vals, dtype=np.float64)
    if vals.size == 0 or not np.isfinite(vals).all():
        raise ManifoldBRDFError(f"{PLUGIN_NAME}: {what} {value!r} must be finite numbers")
    return vals


def _resolve(path, what):
    """A path as given in a scene, resolved with Mitsuba's file resolver (which knows
    the folder of the scene being loaded); error naming the folders searched."""
    path = os.fspath(path)
    found = str(mi.file_resolver().resolve(path))
    if not os.path.exists(found):
        fr = mi.file_resolver()
        where = ", ".join(str(fr[i]) for i in range(len(fr)))
        raise ManifoldBRDFError(f"{PLUGIN_NAME}: {what} '{path}' not found (searched {where})")
    return found


class _ManifoldBRDF:
    r"""Measured-material manifold BSDF (``manifold_brdf``).

    One-sided reflection (zero when ``wi`` or ``wo`` is below the surface) from the
    table ``sum_i w_i table_i`` over the materials that survive pruning, negative
    values clamped to 0. ``eval`` returns ``f(wi, wo) cos(theta_o)``.

    Parameters (plugin properties)
    ------------------------------
    manifold : str
        Path of a manifold saved by :meth:`Manifold.save` (resolved like scene files).
    x : str or float
        Latent point, e.g. ``"0.3, -1.2"`` (``q`` numbers). Exposed by ``mi.traverse``
        as ``x``; updating it rebuilds the material.
    material : str
        A training material by name (exactly its measured table).
    weights : str
        ``"name:w, name:w"`` over the manifold's materials, used as given (see
        :meth:`Manifold.parse_weights`).
    database : str
        Folder of ``.binary`` tables, overriding the manifold's; checked by hash.
    prune : float
        Drop materials with ``|w_i| <= prune * sum |w|`` (default 1e-3); the weight
        dropped is reported by ``to_string()``.
    sampling : ``"cdf"`` or ``"cosine"``
        Tabulated importance sampling (default) or the cosine hemisphere alone.
    interpolation : ``"nearest"`` or ``"linear"``
        MERL bin lookup (default) or trilinear interpolation between bin centres
        (periodic in ``phi_d`` over ``pi``).

    Exactly one of ``x``, ``material`` and ``weights`` must be given.

    Sampling: with probability ``COSINE_FRACTION`` a cosine-weighted direction;
    otherwise a half vector ``h`` drawn from the tabulated density over
    ``(u, v) = (sqrt(theta_h / (pi/2)), |phi_h - phi_i| / pi)`` (interpolated in the
    incident elevation), its azimuth sign from the remaining part of ``sample1``,
    and ``wo`` the reflection of ``wi`` about ``h``. The pdf is the mixture of both
    densities, and 0 where the BSDF is 0.

    Python API (to switch materials between renders without reloading the scene):
    :meth:`set_latent`, :meth:`set_material`, :meth:`set_weights`; read-only
    :attr:`manifold`, :attr:`manifold_path`, :attr:`names`, :attr:`weights`,
    :attr:`latent`, :attr:`used_names`, :attr:`dropped_weight`, :attr:`clamped_bins`.
    Instances are recognised by the class attribute ``is_manifold_brdf = True``.
    """

    is_manifold_brdf = True

    def __init__(self, props):
        mi.BSDF.__init__(self, props)
        if not mi.is_rgb or mi.is_polarized:
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: measured RGB tables need an RGB variant "
                                    f"(scalar_rgb, llvm_ad_rgb, cuda_ad_rgb), not {mi.variant()}")
        self.m_flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        self.m_components = [self.m_flags]
        if "manifold" not in props:
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: the 'manifold' parameter (path of a saved manifold) is required")
        path = _resolve(props["manifold"], "manifold file")
        try:
            self._manifold = Manifold.load(path)
        except ManifoldError as e:
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: {e}") from None
        self._manifold_path = path
        self._database = _resolve(props["database"], "database folder") if "database" in props else None
        if self._database is not None and not os.path.isdir(self._database):
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: database {self._database} is not a folder")
        self._prune = float(props.get("prune", DEFAULT_PRUNE))
        if not 0.0 <= self._prune < 1.0:
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: prune must be in [0, 1), got {self._prune}")
        self._sampling = str(props.get("sampling", "cdf")).strip().lower()
        if self._sampling not in SAMPLING_MODES:
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: sampling must be one of {SAMPLING_MODES}, got {self._sampling!r}")
        self._interpolation = str(props.get("interpolation", "nearest")).strip().lower()
        if self._interpolation not in INTERPOLATION_MODES:
            raise ManifoldBRDFError(
                f"{PLUGIN_NAME}: interpolation must be one of {INTERPOLATION_MODES}, got {self._interpolation!r}")

        given = [k for k in ("x", "material", "weights") if k in props]
        if len(given) != 1:
            raise ManifoldBRDFError(
                f"{PLUGIN_NAME}: give exactly one of 'x', 'material' and 'weights' (got {given or 'none'})")
        try:
            if given[0] == "x":
                self.set_latent(_parse_floats(props["x"], "x"))
            elif given[0] == "material":
                self.set_material(str(props["material"]).strip())
            else:
                self.set_weights(self._manifold.parse_weights(props["weights"]))
        except ManifoldError as e:
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: {e}") from None

    # ------------------------------------------------------------ materials

    @property
    def manifold(self):
        """The :class:`Manifold` this material lives on."""
        return self._manifold

    @property
    def manifold_path(self):
        """Resolved path of the manifold file."""
        return self._manifold_path

    @property
    def names(self):
        """Names of the manifold's materials (the order of :attr:`weights`)."""
        return list(self._manifold.names)

    @property
    def weights(self):
        """Weights ``w`` over :attr:`names` currently rendered (a copy; they sum to 1 for ``x``)."""
        return self._w.copy()

    @property
    def latent(self):
        """Latent point of the material (None when set by weights)."""
        return None if self._x is None else self._x.copy()

    @property
    def used_names(self):
        """Materials whose tables enter the combination (after pruning)."""
        return [self._manifold.names[i] for i in self._keep]

    @property
    def dropped_weight(self):
        """``sum |w_i|`` of the materials dropped by pruning."""
        return self._dropped

    @property
    def clamped_bins(self):
        """Number of (channel, bin) values of the combined table clamped from below 0."""
        return self._n_clamped

    def set_latent(self, x):
        """Render the material at latent point ``x`` (``q`` numbers)."""
        x = np.asarray(x, dtype=np.float64).ravel()
        q = self._manifold.q
        if x.size != q or not np.isfinite(x).all():
            raise ManifoldBRDFError(
                f"{PLUGIN_NAME}: x must be {q} finite numbers (the latent dimension of "
                f"{self._manifold_path}), got {x.tolist()}")
        _, w = self._manifold.weights(x)
        self._rebuild(w, x, None)

    def set_material(self, name):
        """Render training material ``name`` (exactly its table)."""
        try:
            i = self._manifold.index(name)
        except ManifoldError as e:
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: {e}") from None
        self._rebuild(self._manifold.material_weights(name), self._manifold.latent[i].copy(), name)

    def set_weights(self, w, table=None):
        """Render ``sum_i w_i table_i``; ``w`` has one weight per name, or is ``{name: w}``.

        Weights are used as given; they must not sum to 0. ``table`` (shape
        ``(3, n_theta_h, n_theta_d, n_phi_d)``), when the caller already has that sum over
        the materials kept by pruning, is used instead of reading and adding the tables.
        """
        if isinstance(w, dict):
            full = np.zeros(len(self._manifold.names))
            for name, value in w.items():
                if name not in self._manifold.names:
                    raise ManifoldBRDFError(f"{PLUGIN_NAME}: unknown material {name!r} in weights "
                                            f"(the manifold has {', '.join(self._manifold.names[:6])}, ...)")
                full[self._manifold.names.index(name)] += float(value)
            w = full
        w = np.asarray(w, dtype=np.float64)
        n = len(self._manifold.names)
        if w.shape != (n,) or not np.isfinite(w).all():
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: weights must be {n} finite numbers (one per material), "
                                    f"got shape {w.shape}")
        if abs(w.sum()) < 1e-12:
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: weights sum to zero; a material needs weights summing to 1")
        self._rebuild(w, None, None, table)

    def _rebuild(self, w, x, material, table=None):
        """Combine the tables (unless ``table`` is given) and sampling densities for weights ``w``, upload them."""
        m = self._manifold
        try:
            if table is None:
                table, keep, dropped = m.combine(w, prune=self._prune, database=self._database)
            else:
                keep, _, dropped = m.prune(w, self._prune)
            db = m.open_database(self._database, [m.names[i] for i in keep]) if self._sampling == "cdf" else None
        except (ValueError, KeyError, OSError) as e:  # ManifoldError, damaged or missing files
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: {e}") from None
        table = np.asarray(table, dtype=np.float32)
        if table.ndim != 4 or table.shape[0] != 3:
            raise ManifoldBRDFError(
                f"{PLUGIN_NAME}: combined table has shape {table.shape}, expected (3, nh, nd, nphi)")
        if not np.isfinite(table).all():
            raise ManifoldBRDFError(f"{PLUGIN_NAME}: the combined table has NaN or Inf values")
        negative = table < 0
        n_clamped = int(negative.sum())
        if n_clamped:
            table = np.where(negative, np.float32(0), table)
        dims = tuple(int(d) for d in table.shape[1:])
        packed = np.ascontiguousarray(table.reshape(3, -1).T)        # (bins, 3): RGB together

        distr, black = None, False
        if self._sampling == "cdf":
            w_kept = np.asarray(w, dtype=np.float64)[keep]
            dens = np.stack([material_density(db, m.names[i]) for i in keep])
            p, n_empty = combined_density(dens, w_kept)
            black = n_empty == p.shape[0]
            theta_grid = np.linspace(0.0, _HALF_PI, SAMPLING_GRID[0])
            distr = mi.MarginalContinuous2D1(p, [theta_grid.tolist()], normalize=True)

        # Commit only once everything succeeded.
        self._w = np.asarray(w, dtype=np.float64).copy()
        self._x = None if x is None else np.asarray(x, dtype=np.float64).copy()
        self._material = material
        self._keep = np.asarray(keep)
        self._dropped = float(dropped)
        self._n_clamped = n_clamped
        self._n_values = int(table.size)
        self._black = black
        self._dims = dims
        self._distr = distr
        self._cos_frac = 1.0 if distr is None else COSINE_FRACTION
        self._table = mi.Float(packed.ravel()) if dr.is_jit_v(mi.Float) else packed
        if self._x is not None:
            # Parameter objects returned by an earlier mi.traverse hold this array: update
            # it in place (the latent dimension never changes), create it the first time.
            if getattr(self, "_x_param", None) is None:
                array = mi.Float if dr.is_jit_v(mi.Float) else dr.scalar.ArrayXf
                self._x_param = array(self._x)
            else:
                for i, value in enumerate(self._x):
                    self._x_param[i] = float(value)

    # --------------------------------------------------------- lookups

    def _gather(self, idx, active):
        if dr.is_jit_v(mi.Float):
            return dr.gather(mi.Color3f, self._table, idx, active)
        if not active:
            return mi.Color3f(0.0)
        r, g, b = self._table[int(idx)]
        return mi.Color3f(float(r), float(g), float(b))

    def _lookup(self, wi, wo, active):
        """Table value ``f(wi, wo)`` (no cosine) for directions above the surface."""
        n_h, n_d, n_p = self._dims
        theta_h, theta_d, phi_d = merl_angles(wi, wo)
        if self._interpolation == "nearest":
            return self._gather(merl_bin(theta_h, theta_d, phi_d, self._dims), active)
        th = dr.clip(theta_h, 0.0, _HALF_PI)
        h0, h1, th_t = _linear_axis(dr.sqrt(th * (1.0 / _HALF_PI)) * n_h, n_h)
        d0, d1, td_t = _linear_axis(theta_d * (n_d / _HALF_PI), n_d)
        c = phi_d * (n_p / np.pi) - 0.5
        fc = dr.floor(c)
        tp_t = c - fc
        p0 = mi.Int32(fc)
        p0 = dr.select(p0 < 0, p0 + n_p, p0)
        p1 = p0 + 1
        p1 = dr.select(p1 >= n_p, p1 - n_p, p1)
        result = mi.Color3f(0.0)
        for ih, wh in ((h0, 1.0 - th_t), (h1, th_t)):
            for id_, wd in ((d0, 1.0 - td_t), (d1, td_t)):
                for ip, wp in ((p0, 1.0 - tp_t), (p1, tp_t)):
                    idx = mi.UInt32((ih * n_d + id_) * n_p + ip)
                    result += self._gather(idx, active) * (wh * wd * wp)
        return result

    def _pdf_table(self, wi, wo, active):
        """Density (solid angle) of the tabulated half-vector strategy at ``wo``."""
        h = wi + wo
        rh = dr.sqrt(dr.square(h.x) + dr.square(h.y))
        inv_len = dr.rsqrt(dr.square(rh) + dr.square(h.z))
        u = dr.sqrt(dr.atan2(rh, h.z) * (1.0 / _HALF_PI))
        ex, ey, theta_i = self._incident_frame(wi)
        v = dr.abs(dr.atan2(ex * h.y - ey * h.x, ex * h.x + ey * h.y)) * (1.0 / np.pi)
        p_uv = self._distr.eval(mi.Point2f(dr.maximum(u, _U_FLOOR), v), [theta_i], active)
        return self._per_solid_angle(p_uv, u, rh * inv_len, dr.dot(wi, h) * inv_len, active)

    @staticmethod
    def _per_solid_angle(p_uv, u, sin_th, cos_d, active):
        """Density over ``(u, v)`` to density over ``wo``: divide by ``|d wo / d(u, v)|``.

        ``wo = reflect(wi, h)`` gives ``d wo = 4 cos_d d h``, ``d h = sin_th d theta_h d phi``,
        ``theta_h = u^2 pi/2`` and ``phi = +-v pi`` (each sign with probability 1/2):
        ``|d wo / d(u, v)| = 8 pi^2 cos_d sin_th u``. The density grows like 1/theta_h
        towards the mirror direction, and single precision rounds directions within
        ~1e-7 of it onto it (u = 0): those are evaluated at a tiny ``u`` instead of
        letting the Jacobian vanish (which would drop the tabulated part).
        """
        near = u < _U_FLOOR
        u = dr.maximum(u, _U_FLOOR)
        sin_th = dr.select(near, _SIN_FLOOR, sin_th)
        jac = (8.0 * np.pi * np.pi) * cos_d * sin_th * u
        ok = active & (jac > 0)
        return dr.select(ok, p_uv / dr.select(ok, jac, 1.0), 0.0)

    @staticmethod
    def _incident_frame(wi):
        """Unit azimuth ``(ex, ey)`` of ``wi`` (x axis at normal incidence) and its elevation."""
        r = dr.sqrt(dr.square(wi.x) + dr.square(wi.y))
        has = r > 0
        inv_r = dr.select(has, dr.rcp(dr.select(has, r, 1.0)), 0.0)
        ex = dr.select(has, wi.x * inv_r, 1.0)
        ey = dr.select(has, wi.y * inv_r, 0.0)
        return ex, ey, dr.atan2(r, wi.z)

    def _eval_pdf(self, ctx, si, wo, active, p_table=None, known=None):
        """``f cos(theta_o)`` and the pdf at ``wo``; the pdf is 0 where ``f`` is.

        Lanes in ``known`` take the tabulated strategy's density from ``p_table``
        (computed while sampling) instead of evaluating it again.
        """
        wi = si.wi
        active = active & (wi.z > 0) & (wo.z > 0)
        f = self._lookup(wi, wo, active)
        nonzero = active & ((f.x > 0) | (f.y > 0) | (f.z > 0))
        pdf = self._cos_frac * mi.warp.square_to_cosine_hemisphere_pdf(wo)
        if self._distr is not None:
            if known is None:
                p = self._pdf_table(wi, wo, nonzero)
            else:
                p = dr.select(known, p_table, self._pdf_table(wi, wo, dr.select(known, False, nonzero)))
            pdf += (1.0 - self._cos_frac) * p
        value = dr.select(nonzero, f * wo.z, 0.0)
        return value, dr.select(nonzero, pdf, 0.0)

    # --------------------------------------------------------- BSDF interface

    def eval(self, ctx, si, wo, active=True):
        if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
            return mi.Color3f(0.0)
        wi = si.wi
        active = active & (wi.z > 0) & (wo.z > 0)
        return dr.select(active, self._lookup(wi, wo, active) * wo.z, 0.0)

    def pdf(self, ctx, si, wo, active=True):
        if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
            return mi.Float(0.0)
        return self._eval_pdf(ctx, si, wo, active)[1]

    def eval_pdf(self, ctx, si, wo, active=True):
        if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
            return mi.Color3f(0.0), mi.Float(0.0)
        return self._eval_pdf(ctx, si, wo, active)

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs = dr.zeros(mi.BSDFSample3f)
        wi = si.wi
        active = active & (wi.z > 0)
        if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
            return bs, mi.Color3f(0.0)
        wo = mi.warp.square_to_cosine_hemisphere(sample2)
        p_table, use_table = None, None
        if self._distr is not None:
            alpha = self._cos_frac
            use_table = active & (sample1 >= alpha)
            flip = (sample1 - alpha) >= 0.5 * (1.0 - alpha)
            ex, ey, theta_i = self._incident_frame(wi)
            uv, p_uv = self._distr.sample(sample2, [theta_i], use_table)
            theta_h = dr.square(uv.x) * _HALF_PI
            phi = dr.select(flip, -uv.y, uv.y) * np.pi
            sin_th, cos_th = dr.sincos(theta_h)
            sin_p, cos_p = dr.sincos(phi)
            hx, hy = sin_th * cos_p, sin_th * sin_p
            h = mi.Vector3f(ex * hx - ey * hy, ey * hx + ex * hy, cos_th)
            p_table = self._per_solid_angle(p_uv, uv.x, sin_th, dr.dot(wi, h), use_table)
            wo = dr.select(use_table, mi.reflect(wi, h), wo)
        value, pdf = self._eval_pdf(ctx, si, wo, active, p_table, use_table)
        ok = active & (pdf > 0)
        bs.wo = wo
        bs.pdf = dr.select(ok, pdf, 0.0)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
        bs.sampled_component = mi.UInt32(0)
        weight = dr.select(ok, value / dr.select(ok, pdf, 1.0), 0.0)
        return bs, weight

    # --------------------------------------------------------- parameters

    def traverse(self, callback):
        if self._x is not None:
            callback.put("x", self._x_param, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys=[]):
        if getattr(self, "_x_param", None) is None or (keys and "x" not in keys):
            return
        x = np.array(self._x_param, dtype=np.float64).ravel()
        if self._x is None or x.shape != self._x.shape or not np.array_equal(x, self._x.astype(np.float32)):
            self.set_latent(x)

    def to_string(self):
        if self._material is not None:
            what = f"material = {self._material}"
        elif self._x is not None:
            what = "x = [" + ", ".join(f"{v:.6g}" for v in self._x) + "]"
        else:
            what = "weights = given"
        order = self._keep[np.argsort(-np.abs(self._w[self._keep]))]
        top = ", ".join(f"{self._manifold.names[i]}:{self._w[i]:.4g}" for i in order[:6])
        more = f", ... ({len(order)} in all)" if len(order) > 6 else ""
        return (f"ManifoldBRDF[\n"
                f"  manifold = {self._manifold_path},\n"
                f"  database = {self._database or self._manifold.database},\n"
                f"  {what},\n"
                f"  weights used = {top}{more},\n"
                f"  dropped weight = {self._dropped:.4g} (prune = {self._prune:g}),\n"
                f"  resolution = {self._dims[0]}x{self._dims[1]}x{self._dims[2]},\n"
                f"  clamped bins = {self._n_clamped} of {self._n_values} values below 0,\n"
                f"  interpolation = {self._interpolation},\n"
                f"  sampling = {self._sampling}"
                + (" (the material reflects nothing)" if self._black else "") + "\n]")


_CLASSES = {}


def bsdf_class(variant=None):
    """The ``manifold_brdf`` class for ``variant`` (default: the active one).

    Mitsuba's ``BSDF`` base class differs per variant, so one class is made per variant.
    """
    variant = variant or mi.variant()
    if variant is None:
        raise RuntimeError(f"{PLUGIN_NAME}: call mi.set_variant(...) first")
    cls = _CLASSES.get(variant)
    if cls is None:
        if variant != mi.variant():
            raise RuntimeError(f"{PLUGIN_NAME}: variant {variant!r} is not active")
        namespace = {k: v for k, v in vars(_ManifoldBRDF).items() if k not in ("__dict__", "__weakref__")}
        namespace["__qualname__"] = "ManifoldBRDF"
        cls = type("ManifoldBRDF", (mi.BSDF,), namespace)
        _CLASSES[variant] = cls
    return cls


def register():
    """Register ``manifold_brdf`` with Mitsuba for the active variant; returns the class."""
    cls = bsdf_class()
    mi.register_bsdf(PLUGIN_NAME, lambda props: cls(props))
    return cls
