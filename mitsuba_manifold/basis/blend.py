"""Images of any latent point from a basis of per-material renders (paper Sec. 5.2 and 6).

Rendering is linear in the BRDF. With one manifold material (one *target*) in the scene,
the part of the image made of paths that scatter off it at most once (``L1-``) is

    I(x) = base + sum_i w_i(x) I_i                                   (paper Eq. 13)

``base``: the paths that never touch the target; ``I_i``: the paths that touch it exactly
once, rendered with measured material ``i``; ``w(x)``: the manifold's affine weights.
Materials whose ``|w_i|`` is pruned away are skipped (:meth:`Manifold.prune` rescales the
kept weights to the same sum). With ``p`` targets (paper Sec. 6) the image is multilinear:

    I(x^1..x^p) = sum_{i_1..i_p} prod_t w^t_{i_t} I[i_1..i_p]

where ``I[i_1..i_p]`` is the full ``L1-`` image (base included) with target ``t`` set to
material ``i_t``.

A one-pass basis of one target may also hold full-GI images (the paper's
practice, Sec. 5.2 and Fig. 12: "applying this interpolation to calculate I_* directly"):
``F_i = touch_i + L2+_i``, so that ``base + F_i`` is material ``i`` with global illumination,
and the cross terms ``C_ij`` of :mod:`.crossterms`. The default blend (``component="full"``)
is then ``base + sum_i w_i F_i + sum_{i<j} w_i w_j C_ij``, summed (``l2="raw"``) exact at every
training material and for paths with two vertices on the material; by default its part beyond
L1- is denoised, keeping its light (:func:`~.denoise.denoised_l2`). ``component="l1"`` is Eq. 13. A basis without
full-GI images blends L1- (an older basis says so with a warning; one whose scene does not
need them, e.g. a convex object alone, says why in :attr:`BlendInfo.component_note`). The images
come from a basis folder (:mod:`mitsuba_manifold.basis.folder`); no Mitsuba is loaded here.
"""

import dataclasses
import itertools
import time
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import numpy as np

from ..errors import MismatchError
from ..imaging.io import printable
from ..manifold.pruning import DEFAULT_PRUNE
from .composition import compose, read_cross
from .crossterms import cross_weights
from .denoise import BasisAOVs, denoise, denoised_l2
from .folder import Basis

if TYPE_CHECKING:
    from typing import Any


#: How far the weights of one target may sum away from 1 in a multilinear blend.
AFFINE_TOL = 1e-6
#: Values of ``component``: full GI where the basis holds it (default), or L1- (Eq. 13).
BLEND_COMPONENTS = ("full", "l1")


def resolve_component(basis, component=None) -> "tuple[Any, str]":
    """``(component used, note)`` of a blend of ``basis`` asked for ``component`` (None: "full").

    The default is the full-GI blend wherever the basis holds full-GI images (the paper's
    practice, Sec. 5.2): exact at every training material, and with the cross terms through
    each pair's midpoint (:mod:`.crossterms`) close to a full-GI render between them, where the
    L1- blend misses the light that reaches the material more than once (figures in
    ``docs/benchmarks.md``).

    "full" on a basis without full-GI images blends L1-; the note says why (empty when the
    basis holds what was asked). An older basis (no ``components`` in its manifest) also
    warns, once per :class:`Basis`.
    """
    component = "full" if component is None else str(component)
    if component not in BLEND_COMPONENTS:
        raise MismatchError(f"`component` must be one of {BLEND_COMPONENTS}, got {component!r}")
    if component == "l1" or "l2+" in basis.components:
        return component, ""
    if basis.legacy:
        note = (
            f"basis {basis.folder} predates full-GI bases (its manifest lists no components): it blends "
            "L1- only, leaving out light that touched the material twice or more; render it again for full GI"
        )
        if not getattr(basis, "_warned_legacy", False):
            basis._warned_legacy = True
            warnings.warn(note, UserWarning, stacklevel=3)
        return "l1", note
    why = (basis.manifest.left_out or {}).get("l2+", "the basis holds L1- images only")
    return "l1", f"L1- blend: {why}"


# -------------------------------------------------------------------- blend


