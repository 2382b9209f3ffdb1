"""Which files a tool may replace: the ones it made, and nothing the user made.

A tool writing ``out.exr`` or ``manifold.npz`` into a folder records the file's name and
SHA-256 in ``<folder>/.mitsuba-manifold-outputs.json`` (:data:`RECORD`). Before writing
again it calls :func:`check_replaceable`: a path that does not exist is fine; one listed
with the same content is the tool's own output and may be replaced; anything else (a
user's file, or one of the tool's outputs edited since) is refused unless ``force``.
Refused even with ``force``: a read-only file (no write bit for its owner: someone
protected it on purpose), and anything that is not a regular file (a folder, a symbolic
link, a FIFO, a device such as ``/dev/null``: an atomic rename would replace the node
itself), and a name longer than the file system allows.

:class:`Outputs` is the one discipline every tool writes under: it checks each output
before the run (``check``) and, while active, sees every atomic write into its paths and
folders (:func:`mitsuba_manifold._util.atomic.watching`): each file is checked again, and
is recorded as the tool's own *before* it is renamed into place (write-ahead: the record
holds the new content's hash beside the one it replaces), so that a run stopped at any
moment -- an exception, Ctrl-C, SIGKILL -- leaves only files the same command replaces.
A file whose content is already what the tool would write is left as it is.

Folders with a manifest of their own list their files there: a basis folder's
``manifest.json`` (:mod:`mitsuba_manifold.render.jobs.render_basis`), a database folder's ``database.json``
(:func:`owned_tables`, :func:`write_table_record`). No tool writes a result into a folder a
manifest owns (:func:`check_outside_managed`: the basis format says which folders those are,
:mod:`mitsuba_manifold.basis.folder.owned_files`), nor over one of its own inputs
(:func:`check_not_inputs`); a run removes only files it recorded as its own and that are
unchanged since (:func:`remove_owned`, :meth:`Outputs.remove_stale`).

This module is the one rule of what every tool may overwrite, remove or must refuse.
"""

import json
import os
import stat

from ..errors import ForeignFileError
from .atomic import name_max, watching, write_bytes
from .cache import file_hash
from .locking import FolderLock

RECORD = ".mitsuba-manifold-outputs.json"


def _record_path(path):
    return os.path.join(os.path.dirname(os.path.abspath(path)), RECORD)


def _read_record(path):
    try:
        with open(_record_path(path), encoding="utf-8") as f:
            data = json.load(f)
        files = data.get("files") if isinstance(data, dict) else None
        return (
            {k: v for k, v in files.items() if isinstance(v, dict)}
            if isinstance(files, dict)
            else {}
        )
    except (OSError, ValueError, RecursionError):
        return {}


def _update_record(folder, change):
    """Apply ``change(files)`` (it edits the ``{name: entry}`` dict in place and returns the
    names it set) to ``folder``'s record under its lock; entries of vanished files are
    dropped, but for those just set (written ahead of their file).
    """
    with FolderLock(folder, "output folder", name=RECORD + ".lock", wait=True):
        files = _read_record(os.path.join(folder, RECORD))
        fresh = set(change(files) or ())
        files = {
            k: v for k, v in files.items() if k in fresh or os.path.isfile(os.path.join(folder, k))
        }
        text = json.dumps(
            {"format": "mitsuba-manifold-outputs", "files": files}, indent=1, sort_keys=True
        )
        write_bytes(os.path.join(folder, RECORD), text)


def read_only(path):
    """True when ``path`` exists and its owner has no write permission (e.g. mode 0444)."""
    try:
        return not os.stat(path).st_mode & stat.S_IWUSR
    except FileNotFoundError:
        return False


def owned(path):
    """True when ``path`` is listed in its folder's record with its current content (or, for a
    run stopped between recording and renaming, the content it was replacing).
    """
    entry = _read_record(path).get(os.path.basename(path))
    if not isinstance(entry, dict) or not os.path.isfile(path):
        return False
    return file_hash(path) in (entry.get("sha256"), entry.get("was"))


