"""mitsuba-manifold: the manifold of measured materials (MERL BRDFs) in Mitsuba 3.

Implements Soler, Subr, Nowrouzezahrai, "A Versatile Parameterization for Measured
Material Manifolds" (CGF 2018): a GPLVM places N measured BRDFs at latent points;
any latent point gives affine weights over the measured tables, which the
``manifold_brdf`` Mitsuba plugin renders and the blending tools apply to images.

The package face is lazy (PEP 562): ``from mitsuba_manifold import Manifold, Database,
Basis, blend, register`` loads only what is asked for; importing the package loads
neither Mitsuba nor Dr.Jit. The Mitsuba plugins register themselves for every variant
as it becomes active (:mod:`mitsuba_manifold.render.plugin`), whatever the import order.
"""

import importlib

from .render import llvm as _llvm, plugin

# Dr.Jit loads libLLVM on first use of an LLVM variant: choose a working one first.
_llvm.select()

__version__ = "0.1.0"

#: Public names -> "module:attribute" (or "module" for a submodule), loaded on first use.
_FACE = {
    "Manifold": "manifold.model:Manifold",
    "Database": "data.database:Database",
    "Basis": "basis.folder:Basis",
    "blend": "basis.blend:blend",
    "blend_path": "basis.blend:blend_path",
    "make_database": "data.database:make_database",
    "MitsubaManifoldError": "errors:MitsubaManifoldError",
}

__all__ = ["register", "__version__"] + sorted(_FACE)


def __getattr__(name):
    target = _FACE.get(name)
    if target is None:
        raise AttributeError(f"module 'mitsuba_manifold' has no attribute {name!r}")
    module, _, attr = target.partition(":")
    value = importlib.import_module("." + module, __name__)
    if attr:
        value = getattr(value, attr)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_FACE))


def register():
    """Register ``manifold_brdf`` and the package's integrators for the active Mitsuba variant.

    Not needed in normal use (the plugins register themselves for every variant as it
    becomes active); returns the variant.

    Raises
    ------
    VariantError
        (a ``RuntimeError``) If no Mitsuba variant is set, or an LLVM variant is active
        without libLLVM >= 16.
    """
    plugin.install()
    return plugin.register_all()


plugin.install()
