"""``manifold_aovs``: first-hit guides for denoising blends (:mod:`mitsuba_manifold.basis.denoise`).

A plugin module as Mitsuba's own (a ``mi.SamplingIntegrator`` of the active variant, registered
by the last line; :mod:`mitsuba_manifold.render.plugin.plugins` re-creates it for each variant).
"""

import drjit as dr
import mitsuba as mi

from .common import check_variant

#: Bins of the viewing angle ``theta_i`` on the target (uniform over [0, pi/2]).
THETA_BINS = 45


class FirstHitAOVs(mi.SamplingIntegrator):
    r"""First-hit AOVs whose blend is the AOV of the blended material.

    For each camera sample, at its first hit: the shading normal (world space); for
    surfaces other than the target BSDFs, their directional albedo (one BSDF sample's
    weight ``f cos / pdf``, whose mean is the albedo); on the target, a one-hot histogram
    of the angle ``theta_i`` between the viewing direction and the normal over ``bins``
    bins (its per-pixel mean times a material's directional albedo per bin is that
    material's albedo image). Misses are 0. Returns no radiance.

    Parameters (plugin properties): ``bins`` (default 45). The target BSDFs are set as
    the attribute ``targets`` (a list of BSDFs) before rendering.
    """

    def __init__(self, props):
        check_variant()  # first: Mitsuba warns about Python integrators in scalar variants
        super().__init__(props)
        self.bins = int(props.get("bins", THETA_BINS))
        self.targets = []

    def aov_names(self):
        return (
            [f"normal.{c}" for c in "XYZ"]
            + [f"albedo.{c}" for c in "RGB"]
            + [f"theta{k}" for k in range(self.bins)]
        )

    def sample(self, scene, sampler, ray, medium=None, active=True):
        si = scene.ray_intersect(ray, active=active)
        valid = si.is_valid()
        bsdf = si.bsdf(ray)
        on = mi.Bool(False)
        for b in self.targets:
            on |= bsdf == mi.BSDFPtr(b)
        n = dr.select(valid, si.sh_frame.n, 0.0)
        other = valid & ~on
        _, weight = bsdf.sample(mi.BSDFContext(), si, sampler.next_1d(), sampler.next_2d(), other)
        albedo = dr.select(other, dr.clip(weight, 0.0, 1.0), 0.0)
        theta = dr.acos(
            dr.clip(dr.abs(si.wi.z), 0.0, 1.0)
        )  # a twosided material's back side as its front
        k = mi.UInt32(dr.minimum(theta * (2.0 / dr.pi) * self.bins, self.bins - 1))
        hist = [dr.select(valid & on & (k == j), 1.0, 0.0) for j in range(self.bins)]
        return mi.Spectrum(0.0), valid, [n.x, n.y, n.z, albedo.x, albedo.y, albedo.z] + hist

    def to_string(self):
        return f"FirstHitAOVs[bins={self.bins}, targets={len(self.targets)}]"


mi.register_integrator("manifold_aovs", lambda props: FirstHitAOVs(props))
