"""Inverse rendering on a basis: the latent point whose image best matches an image.

The ``L1-`` image of latent point ``x`` (paper Eq. 13) is linear in the affine weights,

    I(x) = base + sum_i w_i(x) I_i,        w(x): the manifold's interpolant (default: convex
                                           Shepard weights; preset "paper": Eq. 4)

and ``w`` is smooth in ``x`` with the closed-form Jacobian :meth:`Manifold.weights_jacobian`,
so ``dI/dx = sum_i (dw_i/dx) I_i`` and an image can be matched by optimising ``x``
over the blend, without rendering. :func:`match` minimises

    E(x) = image_error(s I(x), image) + prior * var(x)

- ``image_error``: the relative MSE of :mod:`metrics` (``(a - r)^2 / (r^2 + eps)`` per pixel
  and channel, ``eps = 0.01``: bright pixels and fireflies of the image do not dominate)
  averaged over the mask, or (``loss="log"``) the MSE of log luminance;
- ``s``: 1, or with ``exposure_free`` the best scale for each ``x`` in closed form (for the
  log loss: both images normalised by their mean luminance over the mask);
- ``var(x)``: the GP's predictive variance (paper Eq. 2), an optional prior keeping the
  result where the data is.

For the relative MSE the error is a quadratic form in ``u = (1, w)``: one float64 Gram matrix
of the ``N + 1`` images over the masked pixels makes every evaluation ``O(N^2)``, at full
resolution and exactly. The log loss evaluates the images at every step: the search runs on a
box-downsampled copy and the best point is refined at full resolution.

Search (:mod:`mitsuba_manifold.basis.inverse.search`, shared with the render match): every
training material alone (``w = e_i``) and ``scan`` random points near the data are scored at
once (one matrix product); L-BFGS-B (SciPy) then starts from the best single material's
latent point and the best scanned points (``starts`` in all; with ``scan=0`` from the
training points nearest to the best single material, which on a stiff manifold often misses
the basin of the answer), and the best of the optimised points and the single materials is
returned. A training point
itself is reachable exactly (every interpolant gives ``w = e_i`` there), so a training
material's own image gives back its own point.
"""

import time
from dataclasses import dataclass, field, replace

import numpy as np

from ..._util.blas import one_thread
from ..._util.moved import renamed_argument
from ...errors import InputError
from ..composition import compose
from ..folder import BASE, Basis
from . import objectives as image_error
from . import search as latent
from .objectives import LOSSES, masked_rel_mse
from .targets import check_mask, check_target, read_mask, read_target

#: Pixels of the downsampled search image (log loss) are about this many at most.
SEARCH_PIXELS = 64 * 64


@dataclass
class SingleMatch:
    """The best training material alone (``w = e_i``)."""

    name: str
    index: int
    error: float
    exposure: float


class LatentMatch:
    """What every match finds: a latent point ``x`` and its affine weights ``weights`` over the
    materials ``names`` (the base of :class:`MatchResult` and of the rendered match's result).
    """

    def top_weights(self, k=6):
        """The ``k`` largest nonzero ``|w_i|`` as ``[(name, w_i)]``."""
        order = np.argsort(-np.abs(self.weights), kind="stable")[:k]
        return [(self.names[i], float(self.weights[i])) for i in order if self.weights[i] != 0]

    def nearest(self, manifold, k=3):
        """The ``k`` training materials nearest to ``x`` in latent space, ``[(name, distance)]``."""
        d = np.linalg.norm(manifold.latent - self.x, axis=1)
        return [(manifold.names[i], float(d[i])) for i in np.argsort(d)[:k]]


