"""The output folder of a basis render (one process, or chunks merged): refusing what is not
the basis's to overwrite, and resuming what a killed run left.

A folder that holds files and no basis manifest is the user's (a database, blends):
:func:`check_foreign_folder` refuses it. :func:`open_folder` checks a basis folder against
the manifest of the run about to write into it: a basis of other settings is refused, files
the run would write that no manifest lists are the user's, and the files a killed run listed
as ``pending`` are removed so they are rendered again (format: :mod:`mitsuba_manifold.basis.folder`).
Used by :mod:`.render_basis` and by the merge of :mod:`.chunks`.
"""

from __future__ import annotations

import os
import re

from ..._util import ownership
from ..._util.locking import LOCK_NAME
from ...errors import FormatError, InputError
from ...imaging import io as imageio
from . import manifest as basis_folder

#: Folder of a chunked render's chunks inside its output folder (:mod:`.chunks`).
CHUNK_DIR = ".chunks"

#: What a basis run leaves in its folder before its manifest: the lock, chunk folders,
#: temporary files of atomic writes killed with the process (:mod:`atomic`).
_OWN = re.compile(
    r"^(?:" + re.escape(LOCK_NAME) + "|" + re.escape(CHUNK_DIR) + r"|\..+\.tmp\.(?:exr|json|npz))$"
)


def check_foreign_folder(out, force=False, bases=None) -> None:
    """Refuse (unless ``force``) an existing ``out`` that holds files and no basis manifest:
    a folder of the user's (a database, blends), which a basis would fill with images that
    no blend may then be written beside. With ``bases`` (the names of the basis folders
    to render in it), ``out`` is the parent of several bases and may hold only bases.
    """
    if (
        not os.path.isdir(out)
        or force
        or (bases is None and os.path.lexists(os.path.join(out, basis_folder.MANIFEST)))
    ):
        return
    foreign = sorted(
        f
        for f in os.listdir(out)
        if not _OWN.match(f)
        and (
            bases is None
            or f not in bases
            and not basis_folder.is_basis_folder(os.path.join(out, f))
        )
    )
    if foreign:
        what = (
            f"not a basis folder (no {basis_folder.MANIFEST})"
            if bases is None
            else "not a folder of bases"
        )
        raise InputError(
            f"{out} is {what} and holds files render_basis did not make ({', '.join(foreign[:3])}"
            f"{' ...' if len(foreign) > 3 else ''}); choose a new or empty folder, or add `force`"
        )


def check_job_folders(jobs, out, force=False) -> None:
    """Before the first render: every folder of :func:`plan_views`'s ``jobs`` and, for
    several, their parent ``out`` (:func:`check_foreign_folder`).
    """
    if len(jobs) > 1:
        check_foreign_folder(
            os.fspath(out), force, bases={os.path.basename(folder) for _, _, folder in jobs}
        )
    for _, _, folder in jobs:
        check_foreign_folder(folder, force)


def open_folder(out, manifest, files, force=False, read_images=True) -> dict:
    """Check ``out`` (locked by the caller) against ``manifest`` (the run's :class:`Manifest`);
    return the images still valid (all those listed without ``read_images``).

    A folder whose manifest has other settings is refused, unless it lists no image yet
    (nothing to lose). A listed image that is damaged or changed since it was written (its
    SHA-256 in the manifest) is rendered again, or refused when it is read-only. Files the run
    would write (``files``) that exist without being listed in the manifest are the user's:
    refused unless ``force``. Files the manifest
    lists as ``pending`` were being written by a run that was killed: they are this tool's,
    and are removed when ``read_images`` (the locked call) so they are rendered again.
    """
    check_foreign_folder(out, force)
    _refuse_special(out, files)
    old = None
    listed = set()
    if os.path.exists(os.path.join(out, basis_folder.MANIFEST)):
        old = basis_folder.Manifest.read(out)  # raises unless it is a basis manifest
        old = old.upgraded(manifest.manifold)  # resume a version-1 basis
        listed.add(basis_folder.MANIFEST)
        listed |= _clear_pending(out, old, remove=read_images)
        diff = old.differences(manifest)
        if diff and old.images:
            raise InputError(
                f"{out} holds a basis made with other settings ({', '.join(diff)} differ); "
                "choose another folder or delete it"
            )
        if diff:
            old = None
    listed |= old.listed_files() if old else set()  # a full-GI basis's too
    foreign = sorted(f for f in files if f not in listed and os.path.lexists(os.path.join(out, f)))
    if foreign and not force:
        raise InputError(
            f"{out} holds files this basis did not make and would overwrite: {', '.join(foreign[:5])}"
            f"{' ...' if len(foreign) > 5 else ''}; choose another folder, or add `force`"
        )
    for f in foreign:
        if ownership.read_only(os.path.join(out, f)):
            raise InputError(f"{os.path.join(out, f)} is read-only; not replacing it")
    if old is None:
        return {}
    if not read_images:
        return dict(old.images)
    size = tuple(manifest.resolution)
    return {key: entry for key, entry in old.images.items() if image_still_valid(out, entry, size)}


def _refuse_special(out, files) -> None:
    """Refuse, whatever ``force`` says, a file the run would write that exists and is not a
    regular file (a symbolic link, a folder, a FIFO or device): an atomic rename would replace
    the node itself, and a link's target is the user's (the rule of :mod:`~mitsuba_manifold._util.ownership`).
    """
    for f in files:
        path = os.path.join(out, f)
        if os.path.islink(path) or (os.path.lexists(path) and not os.path.isfile(path)):
            kind = (
                "a symbolic link"
                if os.path.islink(path)
                else "a folder"
                if os.path.isdir(path)
                else "a device, FIFO or socket"
            )
            raise InputError(
                f"{path} exists and is not a regular file ({kind}); not replacing it, even with "
                "`force`: remove it, or choose another folder"
            )


def image_still_valid(out, entry, size) -> bool:
    """True when the image of manifest ``entry`` in ``out`` is the one written (its SHA-256, when
    recorded), readable and of ``size``; one that is not and is read-only is refused (InputError).
    """
    path = os.path.join(out, entry.file)
    try:
        imageio.check_exr_header(path, size)
        imageio.read_exr(path)  # a killed writer never leaves a partial file, but check anyway
        valid = not basis_folder.image_changed(out, entry)
    except (FormatError, OSError):
        valid = False
    if not valid and os.path.lexists(path) and ownership.read_only(path):
        raise InputError(
            f"{path} is not the image render_basis wrote (changed or damaged since) and is "
            "read-only; not replacing it: make it writable to render it again, or choose "
            "another folder"
        )
    return valid


def _clear_pending(out, old, remove) -> set:
    """The files ``old`` lists as pending and not as images (a killed run's); removed when
    ``remove`` (a read-only one is left, and then refused as the user's).
    """
    done = {e.file for e in old.images.values()}
    pending = {f for f in old.pending or [] if f not in done}
    for f in pending if remove else ():
        path = os.path.join(out, f)
        if os.path.lexists(path) and not ownership.read_only(path):
            os.remove(path)
    return {f for f in pending if not ownership.read_only(os.path.join(out, f))}