def latent_points(basis, manifold, x) -> "np.ndarray":
    """``x`` as (p, q): one latent point per target.

    Accepts (q,) for one target, (p, q), or p*q numbers in target order; a material's name
    stands for its latent point (``"chrome"``, or ``["chrome", "steel"]`` one per target, or
    names and points mixed in a list).
    """
    p, q = basis.p, manifold.q
    if isinstance(x, str) or (isinstance(x, (list, tuple)) and any(isinstance(v, str) for v in x)):
        x = np.concatenate(
            [
                manifold.point(v) if isinstance(v, str) else np.ravel(np.asarray(v, dtype=object))
                for v in ([x] if isinstance(x, str) else x)
            ]
        )
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise MismatchError(f"`x` must be numbers, got {x!r}") from None
    if arr.size != p * q or arr.ndim > 2 or (arr.ndim == 2 and arr.shape != (p, q)):
        raise MismatchError(
            f"`x` has shape {arr.shape} ({arr.size} numbers), but the basis has {p} target(s) "
            f"{basis.targets} on a {q}-dimensional manifold: `x` needs {p * q} numbers "
            f"({'q' if p == 1 else 'p x q'})"
        )
    arr = arr.reshape(p, q)
    if not np.isfinite(arr).all():
        raise MismatchError(f"`x` contains NaN or Inf: {arr.tolist()}")
    return arr


def _target_weights(basis, manifold, x, w) -> "tuple[Any, np.ndarray | None]":
    """Affine weights (p, N) from ``x`` or ``w``, plus the latent points (or None)."""
    if (x is None) == (w is None):
        raise MismatchError("give exactly one of `x` (latent point) and `w` (weights)")
    if x is not None:
        pts = latent_points(basis, manifold, x)
        return manifold.weights(pts)[1], pts
    try:
        arr = np.asarray(w, dtype=np.float64)
    except (TypeError, ValueError):
        raise MismatchError(f"`w` must be numbers, got {w!r}") from None
    n = len(manifold.names)
    if arr.size != basis.p * n or arr.ndim > 2 or (arr.ndim == 2 and arr.shape != (basis.p, n)):
        raise MismatchError(
            f"`w` has shape {arr.shape}; the basis has {basis.p} target(s) and the manifold "
            f"{n} materials: `w` needs shape ({n},) or ({basis.p}, {n})"
        )
    arr = arr.reshape(basis.p, n)
    if not np.isfinite(arr).all():
        raise MismatchError("`w` contains NaN or Inf")
    return arr, None


@dataclass(frozen=True)
class BlendPlan:
    """What one blend sums (Eq. 13): the images, their weights and the cross terms.

    Attributes
    ----------
    keys : list of str
        The materials' image keys, as an L1- blend names them.
    image_weights : ndarray (K,)
        Their weights (after pruning; plus ``base`` with weight 1 for a one-target basis).
    cross : (ndarray, ndarray) or None
        The rows of the basis's cross terms and their weights ``w_i w_j`` (a full-GI blend of
        one target), or None.
    image_keys : list of str
        The images summed: :attr:`keys`, or their full-GI images when there are cross terms.
    """

    keys: list
    image_weights: np.ndarray
    cross: Optional[tuple] = None
    image_keys: list = None

    @property
    def summed(self) -> list:
        """The images summed: :attr:`image_keys` or, when not set, :attr:`keys`."""
        return self.keys if self.image_keys is None else self.image_keys


