"""One mechanism for the package's Mitsuba plugins: per-variant classes and registration.

Mitsuba's plugin base classes (``mi.BSDF``, ``mi.SamplingIntegrator``) are different
classes in every variant, and nanobind allows a single native base. So each plugin is
written once, at module level, as a plain *body* class (``bsdf.ManifoldBRDF``,
``integrators.path.ManifoldPathIntegrator``), and :func:`plugin_class` makes its class
for a variant: the body's namespace over that variant's base class, built once per
(body, variant). Body methods reach the base class through ``self._base`` (zero-argument
``super()`` would name the body class).

Registration does not depend on import order or variant switches: :func:`install`
(run by ``import mitsuba_manifold``) adds a Mitsuba variant callback
(``mi.detail.add_variant_callback``) that registers every plugin for each variant as it
becomes active, and registers them for the active one. Until Mitsuba itself is imported,
nothing of it is loaded: a small import hook runs :func:`install` right after
``import mitsuba``.
"""

import importlib.abc
import importlib.util
import sys
import threading
import warnings

_CLASSES = {}
_LOCK = threading.RLock()
_installed = False


def plugin_class(body, base):
    """The class of plugin ``body`` on ``base`` (a variant's ``mi.BSDF``, ...), made once."""
    with _LOCK:
        cls = _CLASSES.get((body, base))
        if cls is None:
            ns = {k: v for k, v in vars(body).items() if k not in ("__dict__", "__weakref__")}
            ns["_base"] = base
            cls = type(body.__name__, (base,), ns)
            _CLASSES[(body, base)] = cls
        return cls


def register_plugin(kind, name, body, check=None):
    """Register ``body`` as Mitsuba plugin ``name`` of ``kind`` (``"bsdf"`` or ``"integrator"``)
    for the active variant; returns its class.

    ``check(variant)`` may raise :class:`~mitsuba_manifold.errors.VariantError` for variants
    the plugin cannot run in: the name is registered all the same, and creating the plugin
    raises that error (which says which variants work).
    """
    import mitsuba as mi

    from ..errors import VariantError

    register = {"bsdf": mi.register_bsdf, "integrator": mi.register_integrator}[kind]
    base = {"bsdf": lambda: mi.BSDF, "integrator": lambda: mi.SamplingIntegrator}[kind]()
    variant = mi.variant()
    if check is not None:
        try:
            check(variant)
        except VariantError as e:
            message = str(e)

            def refuse(props):
                raise VariantError(message)

            register(name, refuse)
            return None
    cls = plugin_class(body, base)
    register(name, lambda props: cls(props))
    return cls


def register_all():
    """Register every plugin of the package for the active Mitsuba variant; returns the variant."""
    import mitsuba as mi

    from . import llvm as _llvm
    from ..errors import VariantError

    variant = mi.variant()
    if variant is None:
        raise VariantError("mitsuba_manifold.register(): call mi.set_variant(...) first")
    if variant.startswith("llvm"):
        _llvm.require()
    from . import bsdf, integrators

    bsdf.register()
    integrators.register()
    return variant


def _on_variant(old, new):
    if new is None:
        return
    from ..errors import MitsubaManifoldError
    try:
        register_all()
    except MitsubaManifoldError as e:
        warnings.warn(f"mitsuba_manifold: plugins not registered for variant {new}: {e}", RuntimeWarning)


def _mitsuba_ready():
    mi = sys.modules.get("mitsuba")
    if mi is None:
        return None
    try:
        mi.detail.add_variant_callback
        mi.variant
    except AttributeError:  # mitsuba partially imported
        return None
    return mi


def install():
    """Register the plugins for the active variant and for every variant activated later."""
    global _installed
    mi = _mitsuba_ready()
    if mi is None:
        _AfterMitsubaImport.add()
        return
    with _LOCK:
        if _installed:
            return
        _installed = True
        mi.detail.add_variant_callback(_on_variant)
    variant = mi.variant()
    if variant is not None:
        _on_variant(None, variant)


class _AfterMitsubaImport(importlib.abc.MetaPathFinder):
    """Import hook: runs :func:`install` once ``import mitsuba`` has finished executing."""

    @classmethod
    def add(cls):
        if not any(isinstance(f, cls) for f in sys.meta_path):
            sys.meta_path.insert(0, cls())

    def find_spec(self, name, path=None, target=None):
        if name != "mitsuba":
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            install()

        spec.loader.exec_module = exec_module
        return spec
