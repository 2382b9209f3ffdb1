"""Checks of user input made before anything is computed or written.

Each function returns the checked value or raises :class:`InputError` with one line naming
the parameter, the value and what would be accepted. ``name`` is how the message names the
value: a Python parameter in backquotes (```spp```, which the command-line tools write as
their option, :func:`mitsuba_manifold.apps.cli.common.cli_message`) or a tool's own words.
"""

from __future__ import annotations

import math
import numbers
import os
import re
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Sequence

import numpy as np

from ..errors import InputError, MismatchError

#: PNG exposure range in stops: 2**64 already maps every positive float32 to white.
EXPOSURE_RANGE = (-64.0, 64.0)


def finite(name, value, lo=-math.inf, hi=math.inf, lo_open=False) -> float:
    """``value`` as a float, finite and in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``); a
    boolean is refused (``True`` is not a number a user means).
    """
    try:
        if isinstance(value, (bool, np.bool_)):
            raise TypeError("a boolean")
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    low_ok = v > lo if lo_open else v >= lo
    if not math.isfinite(v) or not low_ok or v > hi:
        if hi < math.inf:
            span = f" in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
        else:
            span = f" {'>' if lo_open else '>='} {lo:g}" if lo > -math.inf else ""
        raise InputError(f"{name} must be a finite number{span}, got {value!r}")
    return v


def positive_int(name, value, example, hi=None) -> int:
    """``value`` as an int from 1 (to ``hi``); the error suggests ``name example``."""
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if not ok or value < 1 or (hi is not None and value > hi):
        span = f"from 1 to {hi}" if hi else "of at least 1"
        raise InputError(
            f"{name} {value!r} is not allowed: it must be an integer {span} (e.g. {name} {example})"
        )
    return int(value)


def exposure(value, name="`exposure`") -> float:
    """A PNG exposure in stops (see :data:`EXPOSURE_RANGE`)."""
    return finite(name, value, *EXPOSURE_RANGE)


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``), or None."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def fits_in_memory(name, nbytes, what, fraction=0.8) -> None:
    """Raise unless ``nbytes`` is below ``fraction`` of the memory available now."""
    avail = available_memory()
    if avail is not None and nbytes > fraction * avail:
        raise InputError(
            f"{name}: {what} needs about {nbytes / 2**30:.3g} GiB of memory; a run may take at "
            f"most {fraction:.0%} of the {avail / 2**30:.3g} GiB available now "
            f"({fraction * avail / 2**30:.3g} GiB): choose a smaller value"
        )


#: A number written as text: digits, an optional point and exponent (no ``1_0``, ``0x1``, ``inf``).
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
#: Separators of the coordinates in a latent point's text: commas and/or blanks.
_SEPARATOR = re.compile(r"\s*,\s*|\s+")


def _items(values) -> list:
    """The scalars of a (nested) sequence or array, in order (Python types: ``ndarray.tolist``)."""
    if hasattr(values, "__array__") and not isinstance(values, np.ndarray):
        values = np.asarray(values)
    if isinstance(values, np.ndarray):
        values = values.tolist()
    if isinstance(values, Sequence) and not isinstance(values, (str, bytes, bytearray)):
        return [v for x in values for v in _items(x)]
    return [values]


def _coordinate(name, v, q) -> float:
    """One coordinate as a float: a real number (not a boolean) or a number written as text."""
    if isinstance(v, str):
        if not v.strip():
            raise InputError(
                f"{name} has an empty coordinate (two commas in a row?); give {q} numbers "
                "like '0.25, -1e-3'"
            )
        if not _NUMBER.fullmatch(v.strip()):
            raise InputError(f"{name}: {v!r} is not a number; give {q} numbers like '0.25, -1e-3'")
        return float(v)
    if isinstance(v, (bool, np.bool_)):
        raise InputError(f"{name} must be {q} numbers, got the boolean {v!r}")
    if isinstance(v, numbers.Complex) and not isinstance(v, numbers.Real):
        raise InputError(f"{name} must be {q} real numbers, got the complex number {v!r}")
    if not isinstance(v, numbers.Real):
        raise InputError(f"{name} must be {q} numbers, got {v!r:.60}")
    return float(v)


#: NumPy kinds of what is not a real number, by name.
_NOT_REAL = {"b": "booleans", "c": "complex numbers", "U": "strings", "S": "strings"}


def _kind(v) -> str | None:
    """The NumPy kind of a scalar that is not a real number (``None`` for the others)."""
    if isinstance(v, (bool, np.bool_)):
        return "b"
    if isinstance(v, numbers.Complex) and not isinstance(v, numbers.Real):
        return "c"
    return "U" if isinstance(v, (str, bytes)) else None


def latent_point(name, values, q) -> np.ndarray:
    """One latent point: ``q`` finite numbers as a float64 array ``(q,)``.

    ``values`` is a sequence or array of real numbers (any shape with ``q`` of them), or text
    ``"a, b, c"`` / ``"a b c"``. Refused, with a message naming ``name`` (pass it as the
    caller's parameter, e.g. ``"`x`"``): booleans, complex numbers, non-finite values, a
    wrong count, and number forms ``float()`` accepts but nobody types for a coordinate
    (``"1_0"``, ``"0x1"``, ``"nan"``, ``"inf"``).
    """
    if isinstance(values, str):
        text = values.strip()
        parts = _SEPARATOR.split(text) if text else []
    elif isinstance(values, (bytes, bytearray)):
        raise InputError(f"{name} must be {q} numbers, got bytes {values!r:.60}")
    else:
        parts = _items(values)
    arr = np.array([_coordinate(name, v, q) for v in parts], dtype=np.float64)
    if arr.size != q or not np.isfinite(arr).all():
        raise InputError(
            f"{name} must be {q} finite numbers (the manifold's latent dimension), "
            f"got {arr.tolist()}"
        )
    return arr