@dataclass(frozen=True)
class BlendInfo:
    """What one blend made and how: the second value :func:`blend` returns.

    Attributes
    ----------
    component : {"full", "l1"}
        The blend made: full GI or L1- (Eq. 13).
    component_note : str
        Why :attr:`component` is not the one asked for ("" when it is).
    l2 : {"denoised", "raw"} or None
        The full-GI blend's part beyond L1-: denoised or summed; None for an L1- blend.
    weights : tuple of dict
        Per target, kept material name -> its weight after pruning.
    dropped_weight : tuple of float
        Per target, the weight pruning dropped.
    missing : dict
        Image key -> weight of the images the blend needed and the basis lacks (empty unless
        ``renormalise``).
    renormalised : bool
        Whether the weights were rescaled over the images present.
    cross_left_weight : float or None
        Largest ``|w_i w_j|`` of a pair whose cross term the basis does not hold; None without
        cross terms.
    plan : BlendPlan
        The images, weights and cross terms summed.
    x : ndarray or None
        The latent point ((q,) for one target, (p, q) for several); None for a blend of weights.
    time_ms : float or None
        Milliseconds of weights, pruning, summing the images in memory and denoising; None for
        one image of :func:`blend_path` (:attr:`BlendPathInfo.time_ms` times them all).
    time_read_s : float or None
        Seconds reading the images from disk; None as :attr:`time_ms`.
    denoise_ms : float or None
        Milliseconds denoising the whole image (:func:`denoised_blend` only).
    guided : bool or None
        Whether that denoising used the basis's AOVs (:func:`denoised_blend` only).
    """

    component: str
    component_note: str
    l2: Optional[str]
    weights: tuple
    dropped_weight: tuple
    missing: dict
    renormalised: bool
    cross_left_weight: Optional[float]
    plan: BlendPlan
    x: Optional[np.ndarray] = None
    time_ms: Optional[float] = None
    time_read_s: Optional[float] = None
    denoise_ms: Optional[float] = None
    guided: Optional[bool] = None

    @property
    def n_images(self) -> int:
        """Number of images summed (:attr:`BlendPlan.summed`)."""
        return len(self.plan.summed)


@dataclass(frozen=True)
class BlendPathInfo:
    """What :func:`blend_path` made: the third value it returns.

    Attributes
    ----------
    steps : tuple of BlendInfo
        Each image's blend (their ``time_ms`` and ``time_read_s`` None).
    component, component_note, l2
        As :class:`BlendInfo`, the same for every image.
    time_ms : float
        Milliseconds of weights, pruning and summing all images in memory (denoising apart).
    time_read_s : float
        Seconds reading the images from disk.
    denoise_ms : float
        Milliseconds denoising the images' part beyond L1- (0 when not denoised).
    """

    steps: tuple
    component: str
    component_note: str
    l2: Optional[str]
    time_ms: float
    time_read_s: float
    denoise_ms: float


def _plan(
    basis, manifold, W, prune, renormalise, component="l1"
) -> "tuple[BlendPlan, dict[str, list | None]]":
    """The :class:`BlendPlan` of one blend and its report.

    Returns ``(plan, report)``: the images, weights and cross terms to sum, and the
    :class:`BlendInfo` fields they fix (``weights``, ``dropped_weight``, ``missing``,
    ``renormalised``, ``cross_left_weight``) as keywords.
    """
    p, names = basis.p, manifold.names
    info: dict[str, Any]
    kept, info = [], {"weights": [], "dropped_weight": [], "cross_left_weight": None}
    for t in range(p):
        if p > 1 and abs(W[t].sum() - 1.0) > AFFINE_TOL:
            raise MismatchError(
                f"weights of target {basis.targets[t]!r} sum to {W[t].sum():.9g}; a "
                "multilinear blend needs weights summing to 1 per target (its images "
                "include the base)"
            )
        keep, wk, dropped = manifold.prune(W[t], prune)
        kept.append((keep, wk))
        info["weights"].append({names[i]: float(v) for i, v in zip(keep, wk)})
        info["dropped_weight"].append(dropped)
    if p == 1:
        keys = [basis.key([names[i]]) for i in kept[0][0]]
        cw = kept[0][1].copy()
    else:
        keys = [
            basis.key([names[i] for i in combo])
            for combo in itertools.product(*(k for k, _ in kept))
        ]
        cw = kept[0][1]
        for _, wk in kept[1:]:
            cw = np.multiply.outer(cw, wk).ravel()
    total = cw.sum()
    present = np.array([basis.has(k) for k in keys], dtype=bool)
    missing = {k: float(v) for k, v, ok in zip(keys, cw, present) if not ok}
    info["missing"] = missing
    info["renormalised"] = False
    if missing:
        if not renormalise:
            listed = ", ".join(
                f"{k} (w={v:.4g})"
                for k, v in sorted(missing.items(), key=lambda kv: -abs(kv[1]))[:10]
            )
            raise MismatchError(
                f"basis {basis.folder} lacks {len(missing)} image(s) whose weight survives pruning "
                f"(prune={prune:g}): {listed}{' ...' if len(missing) > 10 else ''}. Render them, raise "
                "`prune`, or pass `renormalise` to rescale over the images present (an approximation)"
            )
        if not present.any() or abs(cw[present].sum()) < 1e-12:
            raise MismatchError(
                f"basis {basis.folder}: none of the images this blend needs is present "
                f"(missing: {', '.join(sorted(missing)[:10])}); cannot renormalise"
            )
        keys = [k for k, ok in zip(keys, present) if ok]
        cw = cw[present] * (total / cw[present].sum())
        info["renormalised"] = True
    cross = None
    if component == "full" and p == 1:
        pairs, _ = basis.cross_terms()
        kept_names = [basis.key([names[i]]) for i in kept[0][0]]
        mats = [k for k in kept_names if k in keys]
        wk = np.array([cw[keys.index(k)] for k in mats])
        rows, prods, left = cross_weights(
            [names[kept[0][0][kept_names.index(k)]] for k in mats], wk, pairs
        )
        cross = (rows, prods)
        info["cross_left_weight"] = left if "cross" in basis.components else None
    summed = keys if cross is None else [basis.gi_key(k) for k in keys]
    info["weights"], info["dropped_weight"] = tuple(info["weights"]), tuple(info["dropped_weight"])
    return BlendPlan(keys, cw, cross, summed), info


