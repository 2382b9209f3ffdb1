"""Former names that keep working for one release: each use warns (``DeprecationWarning``) and
names the new spelling.
"""

import warnings

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
