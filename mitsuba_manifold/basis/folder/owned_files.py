"""Which files a basis folder owns: the images and the manifest that ``render_basis`` wrote.

A folder with a basis manifest (:func:`~mitsuba_manifold.basis.folder.manifest.is_basis_folder`)
belongs to the renderer that lists its images there (:mod:`mitsuba_manifold.render.jobs.render_basis`
resumes and completes it under a :class:`~mitsuba_manifold._util.locking.FolderLock`); a blend
or a match writes its results elsewhere (:func:`check_output_outside_basis`), so that no
image of a basis is ever replaced by a result computed from it.
"""

import os

from ..._util import ownership
from ..._util.atomic import is_temporary
from ..._util.locking import LOCK_NAME
from ...errors import ForeignFileError
from .manifest import MANIFEST, Manifest, is_basis_folder

#: What a basis run leaves beside its images besides the manifest (AOVs, chunk folders).
EXTRA = ("aovs.npz", ".chunks")


def check_output_outside_basis(out, basis_folder=None):
    """Raise unless ``out`` lies outside every basis folder (``basis_folder`` included):
    a blend never writes into a basis, whose files the basis's manifest owns (the rule of
    :func:`mitsuba_manifold._util.ownership.check_outside_managed`).
    """
    ownership.check_outside_managed(out, is_basis_folder, basis_folder)


def basis_entries(folder):
    """``(own, foreign)``: the names in a basis folder that its render made (the manifest, the
    files it lists (:meth:`Manifest.listed_files`: images, full-GI images, cross terms) or has
    pending, :data:`EXTRA`, its lock and temporary files) and the others.
    """
    folder = os.fspath(folder)
    manifest = Manifest.read(folder)
    own = {MANIFEST, LOCK_NAME, *EXTRA, *(manifest.pending or [])} | manifest.listed_files()
    names = sorted(os.listdir(folder))
    return (
        [n for n in names if n in own or is_temporary(n)],
        [n for n in names if n not in own and not is_temporary(n)],
    )


def remove_basis(folder):
    """Remove a basis folder that render_basis made (to render it again from scratch): refused,
    with nothing removed, when it is not a basis folder or holds files its render did not make.
    """
    import shutil

    folder = os.fspath(folder)
    if not os.path.isdir(folder) or os.path.islink(folder):
        if os.path.lexists(folder):
            raise ForeignFileError(f"{folder} is not a folder; not replacing it with a basis")
        return
    if not is_basis_folder(folder):
        if os.listdir(folder):
            raise ForeignFileError(
                f"{folder} holds files and no basis {MANIFEST}; not removing it: "
                "choose another output folder, or move them"
            )
        return
    own, foreign = basis_entries(folder)
    foreign += [
        n
        for n in own
        if os.path.isfile(os.path.join(folder, n))
        and not os.stat(os.path.join(folder, n)).st_mode & 0o200
    ]  # read-only: kept on purpose
    if foreign:
        raise ForeignFileError(
            f"the basis folder {folder} holds files its render did not make "
            f"or read-only ones ({', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}); "
            "not removing it"
        )
    shutil.rmtree(folder)