#: Values of ``l2`` (:class:`BlendSettings`).
L2_MODES = ("denoised", "raw")


@dataclass(frozen=True)
class BlendSettings:
    """How an image is blended: the settings :func:`blend`, :func:`denoised_blend` and
    :func:`blend_path` share.

    Each function takes them the same two ways, as :func:`~.inverse.match.match` takes its
    :class:`~.inverse.match.MatchSettings`: ``settings=BlendSettings(...)``, and each field as a
    keyword of its own (``blend(basis, x=x, prune=0.01)``), which replaces that field of
    ``settings``.

    Parameters
    ----------
    prune : float
        The pruning bound of :meth:`Manifold.prune` (by default on each albedo channel and the
        cosine-weighted table change; the kept weights are rescaled to the same sum).
    renormalise : bool
        When images the blend needs are missing (e.g. a basis rendered ``near`` a point only), drop
        them and rescale the others' weights to the same sum instead of raising (an approximation).
    component : {"full", "l1"}, optional
        The component of the image blended (see the glossary): ``"full"`` (default, None): all
        light, the full-GI blend where the basis holds full-GI images (else L1-, see
        :func:`resolve_component`); ``"l1"``: Eq. 13 on the L1- images.
    l2 : {"denoised", "raw"}
        The full-GI blend's part beyond L1- (noisy where interreflection runs through a narrow peak):
        OIDN-denoised, its light kept (default, :func:`~.denoise.denoised_l2`), or summed (faster).
    """

    prune: float = DEFAULT_PRUNE
    renormalise: bool = False
    component: Optional[str] = None
    l2: str = "denoised"

    def check(self) -> "BlendSettings":
        """Raise :class:`MismatchError` naming the first setting out of range; returns ``self``."""
        if self.component is not None and str(self.component) not in BLEND_COMPONENTS:
            raise MismatchError(
                f"`component` must be one of {BLEND_COMPONENTS}, got {self.component!r}"
            )
        if self.l2 not in L2_MODES:
            raise MismatchError(f"`l2` must be one of {L2_MODES}, got {self.l2!r}")
        return self


#: The fields of :class:`BlendSettings`: the keywords :func:`blend`, :func:`denoised_blend` and
#: :func:`blend_path` take besides ``settings``.
BLEND_SETTINGS = tuple(f.name for f in dataclasses.fields(BlendSettings))