@dataclass
class MatchResult(LatentMatch):
    """What :func:`match` found.

    Attributes
    ----------
    x : ndarray (q,)
        The best latent point.
    weights : ndarray (N,)
        Its affine weights (manifold order).
    error : float
        The image error at ``x`` (relative MSE, or log-luminance MSE with ``loss="log"``)
        over the mask, at full resolution, after the exposure.
    rel_mse : float
        Relative MSE (:func:`metrics.rel_mse` over the mask) of ``exposure * image``.
    exposure : float
        Scale applied to the blend (1 unless ``exposure_free``).
    variance : float
        GP variance (Eq. 2) at ``x``: near 0 at the data, ``1 + mu`` far from it.
    objective : float
        ``error + prior * variance``.
    single : SingleMatch
        The best training material alone.
    from_start : int or None
        Index in ``starts`` of the optimisation that won, None when a training material
        alone was best.
    starts : list of dict
        Per start: ``x0``, ``x``, ``objective``, ``n_evaluations``, ``message``.
    image : ndarray float32 (H, W, 3)
        The blend at ``x`` (full frame, before the exposure).
    names : list of str
    loss, prior, exposure_free, downsample, n_pixels, time_s
        The settings, masked pixels used and the wall time (the basis' images read
        before the call are not re-read; ``time_read_s`` is what reading took).
    """

    x: np.ndarray
    weights: np.ndarray
    error: float
    rel_mse: float
    exposure: float
    variance: float
    objective: float
    single: SingleMatch
    from_start: object
    starts: list
    image: np.ndarray
    names: list
    loss: str
    prior: float
    exposure_free: bool
    downsample: int
    n_pixels: int
    time_s: float
    time_read_s: float = 0.0
    extra: dict = field(default_factory=dict)

    def __repr__(self):  # short: the image and the starts are attributes, not the summary
        fields = ", ".join(
            f"{k}={getattr(self, k)!r}"
            for k in ("error", "rel_mse", "exposure", "variance", "loss")
        )
        x = ", ".join(f"{v:.4g}" for v in np.asarray(self.x).ravel())
        top = ", ".join(f"{n}:{w:.3g}" for n, w in self.top_weights(4))
        return f"MatchResult(x=[{x}], {fields}, top weights {top}, time_s={self.time_s:.3g})"

    def to_dict(self, manifold=None):
        """JSON-ready summary (no image)."""
        out = {
            "x": self.x.tolist(),
            "error": self.error,
            "loss": self.loss,
            "rel_mse": self.rel_mse,
            "exposure": self.exposure,
            "exposure_free": self.exposure_free,
            "variance": self.variance,
            "prior": self.prior,
            "objective": self.objective,
            "top_weights": self.top_weights(10),
            "weights": dict(zip(self.names, self.weights.tolist())),
            "single": {
                "name": self.single.name,
                "error": self.single.error,
                "exposure": self.single.exposure,
            },
            "from_start": self.from_start,
            "starts": [
                {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in s.items()}
                for s in self.starts
            ],
            "downsample": self.downsample,
            "n_pixels": self.n_pixels,
            "time_s": self.time_s,
            "time_read_s": self.time_read_s,
        }
        if manifold is not None:
            out["nearest"] = self.nearest(manifold)
        return out


# ------------------------------------------------------------------- search


def _downsample_factor(resolution, downsample):
    if downsample is not None:
        f = int(downsample)
        if f < 1 or f > min(resolution):
            raise InputError(
                f"`downsample` must be an integer in 1..{min(resolution)}, got {downsample!r}"
            )
        return f
    return max(1, int(np.sqrt(resolution[0] * resolution[1] / SEARCH_PIXELS)))


# -------------------------------------------------------------------- match


def _basis_and_manifold(basis, manifold):
    if not isinstance(basis, Basis):
        basis = Basis.load(basis)
    if basis.p != 1:
        raise InputError(
            f"basis {basis.folder} has {basis.p} targets {basis.targets}: match works on a "
            "basis of one manifold material"
        )
    manifold = basis.check_manifold(manifold)
    missing = [
        n for n, k in zip(manifold.names, basis.material_keys(manifold.names)) if not basis.has(k)
    ]
    if missing:
        raise InputError(
            f"basis {basis.folder} lacks the images of {len(missing)} of the manifold's "
            f"{manifold.n} materials ({', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''}); "
            "match needs every material: render the full basis"
        )
    return basis, manifold


