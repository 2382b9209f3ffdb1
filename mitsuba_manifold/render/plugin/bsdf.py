"""The ``manifold_brdf`` Mitsuba BSDF: any point of a material manifold, rendered.

The material is the affine combination ``sum_i w_i table_i`` of measured MERL tables,
with weights ``w`` from a latent point ``x`` (:meth:`Manifold.weights`), a training
material, or given explicitly. The combination is computed once per material and kept
on the device as one table (:func:`.material.combine`); evaluation looks it up with
MERL's half/diff indexing (:func:`.lookups.table_value`).

Importance sampling follows the paper's Sec. 5.3: every measured material has, for a
grid of incident elevations, a tabulated unnormalised density of outgoing directions
(cached beside the database, keyed by the table's hash). By linearity the density of
the combination is ``sum_i w_i P_i``, clamped at 0, and Mitsuba's
``MarginalContinuous2D1`` samples it (:mod:`.sampling`).

A plugin module as Mitsuba's own: the class derives from the active variant's ``mi.BSDF``
and the last line registers it; :mod:`.plugins` imports (or reloads) this module for each
variant, so import it only with a variant set (``import mitsuba_manifold.render`` does that).
"""

import dataclasses
import operator
from functools import partial

import drjit as dr
import mitsuba as mi
import numpy as np

from ..._util.checks import latent_point, weight_sum
from ...errors import InputError
from . import ad
from .lookups import gather_rgb, table_value
from .material import combine, read_properties
from .sampling import (
    PLUGIN_NAME,
    combined_distribution,
    half_vector_pdf,
    material_density,
    prefixed,
    sample_half_vector,
)

#: Probability of sampling the cosine hemisphere instead of the tabulated density.
COSINE_FRACTION = 0.1


def _read_only(attr, doc):
    """A read-only property returning ``self.<attr>``."""
    return property(operator.attrgetter(attr), doc=doc)


