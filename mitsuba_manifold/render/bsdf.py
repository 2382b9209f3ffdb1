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

import operator
import os

import drjit as dr
import mitsuba as mi
import numpy as np

from . import plugin
from .lookups import HALF_PI, linear_axis, merl_angles, merl_bin
from .sampling import PLUGIN_NAME, SAMPLING_GRID, combined_density, material_density, sampling_cache_path, sampling_density
from ..errors import InputError, VariantError
from ..manifold.model import DEFAULT_PRUNE, Manifold
from .overrides import database_folder
from .._util.checks import weight_sum

#: Probability of sampling the cosine hemisphere instead of the tabulated density.
COSINE_FRACTION = 0.1

SAMPLING_MODES = ("cdf", "cosine")
INTERPOLATION_MODES = ("nearest", "linear")

_U_FLOOR = 1e-4                                  # smallest u = sqrt(theta_h / (pi/2)) used by the pdf
_SIN_FLOOR = float(np.sin(_U_FLOOR ** 2 * HALF_PI))


# ------------------------------------------------------------------ the plugin

def _parse_floats(value, what):
    if isinstance(value, str):
        parts = [p for p in value.replace(",", " ").split() if p]
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise InputError(f"{PLUGIN_NAME}: {what} {value!r} is not a list of numbers") from None
    elif isinstance(value, (int, float)):
        vals = [float(value)]
    else:
        try:
            vals = [float(v) for v in np.ravel(np.array(value, dtype=np.float64))]
        except (TypeError, ValueError):
            raise InputError(
                f"{PLUGIN_NAME}: {what} of type {type(value).__name__} is not a list of numbers") from None
    vals = np.asarray(vals, dtype=np.float64)
    if vals.size == 0 or not np.isfinite(vals).all():
        raise InputError(f"{PLUGIN_NAME}: {what} {value!r} must be finite numbers")
    return vals


def _resolve(path, what):
    """A path as given in a scene, resolved with Mitsuba's file resolver (which knows
    the folder of the scene being loaded); error naming the folders searched."""
    path = os.fspath(path)
    found = str(mi.file_resolver().resolve(path))
    if not os.path.exists(found):
        fr = mi.file_resolver()
        where = ", ".join(str(fr[i]) for i in range(len(fr)))
        raise InputError(f"{PLUGIN_NAME}: {what} '{path}' not found (searched {where})")
    return found


def _read_only(attr, doc):
    """A read-only property returning ``self.<attr>``."""
    return property(operator.attrgetter(attr), doc=doc)


