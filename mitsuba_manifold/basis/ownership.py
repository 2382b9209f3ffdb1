"""Which files a basis folder owns: the images and the manifest that ``render_basis`` wrote.

A folder with a basis manifest (:func:`~mitsuba_manifold.basis.manifest.is_basis_folder`)
belongs to the renderer that lists its images there (:mod:`mitsuba_manifold.render.render_basis`
resumes and completes it under a :class:`~mitsuba_manifold._util.locking.FolderLock`); a blend
or a match writes its results elsewhere (:func:`check_output_outside_basis`), so that no
image of a basis is ever replaced by a result computed from it.
"""

import os

from ..errors import ForeignFileError
from .manifest import is_basis_folder


def check_output_outside_basis(out, basis_folder=None):
    """Raise unless ``out`` lies outside every basis folder (``basis_folder`` included):
    a blend never writes into a basis, whose files the basis's manifest owns."""
    folder = os.path.realpath(os.path.dirname(os.path.abspath(os.fspath(out))))
    inside = basis_folder is not None and folder == os.path.realpath(os.fspath(basis_folder))
    if inside or is_basis_folder(folder):
        raise ForeignFileError(f"`out` {out} lies in the basis folder {folder}; a blend never writes into a "
                               "basis (its images belong to render_basis): choose another folder")