def check_not_inputs(
    outputs, inputs, folders=(), named="an input", what="output", reason=None
) -> None:
    """Raise :class:`ForeignFileError` when an output is one of ``inputs`` or lies in one of the
    input ``folders`` (paths compared after resolving links): ``"<what> <path> <reason>"``,
    by default ``would overwrite <named>; choose another path``.
    """
    files = {os.path.realpath(os.fspath(p)) for p in inputs if p}
    dirs = {os.path.realpath(os.fspath(f)) for f in folders if f}
    reason = reason or f"would overwrite {named}; choose another path"
    for path in outputs:
        real = os.path.realpath(os.fspath(path))
        if real in files or os.path.dirname(real) in dirs:
            raise ForeignFileError(f"{what} {path} {reason}")


def check_outside_managed(
    out, managed, folder=None, what="`out`", writer="a blend", kind="basis", owner="render_basis"
) -> None:
    """Raise :class:`ForeignFileError` unless ``out`` lies outside ``folder`` and outside every
    folder that ``managed(folder)`` says a manifest owns (a basis folder: its images belong to
    ``owner``, and a result computed from them never replaces one).
    """
    here = os.path.realpath(os.path.dirname(os.path.abspath(os.fspath(out))))
    inside = folder is not None and here == os.path.realpath(os.fspath(folder))
    if inside or managed(here):
        raise ForeignFileError(
            f"{what} {out} lies in the {kind} folder {here}; {writer} never writes into a "
            f"{kind} (its images belong to {owner}): choose another folder"
        )


def remove_owned(paths, keep=()) -> list:
    """Remove those of ``paths`` not in ``keep`` that exist and are this package's outputs,
    unchanged since written (:func:`owned`): what an earlier run wrote and this one did not
    write again. A user's file is never touched. Returns the paths removed.
    """
    kept = {os.path.abspath(os.fspath(p)) for p in keep}
    removed = []
    for path in paths:
        if os.path.abspath(path) not in kept and os.path.isfile(path) and owned(path):
            os.remove(path)
            removed.append(path)
    return removed


def _refusal(path, force, what):
    """``(kind, message)`` of why ``path`` may not be written, or None. ``kind`` is
    ``"foreign"`` for a file the tool did not make (allowed by ``force``), else the
    reason no option overrides.
    """
    path = os.fspath(path)
    limit, length = name_max(path), len(os.fsencode(os.path.basename(path)))
    if length > limit:
        return "name", (
            f"{what} {path}: the file name is {length} bytes, longer than the file system "
            f"allows ({limit}); choose a shorter name"
        )
    if not os.path.lexists(path):
        probe = os.path.dirname(os.path.abspath(path))
        while not os.path.exists(probe):
            probe = os.path.dirname(probe)
        if not os.path.isdir(probe):
            return "folder", f"{what} {path}: {probe} is a file, not a folder"
        return None
    if os.path.isdir(path) and not os.path.islink(path):
        return "directory", f"{what} {path} is a folder, not a file"
    if os.path.islink(path) or not os.path.isfile(path):
        kind = "a symbolic link" if os.path.islink(path) else "a device, FIFO or socket"
        return (
            "special",
            f"{what} {path} exists and is not a regular file ({kind}); not replacing it",
        )
    if read_only(path):
        return "read-only", (
            f"{what} {path} exists and is read-only; not replacing it (make it writable or "
            "choose another name)"
        )
    if not force and not owned(path):
        return "foreign", (
            f"{what} {path} exists and was not written by this tool (or was changed since); "
            "not replacing it: choose another name, or pass `force`"
        )
    return None


def check_replaceable(path, force=False, what="output", owner=True):
    """Raise :class:`ForeignFileError` unless writing ``path`` destroys nothing of the user's
    (see the module notes).

    Parameters
    ----------
    path : str
    force : bool
        Allow replacing a file the tool did not make (never a read-only one, nor one
        that is not a regular file).
    what : str
        The role of the path, for the message: a Python parameter in backquotes (``"`out`"``,
        which a command-line tool writes as its option) or plain words (``"output"``).
    owner : bool
        Also refuse a file the tool did not make (False: only what ``force`` cannot allow,
        for a first check before the inputs are read).
    """
    refusal = _refusal(path, force, what)
    if refusal is not None and (owner or refusal[0] != "foreign"):
        raise ForeignFileError(refusal[1])