class ManifoldBRDF:
    r"""Measured-material manifold BSDF (``manifold_brdf``).

    One-sided reflection (zero when ``wi`` or ``wo`` is below the surface) from the
    table ``sum_i w_i table_i`` over the materials that survive pruning, negative
    values clamped to 0. ``eval`` returns ``f(wi, wo) cos(theta_o)``.

    Parameters (plugin properties)
    ------------------------------
    manifold : str
        Path of a manifold saved by :meth:`Manifold.save` (resolved like scene files).
    x : str or float
        Latent point, e.g. ``"0.3, -1.2"`` (``q`` numbers); empty: the first material's
        point, which fits a manifold of any latent dimension (the shipped scenes' default).
        Exposed by ``mi.traverse`` as ``x``; updating it rebuilds the material.
    material : str
        A training material by name (exactly its measured table).
    weights : str
        ``"name:w, name:w"`` over the manifold's materials, used as given (see
        :meth:`Manifold.parse_weights`).
    database : str
        Folder of ``.binary`` tables, overriding the manifold's; checked by hash.
    prune : float
        Drop the materials of smallest contribution ``|w_i| |table_i|`` while the table
        changes by at most ``prune`` of its L2 norm (default 0.01, :meth:`Manifold.prune`);
        the table error and the weight dropped are reported by ``to_string()``.
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
    :attr:`manifold`, :attr:`manifold_path`, :attr:`database`,
    :attr:`interpolation`, :attr:`sampling`, :attr:`names`, :attr:`weights`,
    :attr:`latent`, :attr:`used_names`, :attr:`dropped_weight`, :attr:`clamped_bins`.
    Instances are recognised by the class attribute ``is_manifold_brdf = True``.
    """

    is_manifold_brdf = True

    def __init__(self, props):
        self._base.__init__(self, props)
        if not mi.is_rgb or mi.is_polarized:
            raise InputError(f"{PLUGIN_NAME}: measured RGB tables need an RGB variant "
                                    f"(scalar_rgb, llvm_ad_rgb, cuda_ad_rgb), not {mi.variant()}")
        self.m_flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        self.m_components = [self.m_flags]
        if "manifold" not in props:
            raise InputError(f"{PLUGIN_NAME}: the 'manifold' parameter (path of a saved manifold) is required")
        path = _resolve(props["manifold"], "manifold file")
        try:
            self._manifold = Manifold.load(path)
        except InputError as e:
            raise InputError(f"{PLUGIN_NAME}: {e}") from None
        self._manifold_path = path
        database = props["database"] if "database" in props else database_folder()
        self._database = _resolve(database, "database folder") if database is not None else None
        if self._database is not None and not os.path.isdir(self._database):
            raise InputError(f"{PLUGIN_NAME}: database {self._database} is not a folder")
        prune = props.get("prune", DEFAULT_PRUNE)
        try:
            self._prune = float(prune)
        except (TypeError, ValueError):
            raise InputError(f"{PLUGIN_NAME}: prune must be a number in [0, 1), got {prune!r}") from None
        if not 0.0 <= self._prune < 1.0:
            raise InputError(f"{PLUGIN_NAME}: prune must be in [0, 1), got {self._prune}")
        self._sampling = str(props.get("sampling", "cdf")).strip().lower()
        if self._sampling not in SAMPLING_MODES:
            raise InputError(f"{PLUGIN_NAME}: sampling must be one of {SAMPLING_MODES}, got {self._sampling!r}")
        self._interpolation = str(props.get("interpolation", "nearest")).strip().lower()
        if self._interpolation not in INTERPOLATION_MODES:
            raise InputError(
                f"{PLUGIN_NAME}: interpolation must be one of {INTERPOLATION_MODES}, got {self._interpolation!r}")

        given = [k for k in ("x", "material", "weights") if k in props]
        if len(given) != 1:
            raise InputError(
                f"{PLUGIN_NAME}: give exactly one of 'x', 'material' and 'weights' (got {given or 'none'})")
        try:
            if given[0] == "x" and str(props["x"]).strip() == "":
                self.set_latent(self._manifold.latent[0])
            elif given[0] == "x":
                self.set_latent(_parse_floats(props["x"], "x"))
            elif given[0] == "material":
                self.set_material(str(props["material"]).strip())
            else:
                self.set_weights(self._manifold.parse_weights(props["weights"]))
        except InputError as e:
            raise InputError(f"{PLUGIN_NAME}: {e}") from None

    # ------------------------------------------------------------ materials

    manifold = _read_only("_manifold", "The :class:`Manifold` this material lives on.")
    manifold_path = _read_only("_manifold_path", "Resolved path of the manifold file.")
    database = _read_only("_database", "Database folder of the ``database`` parameter (None: the manifold's own).")
    interpolation = _read_only("_interpolation", "Table lookup: ``'nearest'`` or ``'linear'``.")
    sampling = _read_only("_sampling", "Sampling strategy: ``'cdf'`` or ``'cosine'``.")

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

    dropped_weight = _read_only("_dropped", "``sum |w_i|`` of the materials dropped by pruning.")
    prune_error = _read_only("_prune_error", "Relative L2 change of the table made by pruning (exact).")
    clamped_bins = _read_only("_n_clamped", "Number of (channel, bin) values of the combined table clamped below 0.")

    def set_latent(self, x):
        """Render the material at latent point ``x`` (``q`` numbers)."""
        x = np.asarray(x, dtype=np.float64).ravel()
        q = self._manifold.q
        if x.size != q or not np.isfinite(x).all():
            raise InputError(
                f"{PLUGIN_NAME}: x must be {q} finite numbers (the latent dimension of "
                f"{self._manifold_path}), got {x.tolist()}")
        _, w = self._manifold.weights(x)
        self._rebuild(w, x, None)

    def set_material(self, name):
        """Render training material ``name`` (exactly its table)."""
        try:
            i = self._manifold.index(name)
        except InputError as e:
            raise InputError(f"{PLUGIN_NAME}: {e}") from None
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
                    raise InputError(f"{PLUGIN_NAME}: unknown material {name!r} in weights "
                                            f"(the manifold has {', '.join(self._manifold.names[:6])}, ...)")
                full[self._manifold.names.index(name)] += float(value)
            w = full
        w = np.asarray(w, dtype=np.float64)
        n = len(self._manifold.names)
        if w.shape != (n,) or not np.isfinite(w).all():
            raise InputError(f"{PLUGIN_NAME}: weights must be {n} finite numbers (one per material), "
                                    f"got shape {w.shape}")
        try:
            weight_sum(w)
        except InputError as e:
            raise InputError(f"{PLUGIN_NAME}: {e}") from None
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
        except (ValueError, KeyError, OSError) as e:  # InputError, damaged or missing files
            raise InputError(f"{PLUGIN_NAME}: {e}") from None
        table = np.asarray(table, dtype=np.float32)
        if table.ndim != 4 or table.shape[0] != 3:
            raise InputError(
                f"{PLUGIN_NAME}: combined table has shape {table.shape}, expected (3, nh, nd, nphi)")
        if not np.isfinite(table).all():
            raise InputError(f"{PLUGIN_NAME}: the combined table has NaN or Inf values")
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
            theta_grid = np.linspace(0.0, HALF_PI, SAMPLING_GRID[0])
            distr = mi.MarginalContinuous2D1(p, [theta_grid.tolist()], normalize=True)

        # Commit only once everything succeeded.
        self._w = np.asarray(w, dtype=np.float64).copy()
        self._x = None if x is None else np.asarray(x, dtype=np.float64).copy()
        self._material = material
        self._keep = np.asarray(keep)
        self._dropped = float(dropped)
        self._prune_error = m.prune_error(w, keep)
        self._n_clamped = n_clamped
        self._n_values = int(table.size)
        self._black = black
        self._dims = dims
        self._distr = distr
        self._cos_frac = 1.0 if distr is None else COSINE_FRACTION
        self._table = mi.Float(packed.ravel()) if dr.is_jit_v(mi.Float) else packed
        if self._x is not None:
            self._publish_x()

    def _publish_x(self):
        """The ``x`` parameter as the rendered ``self._x``. Parameter objects returned by an
        earlier mi.traverse hold this array: replaced in place (length too), created the first time."""
        array = (mi.Float if dr.is_jit_v(mi.Float) else dr.scalar.ArrayXf)(self._x)
        if getattr(self, "_x_param", None) is None:
            self._x_param = array
        else:
            mi.set_property(self._x_param, array)

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
        th = dr.clip(theta_h, 0.0, HALF_PI)
        h0, h1, th_t = linear_axis(dr.sqrt(th * (1.0 / HALF_PI)) * n_h, n_h)
        d0, d1, td_t = linear_axis(theta_d * (n_d / HALF_PI), n_d)
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
        u = dr.sqrt(dr.atan2(rh, h.z) * (1.0 / HALF_PI))
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
            theta_h = dr.square(uv.x) * HALF_PI
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
            try:
                self.set_latent(x)
            except Exception:  # refused: back to the material still rendered (its length too),
                if self._x is not None:  # so that later updates work
                    self._publish_x()
                raise

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
                f"  pruning: table error {100 * self._prune_error:.3g}% (L2), dropped weight = {self._dropped:.4g} "
                f"(prune = {self._prune:g}),\n"
                f"  resolution = {self._dims[0]}x{self._dims[1]}x{self._dims[2]},\n"
                f"  clamped bins = {self._n_clamped} of {self._n_values} values below 0,\n"
                f"  interpolation = {self._interpolation},\n"
                f"  sampling = {self._sampling}"
                + (" (the material reflects nothing)" if self._black else "") + "\n]")


def bsdf_class():
    """The ``manifold_brdf`` class for the active variant (see :func:`plugin.plugin_class`)."""
    if mi.variant() is None:
        raise VariantError(f"{PLUGIN_NAME}: call mi.set_variant(...) first")
    return plugin.plugin_class(ManifoldBRDF, mi.BSDF)


def register():
    """Register ``manifold_brdf`` with Mitsuba for the active variant; returns the class."""
    return plugin.register_plugin("bsdf", PLUGIN_NAME, ManifoldBRDF)