@dataclass(frozen=True)
class MatchSettings:
    """How :func:`match` searches (every field is also a keyword of :func:`match`).

    Attributes
    ----------
    loss : {"rel_mse", "log"}
        Relative MSE of :mod:`metrics`, or MSE of log luminance.
    exposure_free : bool
        Fit the blend's scale in closed form at every evaluation.
    prior : float
        Weight of the GP variance (Eq. 2) added to the error (0: off).
    starts : int
        L-BFGS-B starts: the best single material's latent point, then the best of the
        ``scan`` points, kept ``l / 4`` apart.
    max_iter : int
        L-BFGS-B iterations per start.
    downsample : int, optional
        Box factor of the search image for the log loss (default: about 64x64 pixels);
        the relative MSE is always exact at full resolution.
    scan : int
        Random latent points near the data scored (vectorised) to choose the starts; 0:
        start from the training points nearest to the best single material only.
    """

    loss: str = "rel_mse"
    exposure_free: bool = False
    prior: float = 0.0
    starts: int = 8
    max_iter: int = 100
    downsample: object = None
    scan: int = 8192

    def check(self):
        """Raise :class:`InputError` naming the first setting out of range; returns ``self``."""
        if self.loss not in LOSSES:
            raise InputError(f"`loss` must be one of {LOSSES}, got {self.loss!r}")
        if not (np.isfinite(self.prior) and self.prior >= 0):
            raise InputError(f"`prior` must be a finite number >= 0, got {self.prior!r}")
        if not isinstance(self.starts, (int, np.integer)) or self.starts < 1:
            raise InputError(f"`starts` must be a positive integer, got {self.starts!r}")
        if not isinstance(self.scan, (int, np.integer)) or self.scan < 0:
            raise InputError(f"`scan` must be an integer >= 0, got {self.scan!r}")
        return self


def match(basis, image=None, mask=None, manifold=None, settings=None, **overrides):
    """Find the latent point whose blend (Eq. 13) best matches ``image``.

    Parameters
    ----------
    basis : Basis or str
        A complete one-target basis (every material of the manifold).
    image : array_like (H, W, 3)
        The image to match (``target``, its former name, is read with a ``DeprecationWarning``).
        Linear RGB at the basis' resolution, finite.
    mask : array_like (H, W) or (H, W, C), optional
        Pixel weights in [0, 1] (0: ignored); default all pixels.
    manifold : Manifold or str, optional
        Default: the basis' own (checked against its manifest).
    settings : MatchSettings, optional
        How to search (default: :class:`MatchSettings`' defaults).
    **overrides
        Fields of :class:`MatchSettings` (``loss``, ``exposure_free``, ``prior``, ``starts``,
        ``max_iter``, ``downsample``, ``scan``) replacing those of ``settings``.

    Returns
    -------
    MatchResult

    Raises
    ------
    InputError, MismatchError
        An image of another size or with NaN/Inf pixels, an all-zero mask, a basis with
        several targets, missing images or without its manifold, bad settings.
    """
    t0 = time.perf_counter()
    target = renamed_argument(image, overrides, "target", "image", "match")
    opts = replace(settings or MatchSettings(), **overrides).check()
    basis, manifold = _basis_and_manifold(basis, manifold)
    target = check_target(target, basis.resolution, what="`image`")
    weight = np.ones(target.shape[:2]) if mask is None else check_mask(mask, basis.resolution)
    if opts.exposure_free and not (np.abs(target) * weight[..., None]).any():
        raise InputError(
            "`image` is black wherever `mask` weighs it: an exposure-free match has no "
            "brightness to fit (give an image with light in it, or match without `exposure_free`)"
        )
    f = _downsample_factor(basis.resolution, opts.downsample) if opts.loss == "log" else 1
    t_read = basis.read([BASE] + basis.material_keys(manifold.names))
    full, search = image_error.objectives(
        basis, manifold, target, weight, opts.loss, opts.exposure_free, f
    )
    runs = _search(manifold, search, full, opts, f)
    best, from_start, x = _winner(manifold, full, runs, opts.prior)
    _, w = manifold.weights(x)
    err, _, s = full(w)
    image = compose(basis, basis.material_keys(manifold.names), w)[
        0
    ]  # Eq. 13 (images already read)
    var = max(float(manifold.variance(x)), 0.0)
    return MatchResult(
        x=np.asarray(x, dtype=float),
        weights=w,
        error=float(err),
        rel_mse=masked_rel_mse(s * image, target, weight),
        exposure=float(s),
        variance=var,
        objective=float(err + opts.prior * var),
        single=best,
        from_start=from_start,
        starts=runs,
        image=image,
        names=list(manifold.names),
        loss=opts.loss,
        prior=float(opts.prior),
        exposure_free=bool(opts.exposure_free),
        downsample=f,
        n_pixels=int((weight > 0).sum()),
        time_s=time.perf_counter() - t0,
        time_read_s=t_read,
    )


