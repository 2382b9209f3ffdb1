"""Select a libLLVM that Dr.Jit's LLVM backend can use (version 16 or newer).

Dr.Jit loads libLLVM lazily, the first time an ``llvm_*`` variant runs a kernel, and
takes the path from ``DRJIT_LIBLLVM_PATH``. Debian's default libLLVM 15 aborts the
whole process on some kernels ("Cannot select ... fminimum"), so importing
:mod:`mitsuba_manifold.render` points Dr.Jit at a newer library (:func:`select`) when Dr.Jit
is not imported yet, unless the user already chose one. Nothing else in the package
changes ``os.environ``.
"""

import glob
import os
import re

MIN_VERSION = 16

_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)


def _version(path):
    """Major version encoded in a libLLVM file name, or None."""
    name = os.path.basename(path)
    m = re.search(r"LLVM[-.](?:so\.)?(\d+)", name) or re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def candidates():
    """LibLLVM files found on this machine, newest major version first."""
    found = {}
    patterns = []
    for d in _SEARCH_DIRS:
        patterns += [os.path.join(d, "libLLVM*.so*"), os.path.join(d, "libLLVM*.dylib")]
    patterns += ["/usr/lib/llvm-*/lib/libLLVM*.so*"]
    for pattern in patterns:
        for path in glob.glob(pattern):
            v = _version(path)
            if v is not None and os.path.isfile(path):
                found.setdefault(os.path.realpath(path), v)
    return sorted(found.items(), key=lambda kv: -kv[1])


def newest():
    """The newest libLLVM >= 16 of this machine, or None."""
    for path, version in candidates():
        if version >= MIN_VERSION:
            return path
    return None


def select():
    """Set ``DRJIT_LIBLLVM_PATH`` to a libLLVM >= 16 unless the user set it.

    Returns the path in use, or None when no suitable library exists (then the
    LLVM variants are unusable and :func:`require` raises a clear error).
    """
    user = os.environ.get("DRJIT_LIBLLVM_PATH")
    if user:
        return user
    path = newest()
    if path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


def require():
    """The libLLVM for Dr.Jit (``DRJIT_LIBLLVM_PATH``, else :func:`newest`); a ``VariantError``
    (a ``RuntimeError``) naming the problem when there is none. Changes nothing.
    """
    from ...errors import VariantError

    path = os.environ.get("DRJIT_LIBLLVM_PATH") or newest()
    if path is None:
        have = ", ".join(f"{p} (LLVM {v})" for p, v in candidates()) or "none"
        raise VariantError(
            f"mitsuba_manifold: Dr.Jit's LLVM backend needs libLLVM >= {MIN_VERSION}, found: {have}. "
            "Install one (Debian: 'apt-get install libllvm19') or set DRJIT_LIBLLVM_PATH."
        )
    if not os.path.exists(path):
        raise VariantError(f"mitsuba_manifold: DRJIT_LIBLLVM_PATH={path} does not exist")
    return path
