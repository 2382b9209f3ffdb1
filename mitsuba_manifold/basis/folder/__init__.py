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
    MANIFEST,
    MODES,
    SEP,
    SETTINGS,
    Manifest,
    RenderSettings,
    image_changed,
    image_key,
    is_basis_folder,
    key_materials,
    make_manifest,
    manifest_differences,
    manifold_file_identity,
    read_manifest,
    scene_files,
    scene_hash,
    upgrade_manifest,
    validate_manifest,
    write_manifest,
)
from .owned_files import check_output_outside_basis
from .reader import GI, Basis, manifold_object

__all__ = [
    "Basis",
    "Manifest",
    "RenderSettings",
    "manifold_object",
    "GI",
    "BASE",
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
    "make_manifest",
    "manifest_differences",
    "manifold_file_identity",
    "read_manifest",
    "scene_files",
    "scene_hash",
    "upgrade_manifest",
    "validate_manifest",
    "write_manifest",
    "check_output_outside_basis",
]