def _search(manifold, search, full, opts, f):
    """The L-BFGS-B descents of :func:`match` on the ``search`` objective, from the best single
    material and the best scanned points; with ``f > 1`` the best is refined on ``full``.
    """
    prior = opts.prior
    var_train = prior * manifold.variance(manifold.latent)
    bounds = latent.box(manifold)
    # BLAS on one thread: L-BFGS-B's small linear algebra and the scan's products (a few
    # hundred points at a time) are far slower on a thread pool, the more so on a busy machine
    with one_thread():
        best = int(np.argmin(search.singles()[0] + var_train))
        X, scan_err = latent.scan(manifold, search, prior, bounds, opts.scan)
        runs = [
            latent.descend(manifold, search, prior, x0, bounds, opts.max_iter)
            for x0 in latent.start_points(manifold, best, X, scan_err, int(opts.starts))
        ]
        if f > 1:  # refine the best coarse point at full resolution
            i = int(np.argmin([r["objective"] for r in runs]))
            fine = latent.descend(manifold, full, prior, runs[i]["x"], bounds, opts.max_iter)
            runs[i] = {
                **fine,
                "x0": runs[i]["x0"],
                "x_search": runs[i]["x"],
                "n_evaluations": runs[i]["n_evaluations"] + fine["n_evaluations"],
            }
    return runs


def _winner(manifold, full, runs, prior):
    """The best single material, and the winner (an optimised point or a training material
    alone, scored at full resolution): ``(SingleMatch, index of its run or None, x)``.
    """
    var_train = prior * manifold.variance(manifold.latent)
    full_errs, full_scales = full.singles()
    best = int(np.argmin(full_errs + var_train))
    cand = [(full_errs[best] + var_train[best], None, manifold.latent[best].copy())]
    X = np.array([r["x"] for r in runs])
    errs = full.evaluate(manifold.weights(X)[1])[0] + prior * manifold.variance(X)
    cand += [(float(errs[j]), j, r["x"]) for j, r in enumerate(runs)]
    _, from_start, x = min(cand, key=lambda c: c[0])
    single = SingleMatch(
        manifold.names[best], best, float(full_errs[best]), float(full_scales[best])
    )
    return single, from_start, x


def single_material_errors(
    basis, image=None, mask=None, manifold=None, exposure_free=False, **renamed
):
    """Relative MSE (over the mask) of every training material alone against ``image`` (the
    image to match; ``target``, its former name, is read with a ``DeprecationWarning``);
    ``(errors (N,), exposures (N,))``.

    The baseline of a match: the best any one measured material can do.
    """
    target = renamed_argument(image, renamed, "target", "image", "single_material_errors")
    if renamed:
        raise TypeError(f"single_material_errors() got unexpected keywords {sorted(renamed)}")
    basis, manifold = _basis_and_manifold(basis, manifold)
    target = check_target(target, basis.resolution, what="`image`")
    weight = np.ones(target.shape[:2]) if mask is None else check_mask(mask, basis.resolution)
    obj = image_error.objectives(basis, manifold, target, weight, "rel_mse", exposure_free)[0]
    return obj.singles()


__all__ = [
    "match",
    "MatchSettings",
    "MatchResult",
    "SingleMatch",
    "InputError",
    "read_target",
    "read_mask",
    "check_target",
    "check_mask",
    "single_material_errors",
]
