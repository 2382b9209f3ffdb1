"""mitsuba-manifold: the manifold of measured materials (MERL BRDFs) in Mitsuba 3.

Implements Soler, Subr, Nowrouzezahrai, "A Versatile Parameterization for Measured
Material Manifolds" (CGF 2018): a GPLVM places N measured BRDFs at latent points;
any latent point gives affine weights over the measured tables, which the
``manifold_brdf`` Mitsuba plugin renders and the blending tools apply to images.

Importing the package after ``mi.set_variant(...)`` registers the Mitsuba plugins
for that variant; call :func:`register` again after switching variants.
"""

import sys

from . import _llvm

# Dr.Jit loads libLLVM on first use of an LLVM variant: choose a working one first.
_llvm.select()

__version__ = "0.1.0"


def register():
    """Register ``manifold_brdf`` and the package's integrators for the active Mitsuba variant.

    Raises
    ------
    RuntimeError
        If no Mitsuba variant is set, or an LLVM variant is active without libLLVM >= 16.
    """
    import mitsuba as mi

    variant = mi.variant()
    if variant is None:
        raise RuntimeError("mitsuba_manifold.register(): call mi.set_variant(...) first")
    if variant.startswith("llvm"):
        _llvm.require()
    from . import bsdf, integrators

    bsdf.register()
    integrators.register()
    return variant


def _register_if_variant_set():
    mi = sys.modules.get("mitsuba")
    if mi is None:
        return
    try:
        variant = mi.variant()
    except Exception:  # mitsuba partially imported
        return
    if variant is not None:
        register()


_register_if_variant_set()
