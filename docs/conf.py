"""Sphinx configuration: MyST Markdown pages, autodoc with numpydoc docstrings (napoleon), the
command-line reference generated from the tools' parsers (``_ext/clidoc.py``), the file-format
reference from the formats' declared models (``_ext/formatdoc.py``).

Build (as ``.ci/run`` does): ``python3 -m sphinx -W -b html docs docs/_build/html``.
"""

import os
import sys

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path[:0] = [ROOT, os.path.join(os.path.dirname(__file__), "_ext")]

project = "mitsuba-manifold"
author = "mitsuba-manifold developers"
copyright = "mitsuba-manifold developers"
release = version = __import__("mitsuba_manifold").__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "clidoc",
    "formatdoc",
]
source_suffix = {".md": "markdown"}
exclude_patterns = ["_build", "tutorials/*.py", "tutorials/data", "README.md"]
myst_enable_extensions = ["colon_fence", "deflist"]
myst_heading_anchors = 3

napoleon_numpy_docstring = True
napoleon_google_docstring = False
napoleon_use_rtype = False
napoleon_use_ivar = True
autodoc_member_order = "bysource"
autodoc_typehints = "none"
autodoc_default_options = {"members": True, "undoc-members": False}
# The rendering modules derive from the active variant's Mitsuba classes: one variant must be
# set before autodoc imports them (scalar_rgb needs no libLLVM).
try:
    import mitsuba as mi

    import mitsuba_manifold.render  # noqa: F401  (picks a libLLVM, registers the plugins)

    mi.set_variant("scalar_rgb")
except ImportError:
    pass

html_theme = "furo"
html_title = "mitsuba-manifold"
html_static_path = ["_static"]
html_show_sourcelink = False

# Markup slips inside the package's docstrings (reported by docutils while autodoc renders them)
# do not fail the build; everything else does (-W): missing pages, images, references, modules.
suppress_warnings = ["docutils"]