def record(paths, tool, group=None):
    """List ``paths`` (just written) with their content hashes in their folders' records
    (``group``: what the run wrote them as, for :meth:`Outputs.remove_stale`).
    """
    by_folder = {}
    for p in paths:
        by_folder.setdefault(os.path.dirname(os.path.abspath(p)), []).append(os.fspath(p))
    for folder, items in by_folder.items():

        def change(files, items=items):
            for p in items:
                files[os.path.basename(p)] = _entry(file_hash(p), tool, group)

        _update_record(folder, change)


def _entry(digest, tool, group=None, was=None):
    entry = {"sha256": digest, "tool": tool}
    if group is not None:
        entry["group"] = group
    if was is not None:
        entry["was"] = was
    return entry


class Outputs:
    """The output discipline of one tool run, as a context manager (see the module notes).

    Parameters
    ----------
    tool : str
        Recorded as the files' maker (``"blend.py"``).
    force : bool
        Replace files the tool did not make (never read-only or non-regular ones).
    folders : list of path, optional
        Folders whose every file written during the run is an output (the main job's
        ``gi/``, whose image names depend on the fitted manifold); others are added by
        :meth:`check`.
    group : str, optional
        What this run writes (``"path:/abs/seq.exr"``): recorded with each file, so that a
        later run of the same group removes what it no longer writes (:meth:`remove_stale`).

    Examples
    --------
    >>> with Outputs("bench.py", force=args.force) as outputs:
    ...     outputs.check(args.json, "--json")     # before the long run
    ...     write_bytes(args.json, text)          # checked, recorded, renamed
    """

    def __init__(self, tool, force=False, folders=(), group=None):
        self.tool, self.force, self.group = tool, bool(force), group
        self.folders = {os.path.abspath(os.fspath(f)) for f in folders}
        self.written, self.kept = (
            [],
            [],
        )  # paths written (or already right), those left as they were
        self._paths, self._identical, self._was = {}, set(), {}
        self._context = None

    def check(self, path, what="output", identical=False):
        """Refuse ``path`` now (:func:`check_replaceable`) and watch its writes. With
        ``identical``, a file the tool did not make is refused only when the new content
        differs (checked when it is written): for generated files shipped with the package.
        """
        key = os.path.abspath(os.fspath(path))
        refusal = _refusal(path, self.force, what)
        if refusal is not None and not (identical and refusal[0] == "foreign"):
            raise ForeignFileError(refusal[1])
        self._paths[key] = what
        if identical:
            self._identical.add(key)
        return path

    def watches(self, path):
        """True when writes to ``path`` are this run's outputs."""
        key = os.path.abspath(os.fspath(path))
        return os.path.basename(key) != RECORD and (
            key in self._paths or os.path.dirname(key) in self.folders
        )

    def before(self, path):
        """Called by :func:`atomic.atomic_replace` before it writes ``path``."""
        if not self.watches(path):
            return
        key = os.path.abspath(os.fspath(path))
        refusal = _refusal(path, self.force, self._paths.get(key, "output"))
        if refusal is not None and not (key in self._identical and refusal[0] == "foreign"):
            raise ForeignFileError(refusal[1])

    def claim(self, path, tmp):
        """Called by :func:`atomic.atomic_replace` with the complete new content ``tmp`` of
        ``path``: records it as the tool's own before the rename; returns False (keep the
        existing file) when the content is already ``tmp``'s.
        """
        if not self.watches(path):
            return True
        key = os.path.abspath(os.fspath(path))
        new = file_hash(tmp)
        exists = os.path.isfile(path) and not os.path.islink(path)
        mine = exists and owned(path)
        if exists and file_hash(path) == new:
            if mine or self.force:
                record([path], self.tool, self.group)
            self.written.append(path)
            self.kept.append(path)
            return False
        refusal = _refusal(path, self.force, self._paths.get(key, "output"))
        if refusal is not None:
            raise ForeignFileError(refusal[1])
        was = file_hash(path) if mine else None
        if was is not None:
            self._was[key] = new
        name = os.path.basename(key)

        def change(files):
            files[name] = _entry(new, self.tool, self.group, was)
            return [name]

        _update_record(os.path.dirname(key), change)
        self.written.append(path)
        return True

    def remove_stale(self, folder, names=None):
        """Remove the files of ``folder`` (of those ``names`` only, if given) that an earlier
        run of this tool and group recorded and this run did not write (unchanged since: a
        user's edit keeps a file). Returns the paths removed.
        """
        folder = os.path.abspath(os.fspath(folder))
        mine = {os.path.abspath(p) for p in self.written}
        stale = [
            os.path.join(folder, name)
            for name, e in _read_record(os.path.join(folder, RECORD)).items()
            if self.group is not None
            and e.get("group") == self.group
            and e.get("tool") == self.tool
            and os.path.join(folder, name) not in mine
            and (names is None or name in names)
        ]
        removed = [p for p in stale if os.path.isfile(p) and not os.path.islink(p) and owned(p)]
        for p in removed:
            os.remove(p)
        if stale:

            def change(files):
                for p in stale:
                    files.pop(os.path.basename(p), None)

            _update_record(folder, change)
        return removed

    def _settle(self):
        """Drop the replaced content's hash of every file renamed into place."""
        by_folder = {}
        for key, digest in self._was.items():
            if os.path.isfile(key) and file_hash(key) == digest:
                by_folder.setdefault(os.path.dirname(key), []).append(os.path.basename(key))
        for folder, names in by_folder.items():

            def change(files, names=names):
                for n in names:
                    if n in files:
                        files[n].pop("was", None)

            _update_record(folder, change)
        self._was.clear()

    def __enter__(self):
        self._context = watching(self)
        self._context.__enter__()
        return self

    def __exit__(self, *exc):
        self._context.__exit__(*exc)
        self._settle()
        return False


