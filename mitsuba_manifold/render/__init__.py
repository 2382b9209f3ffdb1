"""The only subsystem that imports Mitsuba and Dr.Jit, in five rooms:

- :mod:`.plugin`: the ``manifold_brdf`` BSDF (paper Eq. 4 in a renderer), its table lookups and
  sampling, the differentiable latent point, the plugins' registration;
- :mod:`.integrators`: the package's Mitsuba integrators;
- :mod:`.scene`: scenes, variants, reference renders and the example geometry;
- :mod:`.jobs`: rendering a basis (in chunks, on executors; with full GI,
  :mod:`.jobs.gi_basis`), denoising guides, refinement, interruptible renders;
- :mod:`.inverse`: inverse rendering with Mitsuba (matching by rendering, acquisition from
  photographs).

Depends on every NumPy subsystem; nothing below it imports it.

Importing it (``import mitsuba_manifold.render``, any of its modules, or
``mitsuba_manifold.register()``) does two things, and is the only part of the package that
does anything on import:

1. Unless Dr.Jit is already imported or ``DRJIT_LIBLLVM_PATH`` is set, it sets
   ``DRJIT_LIBLLVM_PATH`` to a libLLVM >= 16 (:mod:`.plugin.llvm`): Dr.Jit loads libLLVM when it is
   first imported, and Debian's default libLLVM 15 aborts some renders. So import the
   package's rendering subsystem before ``drjit`` when you can; importing ``mitsuba``
   first works wherever Dr.Jit finds a good libLLVM by itself.
2. It imports Mitsuba and registers the plugins (``manifold_brdf``, ``manifold_path``,
   ``manifold_aovs``) for the active variant and for every variant activated later
   (:mod:`.plugin.plugins`), whatever the order of ``mi.set_variant`` and this import.

Rendering functions never change the active variant unless asked: they render in the
active one (or activate :func:`.scene.variants.default_variant` when Mitsuba has none yet), and a
``variant`` parameter activates that one (:func:`.scene.variants.use_variant`).
"""

import sys as _sys

from .._util.moved import alias as _alias
from .plugin import llvm as _llvm
from .plugin import measured as _measured  # noqa: F401 (registers the reader of Mitsuba measured files)
from .plugin import plugins as _plugins

if "drjit" not in _sys.modules:
    _llvm.select()
_plugins.install()

#: Modules that moved into sub-packages: their old names import the new modules, deprecated.
_MOVED = {
    "bsdf": ".plugin.bsdf",
    "lookups": ".plugin.lookups",
    "sampling": ".plugin.sampling",
    "material": ".plugin.material",
    "ad": ".plugin.ad",
    "plugins": ".plugin.plugins",
    "overrides": ".plugin.overrides",
    "llvm": ".plugin.llvm",
    "measured": ".plugin.measured",
    "scenes": ".scene.scenes",
    "geometry": ".scene.geometry",
    "render_basis": ".jobs.render_basis",
    "chunks": ".jobs.chunks",
    "executor": ".jobs.executor",
    "gi_basis": ".jobs.gi_basis",
    "guides": ".jobs.guides",
    "refine": ".jobs.refine",
    "interrupt": ".jobs.interrupt",
    "match_render": ".inverse.match_render",
    "match_scan": ".inverse.scan",
    "acquire": ".inverse.acquire",
}
_alias(__name__, _MOVED)
