"""mitsuba-manifold: the manifold of measured materials (MERL BRDFs) in Mitsuba 3.

Implements Soler, Subr, Nowrouzezahrai, "A Versatile Parameterization for Measured
Material Manifolds" (CGF 2018): a GPLVM places N measured BRDFs at latent points;
any latent point gives affine weights over the measured tables, which the
``manifold_brdf`` Mitsuba plugin renders and the blending tools apply to images.

The package face is lazy (PEP 562): ``from mitsuba_manifold import Manifold, Database,
Basis, blend, register`` loads only what is asked for.

No side effects on import: ``import mitsuba_manifold`` (and every subsystem but ``render``)
loads neither Mitsuba nor Dr.Jit and changes nothing, ``os.environ`` included. The one
subsystem that does something on import is the rendering one: importing
:mod:`mitsuba_manifold.render` (any of its modules, e.g. ``mitsuba_manifold.render.scene.scenes``),
or calling :func:`register`,

- sets ``DRJIT_LIBLLVM_PATH`` to a libLLVM >= 16 when Dr.Jit is not imported yet and the
  variable is unset (Dr.Jit reads it on first import; Debian's libLLVM 15 aborts renders);
- registers the Mitsuba plugins (``manifold_brdf``, ``manifold_path``, ``manifold_aovs``) for
  the active variant and for every variant activated later.

So a Mitsuba user writes ``import mitsuba as mi; mi.set_variant("llvm_ad_rgb");
import mitsuba_manifold.render`` (or the two imports the other way round) and then
``mi.load_file(...)`` scenes with ``manifold_brdf`` materials.

Modules that moved into sub-packages keep their old dotted names, deprecated: importing a
subsystem that lost modules adds one finder to ``sys.meta_path`` that answers only for those
old names (:mod:`mitsuba_manifold._util.moved`).
"""

from __future__ import annotations

import importlib
from typing import Any

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


def __getattr__(name: str) -> Any:
    target = _FACE.get(name)
    if target is None:
        raise AttributeError(f"module 'mitsuba_manifold' has no attribute {name!r}")
    module, _, attr = target.partition(":")
    value = importlib.import_module("." + module, __name__)
    if attr:
        value = getattr(value, attr)
    globals()[name] = value
    return value


def __dir__() -> list:
    return sorted(set(globals()) | set(_FACE))


def register() -> str:
    """Register ``manifold_brdf`` and the package's integrators for the active Mitsuba variant
    and every variant activated later; returns the active variant.

    The same as ``import mitsuba_manifold.render`` (see the package docstring), except that
    it raises when no variant is active.

    Raises
    ------
    VariantError
        (a ``RuntimeError``) If no Mitsuba variant is set, or an LLVM variant is active
        without libLLVM >= 16.
    """
    plugins = importlib.import_module(
        ".render.plugin.plugins", __name__
    )  # by name: the face imports no module
    plugins.install()
    return plugins.register()
