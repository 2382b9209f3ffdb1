"""``manifold_path``: a path tracer that renders the part of an image affine in one material.

Paper Sec. 5.2: ``L = L1- + L2+``, where ``L1-`` (paths scattering off the target at most
once) is affine in the target's BRDF. Since a manifold material is an affine combination
``sum_i w_i rho_i`` of measured BRDFs with ``sum_i w_i = 1``, the ``L1-`` image of any
latent point is ``base + sum_i w_i touch_i``: ``base`` holds the paths that never
scatter off the target (the same for every material), ``touch_i`` the paths that
scatter off it exactly once, rendered with training material ``i``.

The integrator is the class below, a ``mi.SamplingIntegrator`` of the active variant
registered by the module's last line (:mod:`mitsuba_manifold.render.plugin.plugins` re-creates it
for each variant, as Mitsuba does its own Python integrators). It is not one of Mitsuba's
``ADIntegrator`` family: it differentiates nothing (its BSDF's ``x`` is not differentiable),
and Mitsuba's C++ ``SamplingIntegrator.render`` (film, AOVs, passes, cancel) is what it needs.
Its method ``render_onepass`` renders ``base`` and the touch images of many materials from
one set of paths (:mod:`.onepass`).
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import drjit as dr
import mitsuba as mi

from ...errors import InputError, UnavailableError
from .common import (
    COMPONENTS,
    DEPRECATED_COMPONENTS,
    TracePlan,
    check_variant,
    class_names,
    group_carriers,
    is_plain_twosided,
    power_heuristic,
    target_groups,
)
from .records import Records

if TYPE_CHECKING:
    from collections.abc import Callable
    from typing import Any

    from .onepass import OnePassGI, OnePassImages


class ManifoldPathIntegrator(mi.SamplingIntegrator):
    r"""Path tracer splitting radiance by the number of scatterings off a manifold material.

    Unidirectional path tracing with next-event estimation, multiple importance
    sampling (power heuristic) and Russian roulette, as Mitsuba's ``path``. Each path
    carries the set of target groups it has scattered off. A contribution (emission
    found by a BSDF sample, or a light connection) is sorted into a *class*: the set of
    target groups that the scattering vertices before it lie on, each touched once, or
    ``rest`` as soon as a group was touched twice. In the ``L1-`` components a path
    ends at its second scattering vertex on a group: the emission found there is still
    counted (it belongs to the light connection of the previous vertex under MIS), the
    light connection made there and everything after are not.

    Parameters (plugin properties)
    ------------------------------
    max_depth : int
        Longest path depth, as in ``path`` (-1: unbounded). Default -1.
    rr_depth : int
        Depth at which Russian roulette starts. Default 5.
    hide_emitters : bool
        Hide directly visible emitters. Default false.
    component : str
        What the image holds: ``"full"`` (all paths, as ``path``), ``"l1"`` (paths
        scattering off each target group at most once), ``"base"`` (never),
        ``"touch"`` (exactly once off every group; with one group: exactly once),
        ``"touch:id1+id2"`` (exactly once off the named groups, never off the others;
        several groups only), ``"l2+"`` (twice or more off some group; ``"rest"``, its former
        spelling, is read with a ``DeprecationWarning``). Default ``"l1"``.
    target : str
        Which manifold BSDFs are "the material": ``"all"`` (default, every
        ``manifold_brdf`` of the scene, as one group), ``"each"`` (one group each, for
        multilinear blends) or comma-separated BSDF ids (one group each).
    split : bool
        Also return every class as an AOV (``base.R`` ... ``touch.R`` ..., and
        ``rest.*`` when the component is ``full``), all from the same paths. Class
        names with ``:`` become ``_`` in channel names. Default false.

    Rendering a scene without a manifold BSDF raises ``ValueError``, except with
    ``component="full"`` and ``split`` false (``render`` raises it directly;
    ``mi.render`` wraps it). :meth:`render_onepass` renders the base image and the
    touch images of many materials of one target from one set of paths.
    """

    def __init__(self, props) -> None:
        check_variant()  # first: Mitsuba warns about Python integrators in scalar variants
        super().__init__(props)
        max_depth = props.get("max_depth", -1)
        if max_depth < -1:
            raise InputError(
                f"manifold_path: max_depth must be -1 (unbounded) or >= 0, got {max_depth}"
            )
        self.max_depth = max_depth if max_depth != -1 else 0xFFFFFFFF
        self.rr_depth = props.get("rr_depth", 5)
        if self.rr_depth <= 0:
            raise InputError(f"manifold_path: rr_depth must be > 0, got {self.rr_depth}")
        self.component = str(props.get("component", "l1")).strip()
        if self.component in DEPRECATED_COMPONENTS:
            new = DEPRECATED_COMPONENTS[self.component]
            warnings.warn(
                f"manifold_path: component {self.component!r} is now spelled {new!r}; the old "
                "spelling goes in the next release",
                DeprecationWarning,
                stacklevel=2,
            )
            self.component = new
        if self.component not in COMPONENTS and not self.component.startswith("touch:"):
            raise InputError(
                f"manifold_path: unknown component {self.component!r}; expected one of "
                f"{', '.join(COMPONENTS)} or 'touch:<id>+<id>'"
            )
        self.target = str(props.get("target", "all"))
        self.split = bool(props.get("split", False))
        self._names = None  # class names of the last scene rendered (for aov_names)

    # ------------------------------------------------------------ set-up

    def needs_targets(self) -> bool:
        """Whether rendering needs the scene's manifold BSDFs."""
        return self.component != "full" or self.split

    def plan(self, scene) -> TracePlan:
        """Resolve targets and component for ``scene``.

        Returns
        -------
        TracePlan
            The groups, the classes summed, kept and written as AOVs, the vertices on each
            group and the mirrored wrappers (:class:`~.common.TracePlan`).
        """
        groups = target_groups(scene, self.target) if self.needs_targets() else []
        hits = group_carriers(scene, groups)
        mirror = [c for group in hits for c in group if is_plain_twosided(c)]
        names = class_names([g[0] for g in groups])
        n_sub = 1 << len(groups)
        rest = n_sub
        comp = self.component
        if comp == "full":
            select = (1 << (n_sub + 1)) - 1
        elif comp == "l1":
            select = (1 << n_sub) - 1
        elif comp == "base":
            select = 1
        elif comp == "l2+":
            select = 1 << rest
        elif comp == "touch":
            select = 1 << (n_sub - 1)
        else:
            if len(groups) < 2:
                raise InputError(
                    f"manifold_path: component {comp!r} names groups, but the target "
                    f"{self.target!r} makes one group; use component='touch'"
                )
            wanted = [s.strip() for s in comp[len("touch:") :].split("+")]
            gnames = [g[0] for g in groups]
            bad = [w for w in wanted if w not in gnames]
            if bad or len(set(wanted)) != len(wanted) or not wanted:
                raise InputError(
                    f"manifold_path: component {comp!r} must name distinct target "
                    f"groups among {gnames}"
                )
            select = 1 << sum(1 << gnames.index(w) for w in wanted)
        aovs = []
        if self.split:
            aovs = list(range(n_sub)) + ([rest] if comp == "full" else [])
        need = select
        for c in aovs:
            need |= 1 << c
        keep = 0
        for c in range(n_sub):  # class c can still reach any superset of c, or rest
            if any(need >> d & 1 for d in range(n_sub) if d & c == c) or need >> rest & 1:
                keep |= 1 << c
        if need >> rest & 1:
            keep |= 1 << rest
        return TracePlan(
            groups=groups,
            select=select,
            keep=keep,
            aovs=aovs,
            hits=hits,
            mirror=mirror,
            names=names,
        )

    def aov_names(self) -> list:
        if not self.split:
            return []
        if self._names is None:
            raise UnavailableError(
                "manifold_path: the AOV names of split=true depend on the scene; call "
                "integrator.prepare_scene(scene) (or render once) before asking for them"
            )
        out = []
        for c in self._aov_classes:
            base = self._names[c].replace(":", "_")
            out += [base + ".R", base + ".G", base + ".B"]
        return out

    def prepare_scene(self, scene) -> TracePlan:
        """Resolve the targets of ``scene`` now (raises on a scene it cannot split)."""
        plan = self.plan(scene)
        self._names = plan.names
        self._aov_classes = plan.aovs
        return plan

    def render(
        self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True
    ) -> dr.auto.ad.TensorXf:
        # The film's channels come from aov_names(), which needs the scene: resolve first.
        self.prepare_scene(scene)
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    # ------------------------------------------------------------ tracing

    def sample(self, scene, sampler, ray, medium=None, active=True) -> tuple[Any, Any, list]:
        plan = self.prepare_scene(scene)
        L, valid, parts, _ = self.trace_paths(scene, sampler, ray, active, plan, False)
        aovs = []
        for part in parts:
            aovs += [part.x, part.y, part.z]
        return L, valid, aovs

    @dr.syntax
    def trace_paths(self, scene, sampler, ray, active, plan, record, proxy=None) -> tuple:  # noqa: C901, PLR0915  one @dr.syntax loop, as prb.sample
        """Trace paths; return the selected radiance, validity, AOV parts and records.

        ``record``: False, or the most vertices on the target recorded per path (True: 1;
        :meth:`render_onepass_gi` records more, :mod:`.records`; a path is cut at the vertex
        after them). With ``record`` (one target group, for :meth:`render_onepass`), the image holds
        the ``base`` class only, and the path's single vertex on the target is recorded
        instead of evaluated (there the BSDF ``proxy`` is sampled in place of the
        target's, with pdf ``q``): the throughput before it (``beta``), the local
        incident direction (``wi``), the light connection made there (direction
        ``wo_nee``; ``e_nee`` = emitted radiance / light pdf, visibility and the MIS
        weight against ``q`` included), and the sampled direction ``wo`` with ``g`` =
        (radiance that came back along it, MIS-weighted emission included) / ``q``.
        A material whose ``eval`` (``f cos``) is ``f`` then adds
        ``beta * (f(wi, wo_nee) e_nee + f(wi, wo) g)``: the same estimator as
        rendering it alone, except that directions come from ``q``.

        The body is one ``@dr.syntax`` loop, as Mitsuba's ``prb`` ``sample``: Dr.Jit tracks
        every loop variable of it.
        """
        groups, select, keep = plan.groups, plan.select, plan.keep
        # closures over the BSDFs: read in the loop, they would be its state (their tables as variables)
        on_target = _target_test(plan.hits or [g[1] for g in groups])
        sampled_at = _proxy_choice(plan.mirror if record else (), proxy)
        n_sub = 1 << len(groups)
        rest = mi.UInt32(n_sub)
        track = len(groups) > 0
        aov_classes = plan.aovs

        levels = int(record)  # most vertices on the target recorded (True: 1)
        bsdf_ctx = mi.BSDFContext()
        ray = mi.Ray3f(ray)
        if dr.hint(self.max_depth == 0, mode="scalar"):
            active = False  # as Mitsuba's path: depth 0 renders nothing, not even the emitters seen
        depth = mi.UInt32(0)
        beta = mi.Spectrum(1)
        eta = mi.Float(1)
        active = mi.Bool(active)
        L = mi.Spectrum(0)
        parts = [mi.Spectrum(0) for _ in aov_classes]
        # Class of the scattering vertices so far: bit g set = group g touched once;
        # the value n_sub = rest (some group touched twice).
        cls = mi.UInt32(0)
        prev_si = dr.zeros(mi.SurfaceInteraction3f)
        prev_bsdf_pdf = mi.Float(1)
        prev_bsdf_delta = mi.Bool(True)
        # Records of the vertices on the target (record mode, :mod:`.records`): ``beta`` is the
        # throughput since the last such vertex, ``rr_scale`` the proxy's throughput up to it.
        # one record per path: an orthographic camera's rays share one direction (``ray.d`` has width 1)
        rec = (
            Records(levels, max(dr.width(ray.o.x), dr.width(ray.d.x), dr.width(active)))
            if record
            else None
        )
        rs = rec.state if record else None
        rr_scale = mi.Float(1) if record else None

        if dr.hint(self.hide_emitters, mode="scalar"):
            # As Mitsuba's path tracers: camera rays pass through area emitters.
            skip = mi.Bool(active)
            while dr.hint(skip, label="manifold_path_skip_emitters"):
                si = scene.ray_intersect(
                    ray, ray_flags=mi.RayFlags.Minimal, coherent=True, active=skip
                )
                skip &= si.is_valid() & (si.shape.emitter() != None)  # noqa: E711
                ray[skip] = si.spawn_ray(ray.d)

        while dr.hint(active, label="manifold_path"):
            si = scene.ray_intersect(
                ray, ray_flags=mi.RayFlags.All, coherent=(depth == 0), active=active
            )
            bsdf = si.bsdf(ray)

            # --- Emission found by the previous BSDF sample (class of the vertices before)
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
            mis_bsdf = power_heuristic(prev_bsdf_pdf, em_pdf)
            visible = mi.Bool(active)
            if dr.hint(self.hide_emitters, mode="scalar"):
                visible &= depth > 0
            Le = beta * mis_bsdf * ds.emitter.eval(si, visible)
            L += dr.select((mi.UInt32(select) >> cls) & 1 != 0, Le, 0)
            for k in range(len(aov_classes)):
                parts[k] += dr.select(cls == aov_classes[k], Le, 0)
            if dr.hint(record, mode="scalar"):
                rs.acc += dr.select(rs.n > 0, Le, 0)

            # --- Class after scattering here
            if dr.hint(track, mode="scalar"):
                hit = on_target(bsdf)
                again = (hit & cls) != 0
                cls = dr.select((cls == rest) | again, rest, cls | hit)
            if dr.hint(record, mode="scalar"):
                # On the target, sample (and weigh the light connection) with the
                # density that covers every material; record the vertex. The back side of a
                # twosided material is recorded mirrored (z negated), as twosided evaluates it.
                bsdf, back = sampled_at(bsdf, hit != 0, si.wi.z < 0)
                rs, first = rec.arrive(rs, active & (hit != 0), beta, _mirrored(si.wi, back))
                active &= rs.n <= levels  # a path that has touched it more often ends here

            active_next = (
                active
                & si.is_valid()
                & (depth + 1 < self.max_depth)
                & ((mi.UInt32(keep) >> cls) & 1 != 0)
            )

            # --- Light connection (next-event estimation)
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
            active_em &= ds.pdf != 0
            wo = si.to_local(ds.d)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, wo, active_em)
            mis_em = dr.select(ds.delta, 1, power_heuristic(ds.pdf, bsdf_pdf))
            Lr = dr.select(active_em, beta * mis_em * bsdf_val * em_weight, 0)
            L += dr.select((mi.UInt32(select) >> cls) & 1 != 0, Lr, 0)
            for k in range(len(aov_classes)):
                parts[k] += dr.select(cls == aov_classes[k], Lr, 0)
            if dr.hint(record, mode="scalar"):
                rs.acc += dr.select((rs.n > 0) & ~first, Lr, 0)
                rec.light(
                    rs, first, _mirrored(wo, back), dr.select(active_em, mis_em * em_weight, 0)
                )

            # --- BSDF sampling
            bs, bsdf_weight = bsdf.sample(
                bsdf_ctx, si, sampler.next_1d(), sampler.next_2d(), active_next
            )
            ray = si.spawn_ray(si.to_world(bs.wo))
            eta *= bs.eta
            beta_full = beta * bsdf_weight
            if dr.hint(record, mode="scalar"):
                ok = first & active_next & (bs.pdf > 0)
                rs = rec.leave(
                    rs, first, _mirrored(bs.wo, back), dr.select(ok, dr.rcp(bs.pdf), 0.0)
                )
                rr_scale = dr.select(
                    first, rr_scale * dr.max(mi.unpolarized_spectrum(beta_full)), rr_scale
                )
                beta = dr.select(first, dr.select(ok, 1.0, 0.0), beta_full)
            else:
                beta = beta_full
            prev_si = dr.detach(si, True)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)

            # --- Russian roulette
            beta_max = dr.max(mi.unpolarized_spectrum(beta))
            active_next &= beta_max != 0
            if dr.hint(record, mode="scalar"):
                beta_max = dr.select(rs.n > 0, beta_max * rr_scale, beta_max)
            rr_prob = dr.minimum(beta_max * dr.square(eta), 0.95)
            rr_active = depth >= self.rr_depth
            beta[rr_active] *= dr.rcp(rr_prob)
            active_next &= ~rr_active | (sampler.next_1d() < rr_prob)

            depth[si.is_valid()] += 1
            active = active_next

        if dr.hint(record, mode="scalar"):
            # one kernel: the records' scatters and every output together (evaluated apart, the
            # loop ran once for the scatters, once for the radiance and once for the counts)
            dr.eval(L, depth, parts, rs)
        records = rec.finish(rs) if record else None
        return L, depth != 0, parts, records

    # ------------------------------------------------------------ one pass

    def render_onepass(
        self,
        scene,
        materials=None,
        spp=0,
        seed=0,
        sensor=0,
        chunk=None,
        max_samples=1 << 22,
        spp_per_pass=None,
        progress=None,
    ) -> OnePassImages:
        """Render the base image and every material's touch image from one set of paths.

        See :func:`mitsuba_manifold.render.integrators.onepass.render_onepass` (the algorithm,
        parameters and results); ``chunk``, ``max_samples`` and ``spp_per_pass`` are those of
        its :class:`~mitsuba_manifold.render.integrators.onepass.PassSettings`.
        """
        from . import onepass

        return onepass.render_onepass(
            self,
            scene,
            materials,
            spp=spp,
            seed=seed,
            sensor=sensor,
            settings=onepass.PassSettings(chunk, max_samples, spp_per_pass),
            progress=progress,
        )

    def render_onepass_gi(
        self, scene, materials=None, spp=0, seed=0, sensor=0, levels=5, pairs=(), **options
    ) -> OnePassGI:
        """Base, touch, ``L2+`` and cross-term images of every material from one set of paths:
        :func:`mitsuba_manifold.render.integrators.onepass.render_onepass_gi`.
        """
        from . import onepass

        return onepass.render_onepass_gi(
            self,
            scene,
            materials,
            spp=spp,
            seed=seed,
            sensor=sensor,
            levels=levels,
            pairs=pairs,
            **options,
        )

    def to_string(self) -> str:
        return (
            f"ManifoldPathIntegrator[max_depth={self.max_depth}, rr_depth="
            f"{self.rr_depth}, component={self.component!r}, target={self.target!r}, "
            f"split={self.split}]"
        )