def blend_settings(settings=None, **overrides) -> BlendSettings:
    """``settings`` (default ``BlendSettings()``) with the fields ``overrides`` names replaced,
    checked: how :func:`blend`, :func:`denoised_blend` and :func:`blend_path` read their settings.

    Raises
    ------
    TypeError
        A keyword that is no field of :class:`BlendSettings` (as Python says of any function).
    """
    if settings is None:
        settings = BlendSettings()
    elif not isinstance(settings, BlendSettings):
        raise MismatchError(
            f"`settings` must be a BlendSettings, got {type(settings).__name__}: give "
            "`settings=BlendSettings(...)` or the settings as keywords (`prune=...`)"
        )
    unknown = sorted(set(overrides) - set(BLEND_SETTINGS))
    if unknown:
        raise TypeError(
            f"unexpected keyword argument(s) {unknown}: the settings of a blend are "
            f"{', '.join(BLEND_SETTINGS)} (fields of BlendSettings)"
        )
    return dataclasses.replace(settings, **overrides).check() if overrides else settings.check()


def blend(
    basis,
    manifold=None,
    *,
    x=None,
    w=None,
    settings=None,
    **overrides,
) -> "tuple[Any, BlendInfo]":
    """The image of latent point ``x`` (or weights ``w``) from a basis.

    Parameters
    ----------
    basis : Basis or str
    manifold : Manifold or str, optional
        Default: the manifest's manifold. Checked against the manifest.
    x : array_like
        Latent point: (q,) for one target, (p, q) (or p*q numbers) for p targets.
    w : array_like
        Weights instead of ``x``: (N,) or (p, N). With one target any weights are allowed
        (the touch images are linear in the BRDF); with several, each row must sum to 1.
    settings : BlendSettings, optional
        How to blend (default ``BlendSettings()``).
    **overrides
        Fields of :class:`BlendSettings` (``prune``, ``renormalise``, ``component``, ``l2``)
        replacing those of ``settings``.

    Returns
    -------
    image : ndarray float32 (H, W, 3)
    info : BlendInfo
        The blend made (component, weights kept, images missing, timings).
    """
    opts = blend_settings(settings, **overrides)
    l2 = opts.l2
    if not isinstance(basis, Basis):
        basis = Basis.load(basis)
    manifold = basis.check_manifold(manifold)
    used, note = resolve_component(basis, opts.component)
    t_cross = read_cross(basis, used)
    t0 = time.perf_counter()
    W, pts = _target_weights(basis, manifold, x, w)
    plan, report = _plan(basis, manifold, W, opts.prune, opts.renormalise, used)
    t_plan = time.perf_counter() - t0
    image, t_read, t_sum = compose(basis, plan.summed, plan.image_weights, plan.cross)
    t_read += t_cross
    t_den = 0.0
    if used == "full" and l2 == "denoised" and basis.p == 1:
        t0 = time.perf_counter()
        image = denoised_l2(basis, image, plan)
        t_den = time.perf_counter() - t0
    info = BlendInfo(
        component=used,
        component_note=note,
        l2=l2 if used == "full" else None,
        plan=plan,
        x=None if pts is None else (pts[0] if basis.p == 1 else pts),
        time_ms=1e3 * (t_plan + t_sum + t_den),
        time_read_s=t_read,
        **report,
    )
    return image, info


def denoised_blend(
    basis,
    manifold=None,
    *,
    x=None,
    w=None,
    aovs=None,
    guides=True,
    settings=None,
    **overrides,
) -> "tuple[Any, np.ndarray, Any]":
    """:func:`blend` and its denoised version (OIDN on the whole image, :mod:`.denoise`).

    Parameters
    ----------
    basis, manifold, x, w
        As :func:`blend`.
    aovs : BasisAOVs, optional
        The denoising guides (default: read beside the basis).
    guides : bool
        Guide the denoiser by the blend's albedo and the normals.
    settings, **overrides
        As :func:`blend`, but ``l2`` defaults to ``"raw"`` when neither it nor ``settings`` is
        given (the whole image is denoised).

    Returns
    -------
    raw, denoised : ndarray float32 (H, W, 3)
    info : BlendInfo
        The blend's, with :attr:`~BlendInfo.denoise_ms` and :attr:`~BlendInfo.guided` set.
    """
    if settings is None:  # its L2+ part summed: the whole image is denoised below
        overrides = {"l2": "raw", **overrides}
    opts = blend_settings(settings, **overrides)
    if not isinstance(basis, Basis):
        basis = Basis.load(basis)
    raw, info = blend(basis, manifold, x=x, w=w, settings=opts)
    t0 = time.perf_counter()
    if guides:
        aovs = aovs or BasisAOVs.load(basis.folder, basis.manifest)
        albedo = aovs.albedo_of_blend(info.plan, basis.manifest.version)
        out = denoise(raw, albedo, aovs.normal)
    else:
        out = denoise(raw)
    info = dataclasses.replace(
        info, denoise_ms=1e3 * (time.perf_counter() - t0), guided=bool(guides)
    )
    return raw, out, info


