"""The basis folder: its format and the code that reads, writes and owns one.

* :mod:`.manifest` — the format: ``manifest.json``, image keys, the identities of scene and
  manifold;
* :mod:`.reader` — :class:`Basis`, a folder opened for blending, its images read on first use;
* :mod:`.owned_files` — which files a basis folder owns; a blend or a match writes elsewhere;
* :mod:`.output` — the output folder of a render: refusing what is not the basis's to
  overwrite, resuming what a killed run left.

The names below are this package's face (``from mitsuba_manifold.basis.folder import Basis``).
"""

from .manifest import (
    BASE,
    FORMAT,
    FORMAT_VERSION,
    GI,
    MANIFEST,
    MODES,
    NOT_RECORDED,
    SEP,
    SETTINGS,
    CrossEntry,
    ImageEntry,
    Manifest,
    ManifestSchema,
    RenderSettings,
    image_changed,
    image_key,
    is_basis_folder,
    key_materials,
    manifold_file_identity,
    scene_files,
    scene_hash,
)
from .owned_files import check_output_outside_basis
from .reader import Basis, manifold_object

__all__ = [
    "Basis",
    "Manifest",
    "ManifestSchema",
    "ImageEntry",
    "CrossEntry",
    "RenderSettings",
    "manifold_object",
    "GI",
    "BASE",
    "NOT_RECORDED",
    "FORMAT",
    "FORMAT_VERSION",
    "MANIFEST",
    "MODES",
    "SEP",
    "SETTINGS",
    "image_changed",
    "image_key",
    "is_basis_folder",
    "key_materials",
    "manifold_file_identity",
    "scene_files",
    "scene_hash",
    "check_output_outside_basis",
]
