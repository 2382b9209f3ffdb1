"""Material names as file names and image keys that cannot collide.

Material names come from the user (``<name>.binary`` files, real MERL or their own), so
any string may appear: ``base`` (the basis image of the paths that never touch the
material), ``a+b`` (the separator of multilinear image keys), ``../x``, ``.hidden``,
``Ünïcode``. :func:`escape` maps a name to a file stem made of ``[A-Za-z0-9._-]`` and
``%XX`` escapes (UTF-8 bytes, as in URLs) such that

- different names give different stems (``%`` itself is escaped, so the map is injective),
- no stem is a reserved word of a basis folder (:data:`RESERVED`) or starts with ``.``,
- no stem holds the key separator ``+`` or a path separator,
- no stem ends in ``.gi`` (:data:`RESERVED_SUFFIX`: ``<name>.gi.exr`` is the full-GI image of
  ``<name>``, so a material named ``steel.gi`` gets ``steel%2Egi.exr``).

Common names are unchanged (``gold-paint`` -> ``gold-paint``), so the files stay readable.
"""

from __future__ import annotations

from urllib.parse import unquote

from ..errors import InputError

#: Characters kept as they are; everything else is %-escaped.
SAFE = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_.")
#: Stems with a meaning in a basis folder (compared case-insensitively).
RESERVED = frozenset({"base", "manifest"})
#: Ending of the stems of a basis's full-GI images (``<stem>.gi.exr``), compared case-insensitively.
RESERVED_SUFFIX = ".gi"
#: Longest escaped stem: file systems allow 255 bytes per name, and ".exr" or a
#: temporary-file suffix is added.
MAX_STEM = 200


def escape(name) -> str:
    """File stem of a material name (see the module docstring); reversible by :func:`unescape`."""
    if not isinstance(name, str) or not name:
        raise InputError(f"material name {name!r} must be a non-empty string")
    out = "".join(
        c if c in SAFE else "".join(f"%{b:02X}" for b in c.encode("utf-8", "surrogatepass"))
        for c in name
    )
    if out.lower() in RESERVED or out.startswith("."):
        out = f"%{ord(out[0]):02X}" + out[1:]
    if out.lower().endswith(RESERVED_SUFFIX):
        cut = len(out) - len(RESERVED_SUFFIX)
        out = out[:cut] + "%2E" + out[cut + 1 :]
    if len(out) > MAX_STEM:
        raise InputError(
            f"material name {name[:40]!r}... is too long for a file name "
            f"({len(out)} characters once escaped, at most {MAX_STEM})"
        )
    return out


def unescape(stem) -> str:
    """The material name of a stem made by :func:`escape`."""
    return unquote(stem, errors="strict")


def check_unique(names) -> list:
    """Escaped stems of ``names``; raise if two would name one file on a case-insensitive
    file system (macOS, Windows), e.g. ``Steel`` and ``steel``.
    """
    stems: dict = {}
    for n in names:
        s = escape(n)
        other = stems.get(s.lower())
        if other is not None and other != n:
            raise InputError(
                f"materials {other!r} and {n!r} differ only in case: their images would be "
                "one file on a case-insensitive file system; rename one of them"
            )
        stems[s.lower()] = n
    return [escape(n) for n in names]


def is_escaped(stem) -> bool:
    """True when ``stem`` is what :func:`escape` makes of some name."""
    try:
        return escape(unescape(stem)) == stem
    except (InputError, UnicodeDecodeError, ValueError):
        return False


def is_name(text) -> bool:
    """Whether ``text`` (from a user, where a latent point may go) names a material rather than
    giving numbers: one word that does not start like a number (a digit, a sign or a point).
    """
    words = str(text).split()
    return len(words) == 1 and "," not in words[0] and words[0][0] not in "+-.0123456789"