def _endpoint(manifold, v):
    if isinstance(v, str):
        return manifold.latent[manifold.index(v)].copy()
    arr = np.asarray(v, dtype=np.float64).ravel()
    if arr.size != manifold.q or not np.isfinite(arr).all():
        raise MismatchError(
            f"path end {v!r} (`a` or `b`): expected a material name or {manifold.q} finite numbers"
        )
    return arr


@dataclass(frozen=True)
class MovingTarget:
    """With several targets: which one moves along a path and where the others stay.

    Parameters
    ----------
    target : int
        The target that moves along the path.
    x : array_like (p, q), optional
        The latent points of the others (row ``target`` ignored); required with several
        targets, refused with one.
    """

    target: int = 0
    x: object = None


def blend_path(  # noqa: C901  its arguments checked, then one pass over the steps
    basis,
    manifold=None,
    a=None,
    b=None,
    *,
    steps=20,
    kind=None,
    points=None,
    moving=None,
    settings=None,
    **overrides,
) -> "tuple[Any, np.ndarray, BlendPathInfo]":
    """Images along a latent path from ``a`` to ``b`` (paper Fig. 12).

    Parameters
    ----------
    a, b : str or array_like (q,)
        Material names (their latent points) or latent points.
    steps : int
        Number of images, ``t = 0 .. 1`` inclusive (>= 2).
    kind : {"faithful", "straight", "uniform", "geodesic"}, optional
        The path (:mod:`mitsuba_manifold.manifold.paths`; default
        :data:`~mitsuba_manifold.manifold.paths.DEFAULT_KIND`, ``faithful``, as
        ``Manifold.path``, ``blend.py --path`` and the explorer): ``straight`` (the latent segment
        at equal steps), ``uniform`` or ``geodesic`` (equal perceptual steps), ``faithful`` (each
        image as far from the two ends as its place says).
    points : array_like (steps, q), optional
        The latent points of the path instead (e.g. from ``Manifold.path``); ``a``, ``b``,
        ``steps`` and ``kind`` are then ignored.
    moving : MovingTarget, optional
        With several targets: which one moves and where the others stay (default
        ``MovingTarget()``: the first, with no others).
    settings, **overrides
        How each image is blended, as :func:`blend` (``time_ms`` leaves the denoising out:
        ``denoise_ms``).

    Returns
    -------
    images : ndarray float32 (steps, H, W, 3)
    xs : ndarray (steps, q)
        The latent points of the moving target.
    info : BlendPathInfo
        Each image's :class:`BlendInfo` and the timings of them all.
    """
    moving = MovingTarget() if moving is None else moving
    opts = blend_settings(settings, **overrides)
    target, x = moving.target, moving.x
    prune, renormalise, l2 = opts.prune, opts.renormalise, opts.l2
    if not isinstance(basis, Basis):
        basis = Basis.load(basis)
    manifold = basis.check_manifold(manifold)
    if points is not None:
        xs = _path_points(manifold, points)
        steps = len(xs)
    elif not isinstance(steps, (int, np.integer)) or steps < 2:
        raise MismatchError(f"`steps` must be an integer >= 2, got {steps!r}")
    if not 0 <= target < basis.p:
        raise MismatchError(f"`target` {target} out of range: the basis has {basis.p} target(s)")
    if basis.p == 1 and x is not None:
        raise MismatchError(
            "`x` is for the targets that stay fixed along a path, and this basis has one target "
            "(the path sets its point): leave `x` out"
        )
    if points is None:
        xs = _segment_points(manifold, a, b, steps, kind)
    if basis.p > 1:
        if x is None:
            raise MismatchError(
                f"the basis has {basis.p} targets: give `x` for the targets that stay fixed"
            )
        fixed = latent_points(basis, manifold, x)
    used, note = resolve_component(basis, opts.component)
    t_cross = read_cross(basis, used)
    t0 = time.perf_counter()
    plans = []
    for xi in xs:
        pts = (
            xi[None] if basis.p == 1 else np.where(np.arange(basis.p)[:, None] == target, xi, fixed)
        )
        W = manifold.weights(pts)[1]
        plans.append(_plan(basis, manifold, W, prune, renormalise, used))
    keys = sorted({k for plan, _ in plans for k in plan.summed})
    col = {k: j for j, k in enumerate(keys)}
    M = np.zeros((steps, len(keys)), dtype=np.float32)
    for s, (plan, _) in enumerate(plans):
        M[s, [col[k] for k in plan.summed]] = plan.image_weights
    cross = None
    if used == "full" and basis.p == 1:  # the cross terms of every step, as one matrix
        rows = sorted({int(r) for plan, _ in plans for r in plan.cross[0]})
        at = {r: j for j, r in enumerate(rows)}
        C = np.zeros((steps, len(rows)), dtype=np.float32)
        for s_, (plan, _) in enumerate(plans):
            C[s_, [at[int(r)] for r in plan.cross[0]]] = plan.cross[1]
        cross = (np.array(rows, dtype=np.intp), C)
    t_plan = time.perf_counter() - t0
    images, t_read, t_sum = compose(basis, keys, M, cross)
    t_read += t_cross
    t0 = time.perf_counter()
    if (
        used == "full" and l2 == "denoised" and basis.p == 1
    ):  # as blend(): each step's L2+ part denoised
        for s_, ((plan, _), img) in enumerate(zip(plans, images)):
            images[s_] = denoised_l2(basis, img, plan)
    l2_used = l2 if used == "full" else None
    info = BlendPathInfo(
        steps=tuple(
            BlendInfo(component=used, component_note=note, l2=l2_used, plan=plan, x=xi, **report)
            for (plan, report), xi in zip(plans, xs)
        ),
        component=used,
        component_note=note,
        l2=l2_used,
        time_ms=1e3 * (t_plan + t_sum),
        time_read_s=t_read,
        denoise_ms=1e3 * (time.perf_counter() - t0),
    )
    return images, xs, info


