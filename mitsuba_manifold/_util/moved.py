"""Modules that moved and parameters that were renamed: their old names keep working, with a
:class:`DeprecationWarning` that names the new place or spelling.

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


# ------------------------------------------------ renamed parameters and fields
#: How every such warning ends.
GOES = "the old spelling goes in the next release"


def warn_renamed(old: str, new: str, stacklevel: int = 3) -> None:
    """Warn that ``old`` is now spelled ``new``."""
    warnings.warn(f"{old} is now spelled {new}; {GOES}", DeprecationWarning, stacklevel=stacklevel)


def renamed_field(old: str, new: str):
    """A class decorator giving a dataclass whose field ``new`` was called ``old`` its former
    name back: ``cls(..., old=...)`` and ``obj.old`` work and warn.
    """

    def decorate(cls: type) -> type:
        init = cls.__init__
        position = [f for f in cls.__dataclass_fields__].index(new)

        def __init__(self, *args, **kwargs):
            if old in kwargs:
                if new in kwargs or len(args) > position:
                    raise TypeError(
                        f"{cls.__name__}() got `{new}` and `{old}` (its former name): give `{new}` only"
                    )
                warn_renamed(f"{cls.__name__}({old}=...)", f"{cls.__name__}({new}=...)")
                kwargs[new] = kwargs.pop(old)
            init(self, *args, **kwargs)

        def former(self):
            warn_renamed(f"{cls.__name__}.{old}", f"{cls.__name__}.{new}")
            return getattr(self, new)

        __init__.__doc__ = init.__doc__
        cls.__init__ = __init__
        setattr(cls, old, property(former, doc=f"The former name of :attr:`{new}`."))
        return cls

    return decorate


#: For a dataclass whose ``image`` (the image to match) was called ``target``.
image_field = renamed_field("target", "image")


def renamed_argument(value, given: dict, old: str, new: str, where: str):
    """``value`` (the argument ``new`` of ``where``), or the one passed by its former name
    ``old``: popped from ``given`` (the call's other keywords) with a ``DeprecationWarning``.
    A ``value`` of None is missing.
    """
    if old not in given:
        if value is None:
            raise TypeError(f"{where}() missing its argument `{new}`")
        return value
    former = given.pop(old)
    if value is not None:
        raise TypeError(f"{where}() got `{new}` and `{old}` (its former name): give `{new}` only")
    warn_renamed(f"{where}({old}=...)", f"{where}({new}=...)", stacklevel=4)
    return former
