"""Modules that moved: their old dotted names keep importing, as the new modules, with a
:class:`DeprecationWarning` that names the new place.

A subsystem registers the modules that left it (:func:`alias`); ``import old.name``,
``from old.name import x`` and ``from old import name`` then give the module object of the new
name itself (one module under two names, not a copy), so the old spellings in users' scripts work.
"""

import importlib
import importlib.abc
import importlib.util
import sys
import threading
import warnings

_MOVED: dict = {}  # old dotted name -> new dotted name
_LOCK = threading.Lock()


class _Loader(importlib.abc.Loader):
    def create_module(self, spec) -> None:
        return None  # the default module, replaced by the new one in exec_module

    def exec_module(self, module) -> None:
        old = module.__name__
        new = _MOVED[old]
        warnings.warn(
            f"module {old} moved to {new}: import it from there (the old name will be removed)",
            DeprecationWarning,
            stacklevel=2,
        )
        sys.modules[old] = importlib.import_module(new)  # the import system returns this one


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None) -> "importlib.machinery.ModuleSpec":
        if fullname not in _MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, _Loader())


_FINDER = _Finder()


def alias(package, moves) -> None:
    """Make each old module ``package.old`` of ``moves`` (``{old: new}``, ``new`` relative to
    ``package`` as in a relative import, e.g. ``".plugin.bsdf"``) import the module ``new``.
    """
    with _LOCK:
        _MOVED.update(
            {
                f"{package}.{old}": importlib.util.resolve_name(new, package)
                for old, new in moves.items()
            }
        )
        if _FINDER not in sys.meta_path:  # first: an old name may now be a data folder
            sys.meta_path.insert(0, _FINDER)
