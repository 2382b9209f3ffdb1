"""The package's Mitsuba integrators (paper Sec. 5.2).

- :mod:`.common`: targets, path classes, variant checks;
- :mod:`.path`: ``manifold_path``, the path tracer splitting ``L = L1- + L2+``;
- :mod:`.onepass`: the base image and every material's touch image from one set of paths
  (the splats of one pass in :mod:`.splats`), and with full GI every material's ``L2+`` image and
  the cross terms (:func:`.onepass.render_onepass_gi`: the vertices recorded in :mod:`.records`,
  their splats in :mod:`.multisplats`);
- :mod:`.aovs`: ``manifold_aovs``, first-hit normal and albedo guides for denoising blends.

:mod:`.path` and :mod:`.aovs` are plugin modules (classes on the active variant's
``mi.SamplingIntegrator``), made for each variant by :mod:`mitsuba_manifold.render.plugin.plugins`;
this package imports neither, so it can be imported before a variant is set.
"""

from .common import (
    COMPONENTS,
    MAX_GROUPS,
    TracePlan,
    check_variant,
    class_names,
    is_manifold_bsdf,
    manifold_bsdfs,
    target_groups,
)

__all__ = [
    "COMPONENTS",
    "MAX_GROUPS",
    "TracePlan",
    "check_variant",
    "class_names",
    "is_manifold_bsdf",
    "manifold_bsdfs",
    "target_groups",
]
