"""The package's Mitsuba integrators (paper Sec. 5.2).

- :mod:`.common`: targets, path classes, variant checks, samplers and primary rays;
- :mod:`.path`: ``manifold_path``, the path tracer splitting ``L = L1- + L2+``;
- :mod:`.onepass`: the base image and every material's touch image from one set of paths;
- :mod:`.aovs`: ``manifold_aovs``, first-hit normal and albedo guides for denoising blends.
"""

from .common import COMPONENTS, MAX_GROUPS, check_variant, class_names, is_manifold_bsdf, manifold_bsdfs, target_groups
from .path import ManifoldPathIntegrator, integrator_class  # noqa: F401


def register():
    """Register the package's integrators (``manifold_path``, ``manifold_aovs``) for the active variant;
    returns the ``manifold_path`` class."""
    from . import aovs, path
    aovs.register()
    return path.register()
