"""Every exception the package raises on bad input, under one root; one-line messages.

There are a dozen classes, named after what went wrong rather than after the module
that noticed it. Tools catch :class:`MitsubaManifoldError` (plus ``OSError`` where files
are involved) and print its one-line message. Each class also derives from the built-in exception a
caller would expect (``ValueError`` for bad values, ``KeyError`` for unknown names,
``RuntimeError`` for a missing or unsuitable Mitsuba variant), so ``except ValueError``
keeps working. Messages name the parameter or file, the value and the fix.

A message names a Python parameter in backquotes (```spp` must be >= 1, got 0``): the
command-line tools write the option that sets it instead (``--spp must be >= 1, got 0``,
:func:`mitsuba_manifold.apps.cli.common.cli_message`), so the library never speaks in
option names.
"""

from __future__ import annotations

import re

import numpy as np


class MitsubaManifoldError(Exception):
    """Root of all mitsuba-manifold exceptions."""


class InputError(MitsubaManifoldError, ValueError):
    """A bad argument, parameter or request value (the message names the parameter, the value
    and what would be accepted).
    """


class FormatError(InputError):
    """A file or folder whose content is not what it must be: a MERL table, a database folder,
    a manifold file, an image.
    """


class MismatchError(InputError):
    """Something made for something else, or incomplete: a basis of another manifold, scene or
    sensor, chunks of other settings, denoising guides of another basis.
    """


class ForeignFileError(InputError):
    """Writing would replace a file the tool did not make, or a protected one."""


class UnknownMaterialError(MitsubaManifoldError, KeyError):
    """A material name that the database or manifold does not hold."""

    def __str__(self) -> str:  # KeyError would quote the message
        return Exception.__str__(self)


class NumericalError(MitsubaManifoldError, FloatingPointError):
    """A computation produced NaN or Inf values."""


class NotPositiveDefiniteError(MitsubaManifoldError, np.linalg.LinAlgError):
    """A kernel matrix that is not positive definite (``LinAlgError``, a ``ValueError``)."""


class VariantError(MitsubaManifoldError, RuntimeError):
    """No Mitsuba variant set, an unsupported one, or no usable libLLVM."""


class UnavailableError(MitsubaManifoldError, RuntimeError):
    """Something a call needs is not there: Ray, a cluster, a denoiser, or state that an
    earlier call makes.
    """


class MissingFileError(MitsubaManifoldError, FileNotFoundError):
    """A file or folder that should exist does not."""


class FolderLockedError(MitsubaManifoldError, OSError):
    """Another process is writing into the folder (:class:`~mitsuba_manifold._util.locking.FolderLock`)."""


class BusyError(InputError):
    """A request refused because too many like it wait already (a server's queue is full): ask
    again once one of them is done or cancelled.
    """


# ------------------------------------------------------------ one-line messages
# Mitsuba wraps an exception raised inside a Python plugin's constructor into a
# RuntimeError whose text holds the parser's context and a Python traceback.

_PLUGIN_LINE = re.compile(r"(manifold_(?:brdf|path): [^\n]*)")


def _chain(exc) -> list:
    seen = []
    while exc is not None and exc not in seen:
        seen.append(exc)
        exc = exc.__cause__ or exc.__context__
    return seen


def plugin_message(exc) -> str:
    """The ``manifold_brdf: ...`` / ``manifold_path: ...`` message inside ``exc`` (or its
    causes), without Mitsuba's wrapping and traceback; else :func:`one_line` of ``exc``.
    """
    for e in _chain(exc):
        found = _PLUGIN_LINE.findall(str(e))
        if found:
            return found[-1].strip()
    return one_line(exc)


def one_line(exc) -> str:
    """``exc`` as one line of text (a plugin's message when Mitsuba wrapped one)."""
    if not isinstance(exc, BaseException):
        return " ".join(str(exc).split())
    text = str(exc)
    if "Traceback (most recent call last)" in text or _PLUGIN_LINE.search(text):
        found = _PLUGIN_LINE.findall(text)
        if found:
            return found[-1].strip()
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        return lines[-1] if lines else type(exc).__name__
    if isinstance(exc, KeyError) and not isinstance(exc, MitsubaManifoldError) and exc.args:
        text = str(exc.args[0])
    return " ".join((text or type(exc).__name__).split())


def did_you_mean(name, choices) -> str:
    """``" (did you mean 'steel'?)"`` for the names of ``choices`` closest to ``name``, or ``""``."""
    import difflib

    close = difflib.get_close_matches(str(name), [str(c) for c in choices], n=3)
    return f" (did you mean {' or '.join(map(repr, close))}?)" if close else ""


class ConvergenceWarning(MitsubaManifoldError, UserWarning):
    """A fit stopped before its convergence test was met (at its iteration cap, or where no
    step improved): the layout is not a stationary point of its objective and may differ
    between machines.
    """