def latent_points(name, x, q, max_abs=math.inf) -> tuple[np.ndarray, bool]:
    """Latent points as an ``(M, q)`` float64 array, and whether ``x`` was one point ``(q,)``.

    The array form of :func:`latent_point` (no text; vectorised for batches): ``x`` is
    ``(q,)`` or ``(M, q)`` real numbers; booleans, complex numbers, text, non-finite values
    and coordinates beyond ``max_abs`` are refused.
    """
    if isinstance(x, (list, tuple)):  # a Python list: its items, not NumPy's promotion of them
        kind = next((k for k in map(_kind, _items(x)) if k), None)
    else:
        kind = np.asarray(x).dtype.kind
    if kind in _NOT_REAL:
        raise InputError(
            f"{name} must be {q} numbers (a list or array; {_NOT_REAL[kind]} are not "
            f"accepted), got {x!r:.60}"
        )
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be {q} numbers (a list or array), got {x!r:.60}") from None
    single, shape = arr.ndim == 1, arr.shape
    arr = np.atleast_2d(arr)
    if arr.ndim != 2 or arr.shape[1] != q:
        raise InputError(f"{name} must have {q} coordinates, got shape {shape}")
    if not np.isfinite(arr).all():
        raise InputError(f"{name} contains NaN or Inf")
    big = float(np.abs(arr).max(initial=0.0))
    if big > max_abs:
        raise InputError(
            f"{name} coordinate {big:.3g} is too far out: its distances to the materials "
            f"overflow; give coordinates within +-{max_abs:.0e} (the materials lie "
            "within a few units of 0)"
        )
    return arr, single


def output_folder(name, path) -> str:
    """A folder that exists or can be created, and takes new files; returns it."""
    path = os.fspath(path)
    if os.path.exists(path) and not os.path.isdir(path):
        raise InputError(f"{name} {path} is a file, not a folder")
    probe = os.path.abspath(path)
    while not os.path.exists(probe):
        probe = os.path.dirname(probe)
    if not os.path.isdir(probe):
        raise InputError(f"{name} {path}: {probe} is a file, not a folder")
    try:  # a real probe: permission bits do not stop root, a read-only or virtual file system does
        with tempfile.TemporaryFile(dir=probe, prefix=".probe-"):
            pass
    except OSError as e:
        raise InputError(
            f"{name} {path}: cannot write in folder {probe} ({e.strerror or e})"
        ) from None
    return path


def scene_xml(path) -> ET.Element:
    """The root element of the Mitsuba scene XML ``path`` (a ``<scene>`` element), or a
    :class:`MismatchError` naming the file when it is missing, not XML (a table, an image) or
    not a scene.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise MismatchError(f"scene {path} does not exist")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise MismatchError(
            f"{path} is not a Mitsuba scene XML ({e}); give a scene "
            ".xml file or a shipped scene's name"
        ) from None
    if root.tag != "scene":
        raise MismatchError(
            f"{path} is not a Mitsuba scene XML (its root element is <{root.tag}>, not <scene>); "
            "give a scene .xml file or a shipped scene's name"
        )
    return root


def fraction(name, value) -> float:
    """A finite number in ``[0, 1)`` (e.g. a pruning threshold)."""
    v = finite(name, value, 0.0, 1.0)
    if v >= 1.0:
        raise InputError(f"{name} must be a finite number in [0, 1), got {value!r}")
    return v


#: Largest ``sum |w| / |sum w|`` accepted: beyond it, float32 tables lose every digit of the
#: combination to cancellation (1e30 - 1e30 + 1 is 0 in float32).
MAX_CANCELLATION = 1e6
#: Largest magnitude of one weight: far beyond any blend (weights sum to 1), and their sum and the
#: combined float32 table stay finite.
MAX_WEIGHT = 1e12


def weight_sum(w) -> float:
    """Raise :class:`InputError` unless weights ``w`` make a usable material: finite, none beyond
    :data:`MAX_WEIGHT` in magnitude, their sum (exact, :func:`math.fsum`) not 0 and not swamped by
    cancelling magnitudes.
    """
    w = np.asarray(w, dtype=np.float64).ravel()
    if not np.isfinite(w).all():
        raise InputError("weights must be finite numbers")
    if np.abs(w).max(initial=0.0) > MAX_WEIGHT:
        raise InputError(
            f"weights must be at most {MAX_WEIGHT:g} in magnitude (a material's "
            f"weights sum to 1), got {np.abs(w).max():.3g}"
        )
    total, size = math.fsum(w.tolist()), math.fsum(np.abs(w).tolist())
    if total == 0.0:
        raise InputError(
            "weights sum to zero; a material needs weights summing to 1 "
            "(they are used as given, not normalised)"
        )
    if size > MAX_CANCELLATION * abs(total):
        raise InputError(
            f"weights sum to {total:.6g} but their magnitudes add up to {size:.3g}: "
            f"terms this large cancel, and the combined table (float32) would keep no "
            f"correct digit; use weights with sum |w| <= {MAX_CANCELLATION:g} * |sum w|"
        )
    return total


#: Mitsuba's samplers take 32-bit seeds.
SEED_LIMIT = 1 << 32


def seed(name, value, streams=1, why="") -> int:
    """A seed from 0 such that ``streams`` consecutive seeds from ``value * streams`` (a
    renderer seeding pass ``p`` of ``n`` with ``seed * n + p``) fit Mitsuba's 32 bits.
    """
    ok = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    streams = max(1, int(streams))
    top = SEED_LIMIT // streams - 1
    if not ok or not 0 <= value <= top:
        raise InputError(f"{name} must be an integer from 0 to {top}{why}, got {value!r}")
    return int(value)