class ManifoldBRDF(mi.BSDF):
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
        Exposed by ``mi.traverse`` as ``x``; updating it rebuilds the material. In AD
        variants ``x`` is differentiable: once it is grad-enabled (``dr.enable_grad``,
        then ``params.update()``), the material is the same pruned, rescaled combination,
        evaluated as ``max(0, sum_k v_k table_k)`` over device slots whose weights follow
        ``x`` (:mod:`.ad`; the gradient holds pruning's selection fixed), and sampling uses a
        detached proxy (the pdf is never differentiated). Without gradients (and in non-AD
        and scalar variants) the material is one combined table.
    ad_terms : int
        Minimum number K of device slots in AD mode (default 8; more when pruning keeps more
        materials; fixed otherwise, so moving ``x`` recompiles nothing).
    material : str
        A training material by name (exactly its measured table).
    weights : str
        ``"name:w, name:w"`` over the manifold's materials, used as given (see
        :meth:`Manifold.parse_weights`).
    database : str
        Folder of ``.binary`` tables, overriding the manifold's; checked by hash.
    prune : float
        Pruning budget (default 0.01, :meth:`Manifold.prune`, rule ``"image"``): the fewest
        materials, their weights rescaled to the same sum, such that each albedo channel
        changes by at most ``prune / 2`` and the cosine-weighted and raw table by at most
        ``prune`` of their norms; what was kept and reached is reported by ``to_string()``.
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
    Setting the attribute ``hold_proxy = True`` keeps the current sampling density through later
    material changes (with and without gradients): renders at nearby materials then draw the same
    directions from the same random numbers, as central differences need.
    ``isinstance(shape.bsdf(), mitsuba_manifold.render.plugin.bsdf.ManifoldBRDF)`` tells a manifold
    material in the active variant (as the package's integrators do); the class attribute
    ``is_manifold_brdf = True`` is kept for callers that tested it before.
    """

    is_manifold_brdf = True

    def __init__(self, props):
        super().__init__(props)
        self.m_flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        self.m_components = [self.m_flags]
        self._manifold, self._options = read_properties(props)
        self._x_param = None
        self._gather, self._active, self._w, self.hold_proxy = gather_rgb, None, None, False
        self._ad_terms = int(props.get("ad_terms", ad.DEFAULT_TERMS))
        if self._ad_terms < 1:
            raise InputError(f"{PLUGIN_NAME}: ad_terms must be >= 1, got {self._ad_terms}")
        chooser, value = self._options.chooser, self._options.value
        try:
            if chooser == "x" and str(value).strip() == "":
                self.set_latent(self._manifold.latent[0])
            elif chooser == "x":
                self.set_latent(value)
            elif chooser == "material":
                self.set_material(str(value).strip())
            else:
                self.set_weights(self._manifold.parse_weights(value))
        except InputError as e:
            raise InputError(prefixed(e)) from None

    # ------------------------------------------------------------ materials

    manifold = _read_only("_manifold", "The :class:`Manifold` this material lives on.")
    manifold_path = _read_only("_options.manifold_path", "Resolved path of the manifold file.")
    database = _read_only(
        "_options.database",
        "Database folder of the ``database`` parameter (None: the manifold's own).",
    )
    interpolation = _read_only(
        "_options.interpolation", "Table lookup: ``'nearest'`` or ``'linear'``."
    )
    sampling = _read_only("_options.sampling", "Sampling strategy: ``'cdf'`` or ``'cosine'``.")
    dropped_weight = _read_only("_c.dropped", "``sum |w_i|`` of the materials dropped by pruning.")
    prune_error = _read_only(
        "_c.prune_error", "Relative L2 change of the table made by pruning (exact)."
    )
    clamped_bins = _read_only(
        "_c.n_clamped", "Number of (channel, bin) values of the combined table clamped below 0."
    )

    @property
    def names(self):
        """Names of the manifold's materials (the order of :attr:`weights`)."""
        return list(self._manifold.names)

    @property
    def weights(self):
        """Weights ``w`` over :attr:`names` currently rendered (a copy; they sum to 1 for ``x``)."""
        return self._c.w.copy()

    @property
    def latent(self):
        """Latent point of the material (None when set by weights)."""
        return None if self._c.x is None else self._c.x.copy()

    @property
    def used_names(self):
        """Materials whose tables enter the combination (after pruning)."""
        return [self._manifold.names[i] for i in self._c.keep]

    def set_latent(self, x):
        """Render the material at latent point ``x`` (``q`` numbers). In AD mode
        (:attr:`differentiable`) the point is the grad-enabled parameter's value: set it through
        ``params["<id>.x"]`` and ``params.update()``.
        """
        try:  # the one check of a latent point (text "0.3, -1.2", a sequence or an array)
            x = latent_point("x", x, self._manifold.q)
        except InputError as e:
            raise InputError(prefixed(e, f" ({self.manifold_path})")) from None
        if self.differentiable:
            self._update_ad()
            return
        _, w = self._manifold.weights(x)
        self._rebuild(w, x, None)

    def set_material(self, name):
        """Render training material ``name`` (exactly its table)."""
        try:
            i = self._manifold.index(name)
        except InputError as e:
            raise InputError(prefixed(e)) from None
        self._rebuild(self._manifold.material_weights(name), self._manifold.latent[i].copy(), name)

    def set_weights(self, w, table=None):
        """Render ``sum_i w_i table_i``; ``w`` has one weight per name, or is ``{name: w}``.

        Weights are used as given; they must not sum to 0. ``table`` (shape
        ``(3, n_theta_h, n_theta_d, n_phi_d)``), when the caller already has that sum over
        the materials kept by pruning, is used instead of reading and adding the tables.
        """
        names = self._manifold.names
        if isinstance(w, dict):
            full = np.zeros(len(names))
            for name, value in w.items():
                if name not in names:
                    raise InputError(
                        f"{PLUGIN_NAME}: unknown material {name!r} in weights "
                        f"(the manifold has {', '.join(names[:6])}, ...)"
                    )
                full[names.index(name)] += float(value)
            w = full
        w = np.asarray(w, dtype=np.float64)
        if w.shape != (len(names),) or not np.isfinite(w).all():
            raise InputError(
                f"{PLUGIN_NAME}: weights must be {len(names)} finite numbers (one per material), "
                f"got shape {w.shape}"
            )
        try:
            weight_sum(w)
        except InputError as e:
            raise InputError(prefixed(e)) from None
        self._rebuild(w, None, None, table)

    def _rebuild(self, w, x, material, table=None):
        """Combine the tables and sampling densities for weights ``w``; committed only once
        everything succeeded.
        """
        c = combine(self._manifold, self._options, w, x, material, table)
        if self.hold_proxy and getattr(self, "_c", None) is not None and self._c.distr is not None:
            c = dataclasses.replace(c, distr=self._c.distr, black=self._c.black)
        self._c = c
        self._gather, self._w = gather_rgb, None
        self._cos_frac = 1.0 if self._c.distr is None else COSINE_FRACTION
        if self._c.x is not None:
            self._publish_x()

    def _publish_x(self):
        """The ``x`` parameter as the rendered latent point. Parameter objects returned by an
        earlier mi.traverse hold this array: replaced in place (length too), created the first time.
        """
        array = (mi.Float if dr.is_jit_v(mi.Float) else dr.scalar.ArrayXf)(self._c.x)
        if self._x_param is None:
            self._x_param = array
        else:
            mi.set_property(self._x_param, array)

    # --------------------------------------------------------- BSDF interface

    def _eval_pdf(self, ctx, si, wo, active, p_table=None, known=None):
        """``f cos(theta_o)`` and the pdf at ``wo``; the pdf is 0 where ``f`` is.

        Lanes in ``known`` take the tabulated strategy's density from ``p_table``
        (computed while sampling) instead of evaluating it again.
        """
        wi, c = si.wi, self._c
        active = active & (wi.z > 0) & (wo.z > 0)
        f = table_value(c.table, c.dims, self.interpolation, wi, wo, active, self._gather)
        nonzero = active & ((f.x > 0) | (f.y > 0) | (f.z > 0))
        pdf = self._cos_frac * mi.warp.square_to_cosine_hemisphere_pdf(wo)
        if c.distr is not None:
            if known is None:
                p = half_vector_pdf(c.distr, wi, wo, nonzero)
            else:
                p = dr.select(
                    known,
                    p_table,
                    half_vector_pdf(c.distr, wi, wo, dr.select(known, False, nonzero)),
                )
            pdf += (1.0 - self._cos_frac) * p
        value = dr.select(nonzero, f * wo.z, 0.0)
        return value, dr.detach(dr.select(nonzero, pdf, 0.0))

    def eval(self, ctx, si, wo, active=True):
        if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection):
            return mi.Color3f(0.0)
        wi, c = si.wi, self._c
        active = active & (wi.z > 0) & (wo.z > 0)
        f = table_value(c.table, c.dims, self.interpolation, wi, wo, active, self._gather)
        return dr.select(active, f * wo.z, 0.0)

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
        if self._c.distr is not None:
            alpha = self._cos_frac
            use_table = active & (sample1 >= alpha)
            flip = (sample1 - alpha) >= 0.5 * (1.0 - alpha)
            wo_table, p_table = sample_half_vector(self._c.distr, wi, sample2, flip, use_table)
            wo = dr.select(use_table, wo_table, wo)
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
        if self._c.x is not None:
            flags = (
                mi.ParamFlags.Differentiable
                if dr.is_diff_v(mi.Float)
                else mi.ParamFlags.NonDifferentiable
            )
            callback.put("x", self._x_param, flags)

    def parameters_changed(self, keys=()):
        if self._x_param is None or (keys and "x" not in keys):
            return
        x = np.array(self._x_param, dtype=np.float64).ravel()
        if self.differentiable:
            self.set_latent(x)
            return
        rendered = self._c.x if self._w is None else None  # leaving AD mode: rebuild
        if (
            rendered is None
            or x.shape != rendered.shape
            or not np.array_equal(x, rendered.astype(np.float32))
        ):
            try:
                self.set_latent(x)
            except Exception:  # refused: back to the material still rendered (its length too),
                if self._c.x is not None:  # so that later updates work
                    self._publish_x()
                raise

    # --------------------------------------------------------- AD mode

    @property
    def differentiable(self):
        """True in an AD variant while the ``x`` parameter is grad-enabled (:mod:`.ad` mode)."""
        return (
            dr.is_diff_v(mi.Float) and self._x_param is not None and dr.grad_enabled(self._x_param)
        )

    @property
    def active_set(self):
        """The :class:`.ad.ActiveSet` of AD mode (None before it was first entered)."""
        return self._active

    @property
    def ad_weights(self):
        """AD mode: a new ``mi.Float`` (K) of the active set's weights following ``x`` through
        :class:`.ad.LatentWeights`, for use outside a render (``render_forward`` from ``x`` refuses its
        edge while it is alive); None otherwise.
        """
        if self._w is None:
            return None
        v, J = self._ad_state
        return ad.latent_weights(self._x_param, lambda _x: (v, J))

    def forward_weights(self, dx):
        """The active set's weights as a new AD leaf carrying ``J dx`` (:class:`.ad.LatentWeights`), rendered
        until the next ``params.update()``; returns it, for ``integrator.render_forward(scene, {"w": leaf})``.
        Forward mode from ``x`` itself needs none of this: ``dr.set_grad(params["<id>.x"], dx)``, then
        ``render_forward`` (or ``mi.render`` and ``dr.forward_to``), see :func:`.ad.traced_weights`.
        """
        if self._w is None:
            raise InputError(
                f"{PLUGIN_NAME}: forward_weights needs AD mode (a grad-enabled x after params.update())"
            )
        self._w = leaf = ad.forward_leaf(self._x_param, self.ad_weights, dx)
        self._gather = ad.mixture_gather(
            self._active.slots, leaf, self._active.host.shape[1], self._active.k
        )
        return leaf

    def _read_tables(self, names):
        db = self._manifold.open_database(self._options.database, names)
        return {n: np.asarray(db.reflectance(n)) for n in names}

    def _read_density(self, name):
        return material_density(self._manifold.open_database(self._options.database, [name]), name)

    def _update_ad(self):
        """AD mode at the grad-enabled ``x``: the active set, its weights ``v`` and Jacobian ``J`` (NumPy),
        the slots' tables, and (unless :attr:`hold_proxy`) the detached sampling proxy. The weights enter
        every lookup as :func:`.ad.traced_weights` (value ``v``, derivative ``J dx``), made inside the
        integrator's AD scope: forward and backward mode from ``x`` work through Mitsuba's own API.
        """
        if self._active is None:
            self._active = ad.ActiveSet(
                self._manifold,
                self._ad_terms,
                self._read_tables,
                self._read_density,
                self._options.prune,
            )
        x = np.array(self._x_param, dtype=np.float64).ravel()
        try:
            idx, v, J, w = self._active.update(x)
        except (ValueError, KeyError, OSError) as e:  # damaged or missing files
            raise InputError(prefixed(e)) from None
        state = {"idx": idx, "v": v, "w": w, "x": x, "keep": self._active.keep}
        a, distr, black = self._active, self._c.distr, self._c.black
        if self.sampling == "cdf" and (not self.hold_proxy or self._w is None or distr is None):
            distr, black = combined_distribution(a.densities, v)
        self._c = ad.combination(self._manifold, a, state, distr, black)
        self._cos_frac = 1.0 if distr is None else COSINE_FRACTION
        self._ad_state = (v, J)
        self._w = mi.Float(np.asarray(v, dtype=np.float32))  # detached: AD mode's marker and values
        traced = partial(
            ad.traced_weights,
            self._x_param,
            self._w,
            mi.Float(np.asarray(J, dtype=np.float32).ravel()),
        )
        self._gather = ad.mixture_gather(
            a.slots, traced, a.host.shape[1], a.k
        )  # edges made at each lookup

    def to_string(self):
        """What ``print(bsdf)`` shows. The material's line is the plugin's own parameter, its
        value as a scene gives it (``<string name="x" value="..."/>``, ``"x": "..."``), the
        latent coordinates to full precision: pasted into a scene it gives the same material.
        """
        c, o = self._c, self._options
        if c.material is not None:
            what = f'material = "{c.material}"'
        elif c.x is not None:
            what = 'x = "' + ", ".join(repr(float(v)) for v in c.x) + '"'
        else:
            what = "weights = given"
        if self._w is not None:
            what += f" (AD mode: {self._active.k} slots, clamping per lookup)"
        order = c.keep[np.argsort(-np.abs(c.w[c.keep]))]
        top = ", ".join(f"{self._manifold.names[i]}:{c.w[i]:.4g}" for i in order[:6])
        more = f", ... ({len(order)} in all)" if len(order) > 6 else ""
        return (
            f"ManifoldBRDF[\n"
            f"  manifold = {o.manifold_path},\n"
            f"  database = {o.database or self._manifold.database},\n"
            f"  {what},\n"
            f"  weights used = {top}{more},\n"
            f"  pruning: {c.pruning},\n"
            f"  resolution = {c.dims[0]}x{c.dims[1]}x{c.dims[2]},\n"
            f"  clamped bins = {c.n_clamped} of {c.n_values} values below 0,\n"
            f"  interpolation = {o.interpolation},\n"
            f"  sampling = {o.sampling}"
            + (" (the material reflects nothing)" if c.black else "")
            + "\n]"
        )


mi.register_bsdf(PLUGIN_NAME, lambda props: ManifoldBRDF(props))