def _target_test(hits) -> Callable[..., Any]:
    """``test(bsdf)``: per lane, the bit set of the target groups whose BSDFs (``hits``: per group,
    its manifold materials and the twosided wrappers holding them) the BSDF pointer is one of.
    """

    def test(bsdf) -> mi.UInt32:
        hit = mi.UInt32(0)
        for g, carriers in enumerate(hits):
            for b in carriers:
                hit |= dr.select(bsdf == mi.BSDFPtr(b), mi.UInt32(1 << g), 0)
        return hit

    return test


def _proxy_choice(mirror, proxy) -> Callable[..., Any]:
    """``choose(bsdf, on, below)``: the BSDF sampled at each vertex (on the target: the proxy, or
    its twosided wrapper where one of the twosided materials ``mirror`` was hit; ``proxy`` is the
    proxy or the pair ``(proxy, twosided proxy)``) and whether the vertex is a twosided material's
    back side (``below``: the incident direction is below the shading frame).
    """
    proxy, proxy_two = proxy if isinstance(proxy, tuple) else (proxy, None)

    def choose(bsdf, on, below) -> tuple:
        two = mi.Bool(False)
        for carrier in mirror:
            two |= bsdf == mi.BSDFPtr(carrier)
        use = mi.BSDFPtr(proxy) if proxy is not None else bsdf
        if proxy_two is not None:
            use = dr.select(two, mi.BSDFPtr(proxy_two), use)
        return dr.select(on, use, bsdf), two & below

    return choose


def _mirrored(v, back) -> mi.Vector3f:
    """``v`` with its z negated where ``back``: a direction on a twosided material's back side in
    the frame its front side is evaluated in.
    """
    return mi.Vector3f(v.x, v.y, dr.select(back, -v.z, v.z))


mi.register_integrator("manifold_path", lambda props: ManifoldPathIntegrator(props))