def _segment_points(manifold, a, b, steps, kind):
    """The ``steps`` latent points of a path of ``kind`` from ``a`` to ``b`` (None: the package's
    default kind; ``"straight"``: the segment, evenly spaced).
    """
    xa, xb = _endpoint(manifold, a), _endpoint(manifold, b)
    if np.array_equal(xa, xb):
        raise MismatchError(
            f"the path's ends {a!r} and {b!r} are the same latent point (all {steps} images would "
            "be the same): give two different materials or points"
        )
    from ..manifold import paths

    kind = paths.DEFAULT_KIND if kind is None else kind
    if kind == "straight":
        t = np.linspace(0.0, 1.0, steps)[:, None]
        return (1.0 - t) * xa + t * xb
    return paths.path(manifold, xa, xb, steps, kind)


def _path_points(manifold, points) -> "np.ndarray":
    """``points`` as a ``(steps, q)`` array of finite latent points (steps >= 2)."""
    try:
        xs = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError):
        raise MismatchError(f"`points` must be numbers, got {points!r:.60}") from None
    if xs.ndim != 2 or xs.shape[1] != manifold.q or len(xs) < 2 or not np.isfinite(xs).all():
        raise MismatchError(
            f"`points` must be (steps >= 2, q = {manifold.q}) finite latent points, got shape {xs.shape}"
        )
    return xs


def path_labels(pair, steps) -> list[str]:
    """Labels of a contact sheet of :func:`blend_path` from ``pair[0]`` to ``pair[1]``: ``t``
    under every frame, each end's name (or latent point, as given) under the first and the last
    (control characters of a name escaped: one field per line).
    """
    labels = [f"t = {t:.2f}" for t in np.linspace(0, 1, steps)]
    labels[0] += f"\n{printable(pair[0])}"
    labels[-1] += f"\n{printable(pair[1])}"
    return labels
