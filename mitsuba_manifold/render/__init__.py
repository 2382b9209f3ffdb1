"""The only subsystem that imports Mitsuba and Dr.Jit: the ``manifold_brdf`` BSDF (paper Eq. 4
in a renderer), table lookups and sampling, the integrators, scenes, rendering a basis (in
chunks, on executors; with full GI, :mod:`.gi_basis`) and the example geometry.

Depends on every NumPy subsystem; nothing below it imports it.

Importing it (``import mitsuba_manifold.render``, any of its modules, or
``mitsuba_manifold.register()``) does two things, and is the only part of the package that
does anything on import:

1. Unless Dr.Jit is already imported or ``DRJIT_LIBLLVM_PATH`` is set, it sets
   ``DRJIT_LIBLLVM_PATH`` to a libLLVM >= 16 (:mod:`.llvm`): Dr.Jit loads libLLVM when it is
   first imported, and Debian's default libLLVM 15 aborts some renders. So import the
   package's rendering subsystem before ``drjit`` when you can; importing ``mitsuba``
   first works wherever Dr.Jit finds a good libLLVM by itself.
2. It imports Mitsuba and registers the plugins (``manifold_brdf``, ``manifold_path``,
   ``manifold_aovs``) for the active variant and for every variant activated later
   (:mod:`.plugins`), whatever the order of ``mi.set_variant`` and this import.

Rendering functions never change the active variant unless asked: they render in the
active one (or activate :func:`.scenes.default_variant` when Mitsuba has none yet), and a
``variant`` parameter activates that one (:func:`.scenes.use_variant`).
"""

import sys as _sys

from . import llvm as _llvm
from . import measured as _measured  # noqa: F401 (registers the reader of Mitsuba measured files)
from . import plugins as _plugins

if "drjit" not in _sys.modules:
    _llvm.select()
_plugins.install()
