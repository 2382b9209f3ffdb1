"""Small helpers shared by the test modules."""


def chain(exc):
    """The messages of an exception and of those it was raised from (mi.render and plugins wrap them)."""
    out = []
    while exc is not None:
        out.append(str(exc))
        exc = exc.__cause__ or exc.__context__
    return " | ".join(out)
