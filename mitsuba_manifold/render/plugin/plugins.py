"""The package's Mitsuba plugins, made for the active variant the way Mitsuba makes its own.

Mitsuba's Python plugins are ordinary classes derived from the active variant's base
(``class PRBIntegrator(RBIntegrator)``), registered by one ``mi.register_integrator(...)``
line at the bottom of their module; when the variant changes, Mitsuba reloads
``mitsuba.ad.integrators``, which re-imports those modules for the new variant. The
package does the same for its plugin modules (:data:`MODULES`):

- :mod:`.bsdf`: ``manifold_brdf`` (:class:`~.bsdf.ManifoldBRDF`, a ``mi.BSDF``);
- :mod:`..integrators.path`: ``manifold_path`` (a ``mi.SamplingIntegrator``);
- :mod:`..integrators.aovs`: ``manifold_aovs`` (a ``mi.SamplingIntegrator``).

:func:`install` (run by ``import mitsuba_manifold.render``) adds a Mitsuba variant callback
(``mi.detail.add_variant_callback``) and loads the modules for the active variant, if any.
The first time a variant is activated its modules are imported (or reloaded, re-creating
the classes on that variant's base classes and registering them); when a variant is
activated again, the classes made for it are put back, so that objects created before a
round trip (``llvm_ad_rgb -> scalar_rgb -> llvm_ad_rgb``) are still instances of
``bsdf.ManifoldBRDF``. Refer to a plugin class through its module
(``mitsuba_manifold.render.plugin.bsdf.ManifoldBRDF``), which follows the active variant, as for
``mi.ad.integrators.prb.PRBIntegrator``.
"""

import importlib
import sys
import threading
import warnings

#: Plugin modules (relative to the rendering subsystem) -> the plugin classes each defines.
MODULES = {
    "plugin.bsdf": ("ManifoldBRDF",),
    "integrators.aovs": ("FirstHitAOVs",),
    "integrators.path": ("ManifoldPathIntegrator",),
}

_PACKAGE = __name__.rsplit(".", 2)[0]  # mitsuba_manifold.render
_LOCK = threading.RLock()
_made = {}  # variant -> {module name: {class name: class}}
_installed = False


def _load(variant):
    """Make the plugin modules' classes those of ``variant``: import, reload or restore them."""
    with _LOCK:
        made = _made.get(variant)
        for name, classes in MODULES.items():
            full = f"{_PACKAGE}.{name}"
            module = sys.modules.get(full)
            if made is not None and name in made and module is not None:
                for cls in classes:  # registered with Mitsuba for this variant already
                    setattr(module, cls, made[name][cls])
                continue
            module = (
                importlib.reload(module) if module is not None else importlib.import_module(full)
            )
            _made.setdefault(variant, {})[name] = {cls: getattr(module, cls) for cls in classes}


def register():
    """Register the plugins for the active Mitsuba variant; returns the variant.

    Raises
    ------
    VariantError
        (a ``RuntimeError``) If no Mitsuba variant is set, or an LLVM variant is active
        without libLLVM >= 16.
    """
    import mitsuba as mi

    from ...errors import VariantError
    from . import llvm

    variant = mi.variant()
    if variant is None:
        raise VariantError("mitsuba_manifold.register(): call mi.set_variant(...) first")
    if variant.startswith("llvm"):
        llvm.require()
    _load(variant)
    return variant


def _on_variant(old, new):
    """Mitsuba variant callback: the plugins of the new variant."""
    if new is None:
        return
    from ...errors import MitsubaManifoldError

    try:
        register()
    except MitsubaManifoldError as e:
        warnings.warn(
            f"mitsuba_manifold: plugins not registered for variant {new}: {e}",
            RuntimeWarning,
            stacklevel=2,
        )


def install():
    """Register the plugins for the active variant and for every variant activated later
    (once per process); returns the active variant (None when none is set).
    """
    global _installed
    import mitsuba as mi

    with _LOCK:
        if not _installed:
            mi.detail.add_variant_callback(_on_variant)
            _installed = True
    variant = mi.variant()
    if variant is not None and variant not in _made:
        _on_variant(None, variant)
    return variant