DATABASE_JSON = "database.json"


def write_table_record(out_dir, settings, made, pending=()):
    """Write ``<out_dir>/database.json``: ``settings``, the names of the tables made and of those
    being written (``pending``, left out when empty: a run killed while writing them owns them).
    """
    record = {**settings, "tables": sorted(made)}
    if pending:
        record["pending"] = sorted(pending)
    text = json.dumps(record, indent=1)
    write_bytes(os.path.join(out_dir, DATABASE_JSON), text)


def pending_tables(out_dir):
    """Names listed as ``pending`` in ``<out_dir>/database.json`` (tables a killed run was writing;
    one may be on disk without the cache its worker writes after it), empty without a record.
    """
    try:
        with open(os.path.join(out_dir, DATABASE_JSON), encoding="utf-8") as f:
            return set(json.load(f).get("pending", []))
    except (OSError, ValueError, AttributeError, TypeError, RecursionError):
        return set()


def owned_tables(out_dir, settings, names, force):
    """Names of the tables in ``out_dir`` that ``database.make_database`` made with ``settings``.

    Raises when the folder was made with other settings (and holds tables of them), or when
    a table to write exists without having been made here (unless ``force``; never a
    read-only one). The tables listed as ``pending`` (being written by a run that was killed)
    are its own too. A ``database.json`` without a table list (older versions) owns every
    table of the folder.
    """
    path = os.path.join(out_dir, DATABASE_JSON)
    made = set()
    if os.path.exists(path):
        try:
            with open(path, encoding="utf-8") as f:
                old = json.load(f)
            listed = old.get("tables", None)
            listed = None if listed is None else list(listed) + list(old.get("pending", []))
        except (OSError, ValueError, AttributeError, TypeError, RecursionError):
            raise ForeignFileError(
                f"{path} is not a database.json written by make_database; choose another folder"
            ) from None
        present = {
            n[:-7] for n in os.listdir(out_dir) if n.endswith(".binary") and not n.startswith(".")
        }
        made = present if listed is None else set(listed) & present
        if {k: old.get(k) for k in settings} != settings and made:
            raise ForeignFileError(
                f"{out_dir} holds tables made with "
                f"{ {k: old.get(k) for k in settings} }, not {settings}; choose another folder"
            )
    foreign = [
        n + ".binary"
        for n in names
        if n not in made and os.path.lexists(os.path.join(out_dir, n + ".binary"))
    ]
    if foreign and not force:
        raise ForeignFileError(
            f"{out_dir} holds tables make_database did not make: {', '.join(foreign[:5])}"
            f"{' ...' if len(foreign) > 5 else ''}; not overwriting them: choose another "
            "folder, or pass `force`"
        )
    for f in foreign:
        if read_only(os.path.join(out_dir, f)):
            raise ForeignFileError(f"{os.path.join(out_dir, f)} is read-only; not replacing it")
    return made
