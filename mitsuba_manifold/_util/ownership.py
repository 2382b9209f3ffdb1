"""Which files a tool may replace: the ones it made, and nothing the user made.

A tool writing ``out.exr`` or ``manifold.npz`` into a folder records the file's name and
SHA-256 in ``<folder>/.mitsuba-manifold-outputs.json`` (:data:`RECORD`). Before writing
again it calls :func:`check_replaceable`: a path that does not exist is fine; one listed
with the same content is the tool's own output and may be replaced; anything else (a
user's file, or one of the tool's outputs edited since) is refused unless ``force``.
A read-only file (no write bit for its owner) is refused even with ``force``: someone
protected it on purpose.

Folders with a manifest of their own list their files there: a basis folder's
``manifest.json`` (:mod:`mitsuba_manifold.render.render_basis`), a database folder's ``database.json``
(:func:`owned_tables`, :func:`write_table_record`).
"""

import json
import os
import stat

from .atomic import write_bytes
from .cache import file_hash
from ..errors import ForeignFileError
from .locking import FolderLock

RECORD = ".mitsuba-manifold-outputs.json"


def _record_path(path):
    return os.path.join(os.path.dirname(os.path.abspath(path)), RECORD)


def _read_record(path):
    try:
        with open(_record_path(path), encoding="utf-8") as f:
            data = json.load(f)
        files = data.get("files") if isinstance(data, dict) else None
        return files if isinstance(files, dict) else {}
    except (OSError, ValueError):
        return {}


def read_only(path):
    """True when ``path`` exists and its owner has no write permission (e.g. mode 0444)."""
    try:
        return not os.stat(path).st_mode & stat.S_IWUSR
    except FileNotFoundError:
        return False


def owned(path):
    """True when ``path`` is listed in its folder's record with its current content."""
    entry = _read_record(path).get(os.path.basename(path))
    return isinstance(entry, dict) and entry.get("sha256") == file_hash(path)


def check_replaceable(path, force=False, what="output"):
    """Raise :class:`ForeignFileError` unless writing ``path`` destroys nothing of the user's.

    Parameters
    ----------
    path : str
    force : bool
        Allow replacing a file the tool did not make (never a read-only one).
    what : str
        The role of the path, for the message: a Python parameter in backquotes (``"`out`"``,
        which a command-line tool writes as its option) or plain words (``"output"``).
    """
    path = os.fspath(path)
    if not os.path.lexists(path):
        folder = os.path.dirname(os.path.abspath(path))
        probe = folder
        while not os.path.exists(probe):
            probe = os.path.dirname(probe)
        if not os.path.isdir(probe):
            raise ForeignFileError(f"{what} {path}: {probe} is a file, not a folder")
        return
    if os.path.isdir(path):
        raise ForeignFileError(f"{what} {path} is a folder, not a file")
    if os.path.islink(path) or not os.path.isfile(path):
        raise ForeignFileError(f"{what} {path} exists and is not a regular file; not replacing it")
    if read_only(path):
        raise ForeignFileError(f"{what} {path} exists and is read-only; not replacing it (make it "
                               "writable or choose another name)")
    if not force and not owned(path):
        raise ForeignFileError(f"{what} {path} exists and was not written by this tool (or was changed "
                               "since); not replacing it: choose another name, or pass `force`")


def record(paths, tool):
    """List ``paths`` (just written) with their content hashes in their folders' records."""
    by_folder = {}
    for p in paths:
        by_folder.setdefault(os.path.dirname(os.path.abspath(p)), []).append(os.fspath(p))
    for folder, items in by_folder.items():
        with FolderLock(folder, "output folder", name=RECORD + ".lock", wait=True):
            files = _read_record(items[0])
            for p in items:
                files[os.path.basename(p)] = {"sha256": file_hash(p), "tool": tool}
            files = {k: v for k, v in files.items() if os.path.isfile(os.path.join(folder, k))}
            text = json.dumps({"format": "mitsuba-manifold-outputs", "files": files}, indent=1, sort_keys=True)
            write_bytes(os.path.join(folder, RECORD), text)


DATABASE_JSON = "database.json"


def write_table_record(out_dir, settings, made):
    """Write ``<out_dir>/database.json``: ``settings`` and the names of the tables made."""
    text = json.dumps({**settings, "tables": sorted(made)}, indent=1)
    write_bytes(os.path.join(out_dir, DATABASE_JSON), text)


def owned_tables(out_dir, settings, names, force):
    """Names of the tables in ``out_dir`` that ``database.make_database`` made with ``settings``.

    Raises when the folder was made with other settings (and holds tables of them), or when
    a table to write exists without having been made here (unless ``force``; never a
    read-only one). A ``database.json`` without a table list (older versions) owns every
    table of the folder.
    """
    path = os.path.join(out_dir, DATABASE_JSON)
    made = set()
    if os.path.exists(path):
        try:
            with open(path, encoding="utf-8") as f:
                old = json.load(f)
            listed = old.get("tables", None)
        except (OSError, ValueError, AttributeError):
            raise ForeignFileError(f"{path} is not a database.json written by make_database; "
                                   "choose another folder") from None
        present = {n[:-7] for n in os.listdir(out_dir) if n.endswith(".binary")}
        made = present if listed is None else set(listed) & present
        if {k: old.get(k) for k in settings} != settings and made:
            raise ForeignFileError(f"{out_dir} holds tables made with "
                                   f"{ {k: old.get(k) for k in settings} }, not {settings}; choose another folder")
    foreign = [n + ".binary" for n in names
               if n not in made and os.path.lexists(os.path.join(out_dir, n + ".binary"))]
    if foreign and not force:
        raise ForeignFileError(f"{out_dir} holds tables make_database did not make: {', '.join(foreign[:5])}"
                               f"{' ...' if len(foreign) > 5 else ''}; not overwriting them: choose another "
                               "folder, or pass `force`")
    for f in foreign:
        if read_only(os.path.join(out_dir, f)):
            raise ForeignFileError(f"{os.path.join(out_dir, f)} is read-only; not replacing it")
    return made
