"""Former names that keep working for one release: each use warns (``DeprecationWarning``) and
names the new spelling.
"""

import warnings

#: How every such warning ends.
GOES = "the old spelling goes in the next release"


def warn_renamed(old: str, new: str, stacklevel: int = 3) -> None:
    """Warn that ``old`` is now spelled ``new``."""
    warnings.warn(f"{old} is now spelled {new}; {GOES}", DeprecationWarning, stacklevel=stacklevel)


def image_field(cls: type) -> type:
    """Give a dataclass whose field ``image`` (the image to match) was called ``target`` its
    former name back: ``cls(..., target=...)`` and ``obj.target`` work and warn.
    """
    init = cls.__init__

    def __init__(self, *args, target=None, **kwargs):
        if target is not None:
            if "image" in kwargs or len(args) > 1:
                raise TypeError(
                    f"{cls.__name__}() got `image` and `target` (its former name): give `image` only"
                )
            warn_renamed(f"{cls.__name__}(target=...)", f"{cls.__name__}(image=...)")
            kwargs["image"] = target
        init(self, *args, **kwargs)

    def target(self):
        warn_renamed(f"{cls.__name__}.target", f"{cls.__name__}.image")
        return self.image

    __init__.__doc__ = init.__doc__
    cls.__init__ = __init__
    cls.target = property(target, doc="The former name of :attr:`image`.")
    return cls


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
