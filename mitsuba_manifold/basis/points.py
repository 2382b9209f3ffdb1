"""Which latent point each target of a basis takes: the points a user asks a blend for, checked.

A basis rendered with ``p`` manifold materials (its ``targets``, BSDF ids, in the manifest's
order) blends one latent point per target (paper Eq. 13 for each). A user gives them as
material names or ``q`` numbers, target after target (:func:`target_points`); along a path one
target moves (:func:`target_index`) between two ends (:func:`path_end`) and the points of the
others stay fixed. Messages name the Python parameters (`x`, `path`, `target`, `steps`), which a
command-line tool writes as its options.
"""

import math
from collections.abc import Sequence
from typing import Optional

from .._util import checks
from ..errors import MismatchError


def flat_numbers(points, manifold) -> Optional[list]:
    """``points`` (each a material's name or a sequence of numbers) as one flat list of numbers,
    each name replaced by its latent point (``q`` numbers); None stays None.
    """
    if points is None:
        return None
    return [float(c) for v in points for c in (manifold.point(v) if isinstance(v, str) else v)]


def target_index(basis, target: Optional[str]) -> int:
    """The row of the target ``target`` (a BSDF id; None: the first) among ``basis.targets``."""
    if target is None:
        return 0
    if target not in basis.targets:
        raise MismatchError(f"`target` {target!r} is not a target of the basis ({basis.targets})")
    return list(basis.targets).index(target)


def target_points(
    basis, manifold, points: Optional[Sequence], path: bool = False, moving: Optional[str] = None
) -> Optional[list]:
    """The latent points of ``points`` for the targets of ``basis``, as one flat list of numbers.

    Parameters
    ----------
    basis : Basis
    manifold : Manifold
    points : list or None
        One point per target (each a material's name or ``q`` numbers), in the order of
        ``basis.targets``; along a path on several targets, one per target that stays fixed
        (one per target is accepted too, the moving one's ignored).
    path : bool
        The points are the fixed ones of a path (:func:`~mitsuba_manifold.basis.blend.blend_path`).
    moving : str, optional
        Along a path: the target that moves (default: the first).

    Returns
    -------
    list of float or None
        ``p * q`` numbers (along a path, the moving target's row holds the first training
        material's point, which the path replaces); None where ``points`` is None.

    Raises
    ------
    MismatchError
        Too many or too few points, an unknown ``moving`` target, or fixed points given for a
        basis of one target.
    """
    x = flat_numbers(points, manifold)
    groups = len(points or ())
    p, q, targets = basis.p, manifold.q, basis.targets
    each = f"each a material name or {q} number{'s' if q > 1 else ''}"
    if path and moving not in (None, *targets):
        raise MismatchError(f"`target` {moving!r} is not a target of the basis ({targets})")
    if path and p > 1:
        row = target_index(basis, moving)
        fixed = [t for k, t in enumerate(targets) if k != row]
        if x is not None and len(x) == (p - 1) * q:
            rows = [x[k * q : (k + 1) * q] for k in range(p - 1)]
            rows.insert(row, list(manifold.latent[0]))  # the path sets this target's point
            return [v for r in rows for v in r]
        if x is None or len(x) != p * q:
            got = "no `x`" if x is None else f"`x` gives {groups} point(s)"
            raise MismatchError(
                f"`path` moves target {targets[row]!r} of the basis's targets {targets}, and "
                f"{got}: give one `x` per target that stays fixed ({', '.join(fixed)}"
                f"{', in this order' if len(fixed) > 1 else ''}), {each} (`x` A{' `x` B' if len(fixed) > 1 else ''})"
            )
        return x
    if path:
        if x is not None:
            raise MismatchError(
                "`x` sets the fixed targets along `path`, and this basis has one target, whose point the path "
                "sets: drop `x` (or drop `path` to blend the point `x`)"
            )
        return x
    if x is not None and groups > p:
        raise MismatchError(
            f"`x` is given {groups} times, and this basis has {p} target(s) "
            f"{targets}: give `x` once per target, {each}"
        )
    if x is not None and len(x) != p * q and p == 1:
        raise MismatchError(
            f"`x` needs {q} numbers (the manifold's latent dimension) or a material's name, "
            f"got {len(x)} numbers"
        )
    if x is not None and len(x) != p * q:
        raise MismatchError(
            f"`x` gives {groups} point(s) ({len(x)} numbers), and this basis has "
            f"{p} target(s) {targets} on a {q}-dimensional manifold: repeat `x` once per target, "
            f"in this order, {each}"
        )
    return x


def path_end(manifold, end, given=None):
    """One end of a path: a training material's name, or ``q`` finite numbers (``given``: the
    text the user typed, for the message). A name the manifold does not know is returned as it
    is (:func:`~mitsuba_manifold.basis.blend.blend_path` reports it).
    """
    if isinstance(end, str):
        return end
    if len(end) != manifold.q or not all(map(math.isfinite, end)):
        shown = end if given is None else given
        raise MismatchError(
            f"`path` end {shown!r} must be a material name or {manifold.q} finite numbers"
        )
    return end


def check_path_memory(basis, steps: int) -> None:
    """Raise unless the ``steps`` images of a path of ``basis`` (and their working copies) fit
    in the memory available now.
    """
    w, h = basis.resolution
    checks.fits_in_memory("`steps`", 2 * steps * w * h * 3 * 4, f"{steps} images of {w}x{h}")
