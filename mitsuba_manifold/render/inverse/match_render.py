"""Inverse rendering with full GI and no basis: optimise the latent point ``x`` (and, optionally,
an exposure) so that Mitsuba renders of one or more scenes / sensors match target images.

The loop is the one a Mitsuba user writes (``mi.traverse``, ``dr.enable_grad``, ``mi.render``
with ``prb``, ``dr.backward``, ``mi.ad.Adam``), on the differentiable ``x`` of ``manifold_brdf``
(:mod:`.ad`). Every ``manifold_brdf`` of every scene shares one ``x`` (one material). The
loss is the relative MSE of :func:`imaging.metrics.rel_mse` over the masks, summed over the views.

Starts (:mod:`.scan`): every training material rendered alone at ``scan_spp`` (two
independent renders), any blend's error estimated as a quadratic form in its weights from those
renders, free of their noise (the error of one noisy render ranks glossy materials last), L-BFGS-B
on it, and the best candidates checked with true renders; and the basis match's point when a basis
is given. Each start runs ``iterations`` Adam steps (learning rate decayed to a tenth); the start
itself, its last iterate, its iterate of lowest loss and the mean of its second half's iterates are
re-rendered at ``eval_spp`` with another seed, as are the scan's best few training materials alone
(the best of which is ``single``), and the best becomes the result.
``x`` is not identifiable from one image (several points give near-identical weights):
report the weights and the image error, not the error in ``x``.
"""

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..._util.moved import image_field, renamed_argument
from ...basis.inverse.match import LatentMatch
from ...errors import InputError
from ...imaging.metrics import REL_EPS
from . import scan

#: Mitsuba's differentiable integrators the loop can use (``integrator``; each takes max_depth and rr_depth).
INTEGRATORS = ("prb", "prb_basic", "prbvolpath", "direct_projective", "prb_projective")

#: Training materials first in the scan's ranking re-rendered at ``eval_spp``: the best single material.
SINGLES_CHECKED = 3


@image_field
@dataclass
class View:
    """One view to match: a scene file, the sensor index in it, the image to match (array
    ``(H, W, 3)`` linear, or a file: EXR, or 8-bit PNG/JPEG), and an optional mask (array or
    file). ``target``, the former name of ``image``, still works (``DeprecationWarning``).
    """

    scene: str
    image: object
    mask: object = None
    sensor: int = 0


@dataclass
class MatchRenderOptions:
    """Settings of :func:`match_render` (``lr``: Adam's step in latent units; None: a third of a
    typical step of the data, :func:`.ad.typical_step`, since the starts are the scan's checked
    points, already near: Adam's steps are about ``lr`` long however small the noisy gradient,
    and a full typical step walked away from good starts). ``scan_spp``: samples per training
    material in the scan, split over two renders (:mod:`.scan`).
    """

    iterations: int = 30
    spp: int = 8
    eval_spp: int = 64
    scan_spp: int = 16
    starts: int = 3
    lr: float = None
    exposure: bool = False  # fit a brightness scale (least squares at every step)
    max_depth: int = 4
    integrator: str = "prb"
    seed: int = 0
    progress: bool = True
    plot: str = None  # path of the convergence plot (PNG), or None


@dataclass
class MatchRenderResult(LatentMatch):
    """The best point: ``x``, full weights ``w`` over ``names``, ``error`` (relative MSE over the
    masks, mean over the views, at ``eval_spp``), per-view ``errors``, ``exposure``, the renders
    at the best point ``images``, ``single`` (best training material: name, error), ``starts``
    (one dict per start), ``history`` (loss per iteration per start), timings.
    """

    x: np.ndarray
    w: np.ndarray
    names: list
    error: float
    errors: list
    exposure: float
    images: list
    single: dict
    starts: list
    history: list
    time_s: float
    time_per_iteration_s: float
    plot: str = None
    extra: dict = field(default_factory=dict)

    @property
    def weights(self):
        """``w`` (:class:`~mitsuba_manifold.basis.inverse.match.LatentMatch`'s name for them)."""
        return self.w

    def to_dict(self, manifold=None):
        """JSON-ready summary (no image)."""
        out = {
            "x": self.x.tolist(),
            "error": self.error,
            "errors": self.errors,
            "exposure": self.exposure,
            "weights": dict(zip(self.names, self.w.tolist())),
            "top_weights": self.top_weights(10),
            "single": self.single,
            "starts": self.starts,
            "history": self.history,
            "time_s": self.time_s,
            "time_per_iteration_s": self.time_per_iteration_s,
            "plot": self.plot,
            **self.extra,
        }
        if manifold is not None:
            out["nearest"] = self.nearest(manifold)
        return out


def _targets(views):
    """Targets (float32 (H, W, 3)) and per-pixel loss weights ``mask / (t^2 + eps)`` normalised
    to mean 1 over the mask (so that the loss is :func:`rel_mse` over the mask).
    """
    from ...basis.inverse import match as mt

    out = []
    for v in views:
        if isinstance(v.image, str):
            target, clipped = mt.read_target(v.image)
        else:
            target = np.asarray(v.image, dtype=np.float32)
            clipped = np.zeros(target.shape[:2], dtype=bool)
        shape = np.shape(target) + (0, 0)
        target = mt.check_target(
            target, (shape[1], shape[0]), what=f"image to match of {v.scene}"
        ).astype(np.float32)
        mask = np.ones(target.shape[:2])
        if v.mask is not None:
            mask = (
                mt.read_mask(v.mask)
                if isinstance(v.mask, str)
                else np.asarray(v.mask, dtype=np.float64)
            )
            if mask.shape != target.shape[:2]:
                raise InputError(
                    f"`mask` of {v.scene} has shape {mask.shape}, the target {target.shape[:2]}"
                )
        mask = mask * ~clipped
        if mask.sum() <= 0:
            raise InputError(f"`mask` of {v.scene} selects no pixel")
        weight = mask[..., None] / (np.square(target.astype(np.float64)) + REL_EPS)
        out.append((target, weight / (mask.sum() * 3.0)))
    return out


class _Problem:
    """The loaded scenes, their ``x`` parameters and the loss of a set of views."""

    def __init__(self, views, manifold_path, opts, database=None):
        import mitsuba as mi

        from ..integrators import manifold_bsdfs
        from ..scene import scenes

        self.mi, self.opts, self.views = mi, opts, views
        self.data = _targets(views)
        self.loaded, self.params, self.keys = {}, {}, {}
        for v, (target, _) in zip(views, self.data):
            if v.scene in self.loaded:
                continue
            size = (target.shape[1], target.shape[0])
            ls = scenes.load_scene(
                v.scene, manifold_path, opts.spp, size, opts.max_depth, database=database
            )
            ids = {b.id() for b in manifold_bsdfs(ls.scene)}
            params = mi.traverse(ls.scene)
            self.loaded[v.scene], self.params[v.scene] = ls, params
            self.keys[v.scene] = [k for k in params.keys() if k.endswith(".x") and k[:-2] in ids]
            if not self.keys[v.scene]:
                raise InputError(f"`scene` {v.scene} has no manifold_brdf with a latent point x")
        self.manifold = next(iter(self.loaded.values())).targets[0].manifold
        self.integrator = mi.load_dict(
            {
                "type": opts.integrator,
                "max_depth": opts.max_depth,
                "rr_depth": max(opts.max_depth, 1) + 1,
            }
        )
        self.primal = mi.load_dict({"type": "path", "max_depth": opts.max_depth})
        self.tensors = [(mi.TensorXf(t), mi.TensorXf(w.astype(np.float32))) for t, w in self.data]

    def set_x(self, x):
        """Every manifold material at ``x`` (a grad-enabled ``mi.Float``, or NumPy: no gradient)."""
        mi = self.mi
        for scene, params in self.params.items():
            for k in self.keys[scene]:
                params[k] = (
                    x if isinstance(x, mi.Float) else mi.Float(np.asarray(x, dtype=np.float32))
                )
            params.update()

    def loss(self, exposure, spp, seed, differentiable=True):
        """``(loss, images, exposure)``: the mean over the views of the weighted squared error (a
        Dr.Jit Float) of ``exposure * image``; ``exposure`` None: the least-squares scale of the
        images (detached: at the optimal scale, the gradient in x is the one at fixed scale).
        """
        import drjit as dr

        mi, images = self.mi, []
        for i, v in enumerate(self.views):
            integ = self.integrator if differentiable else self.primal
            images.append(
                mi.render(
                    self.loaded[v.scene].scene,
                    self.params[v.scene] if differentiable else None,
                    integrator=integ,
                    sensor=v.sensor,
                    spp=spp,
                    seed=seed + 7919 * i,
                    seed_grad=seed + 7919 * i + 104729,
                )
            )
        if exposure is None:
            num = sum(
                dr.sum(dr.detach(im) * t * w, axis=None) for im, (t, w) in zip(images, self.tensors)
            )
            den = sum(
                dr.sum(dr.square(dr.detach(im)) * w, axis=None)
                for im, (t, w) in zip(images, self.tensors)
            )
            exposure = mi.Float(
                float(np.array(num).ravel()[0]) / max(float(np.array(den).ravel()[0]), 1e-30)
            )
        total = sum(
            dr.sum(dr.square(exposure * im - t) * w, axis=None)
            for im, (t, w) in zip(images, self.tensors)
        )
        return total / len(self.views), images, float(np.array(exposure).ravel()[0])

    def evaluate(self, x, exposure, spp, seed):
        """Primal ``(error, images as NumPy, exposure)`` at ``x`` with today's combined table (no
        gradient); ``exposure`` None: fitted.
        """
        import drjit as dr

        self.set_x(np.asarray(x))
        with dr.suspend_grad():
            loss, images, e = self.loss(
                None if exposure is None else self.mi.Float(exposure),
                spp,
                seed,
                differentiable=False,
            )
        return float(np.array(loss).ravel()[0]), [np.array(im) for im in images], e


def _descend(problem, x0, opts, lr, bar):
    """Adam from ``x0`` (learning rate decayed to a tenth): ``(history, x_last, x_best, x_mean)``,
    ``x_mean`` the mean of the second half's iterates (the noisy gradients' random walk averaged).
    """
    import drjit as dr

    mi = problem.mi
    opt = mi.ad.Adam(lr=lr)
    opt["x"] = mi.Float(np.asarray(x0, dtype=np.float32))
    history, best, tail = [], (np.inf, np.asarray(x0, dtype=np.float64)), []
    for it in range(opts.iterations):
        opt.set_learning_rate(lr * (0.1 + 0.9 * 0.5 * (1 + np.cos(np.pi * it / opts.iterations))))
        problem.set_x(opt["x"])
        loss, _, _ = problem.loss(
            None if opts.exposure else mi.Float(1.0), opts.spp, opts.seed + 1000 * (it + 1)
        )
        dr.backward(loss)
        value = float(np.array(loss).ravel()[0])
        history.append(value)
        if value < best[0]:
            best = (value, np.array(opt["x"], dtype=np.float64))
        opt.step()
        if 2 * (it + 1) > opts.iterations:
            tail.append(np.array(opt["x"], dtype=np.float64))
        if bar is not None:
            bar.set_postfix(loss=f"{value:.4g}")
            bar.update(1)
    return history, np.array(opt["x"], dtype=np.float64), best[1], np.mean(tail, axis=0)


def _plot(history, path, labels):
    from ...imaging.plots import finish, subplots

    fig, ax = subplots(figsize=(6, 4))
    for h, lab in zip(history, labels):
        ax.semilogy(np.arange(1, len(h) + 1), h, marker=".", label=lab)
    ax.set_xlabel("Adam iteration")
    ax.set_ylabel("loss (relative MSE, training spp)")
    return finish(fig, ax, path)


def match_render(views, manifold=None, options=None, basis=None, database=None, **renamed):
    """Optimise ``x`` so that renders of ``views`` (:class:`View`) match their images.

    Parameters
    ----------
    views : list of View
    manifold : str
        The manifold file every ``manifold_brdf`` of the scenes uses (``manifold_path``, its
        former name, is read with a ``DeprecationWarning``).
    options : MatchRenderOptions, optional
    basis : basis folder path or :class:`basis.folder.Basis`, optional
        Also start from the basis match of the first view's image.
    database : str, optional
        Folder of the manifold's tables (as :func:`.scenes.load_scene`).

    Returns
    -------
    MatchRenderResult
    """
    from ..plugin import ad

    manifold_path = renamed_argument(manifold, renamed, "manifold_path", "manifold", "match_render")
    if renamed:
        raise TypeError(f"match_render() got unexpected keywords {sorted(renamed)}")
    opts = options or MatchRenderOptions()
    check_options(opts)
    views = check_views(views)
    t0 = time.perf_counter()
    problem = _Problem(views, manifold_path, opts, database)
    m = problem.manifold
    lr = opts.lr if opts.lr is not None else ad.typical_step(m.latent) / 3.0
    found = scan.scan(problem, opts, max(1, opts.eval_spp // 4))
    ranked, starts = found["ranked"], found["starts"]
    if basis is not None:
        x_b = _basis_start(basis, m, problem.data[0][0])
        starts.insert(0, ("basis match", scan.adam_start(m, x_b, ranked), x_b))
    from tqdm import tqdm

    bar = tqdm(
        total=len(starts) * opts.iterations,
        desc="match-render",
        disable=not opts.progress,
        leave=False,
    )
    runs, t_iter = [], time.perf_counter()
    e_fix = None if opts.exposure else 1.0

    def candidate(kind, x0, which, x, history):
        err, images, e = problem.evaluate(x, e_fix, opts.eval_spp, opts.seed + 55)
        runs.append(
            {
                "start": kind,
                "x0": np.asarray(x0).tolist(),
                "iterate": which,
                "x": np.asarray(x).tolist(),
                "error": err,
                "exposure": e,
                "images": images,
                "history": history,
            }
        )

    for kind, x0, x_start in starts:
        history, x_last, x_best, x_mean = _descend(problem, x0, opts, lr, bar)
        candidate(kind, x0, "start", x_start, history)  # the scan's point itself stays a candidate
        for which, x in (
            ("last", x_last),
            ("lowest loss", x_best),
            ("mean of the second half", x_mean),
        ):
            candidate(kind, x0, which, x, history)
    bar.close()
    t_iter = (time.perf_counter() - t_iter) / max(1, len(starts) * opts.iterations)
    singles = []
    for _, i in ranked[
        :SINGLES_CHECKED
    ]:  # the best single material: of the scan's first few, at eval_spp
        candidate("material " + m.names[i], m.latent[i], "none", m.latent[i], [])
        singles.append((runs[-1]["error"], i, runs[-1]["exposure"]))
    s_err, single_i, s_e = min(singles)
    best = min(runs, key=lambda r: r["error"])
    x = np.asarray(best["x"])
    _, w = m.weights(x)
    per_view = _per_view_errors(best["images"], problem.data, best["exposure"])
    history = [r["history"] for r in runs if r["iterate"] == "last"]
    extra = {
        "from_start": None if best["iterate"] == "none" else best["start"],
        "from_iterate": best["iterate"],
        "scan": {"time_s": found["time_s"], "candidates": found["candidates"]},
    }
    plot = _plot(history, opts.plot, [s[0] for s in starts]) if opts.plot else None
    return MatchRenderResult(
        x=x,
        w=np.asarray(w),
        names=list(m.names),
        error=float(np.mean(per_view)),
        errors=per_view,
        exposure=best["exposure"],
        images=[best["exposure"] * im for im in best["images"]],
        single={"name": m.names[single_i], "error": s_err, "exposure": s_e},
        starts=[{k: v for k, v in r.items() if k not in ("images", "history")} for r in runs],
        history=history,
        time_s=time.perf_counter() - t0,
        time_per_iteration_s=t_iter,
        plot=plot,
        extra=extra,
    )


def check_options(opts):
    """Every setting of ``opts`` usable, or an :class:`InputError` naming it (before any work)."""
    for name in ("iterations", "spp", "eval_spp", "scan_spp", "starts", "max_depth"):
        if int(getattr(opts, name)) < 1:
            raise InputError(f"`{name}` must be >= 1, got {getattr(opts, name)}")
    number = isinstance(opts.lr, (int, float, np.integer, np.floating)) and not isinstance(
        opts.lr, bool
    )
    if opts.lr is not None and not (number and math.isfinite(opts.lr) and opts.lr > 0):
        raise InputError(f"`lr` must be a finite number > 0, got {opts.lr}")
    if isinstance(opts.seed, bool) or not isinstance(opts.seed, (int, np.integer)) or opts.seed < 0:
        raise InputError(f"`seed` must be an integer >= 0, got {opts.seed!r}")
    if opts.integrator not in INTEGRATORS:
        raise InputError(
            f"`integrator` {opts.integrator!r} is not one of the differentiable integrators this "
            f"match uses: {', '.join(INTEGRATORS)}"
        )


def check_views(views):
    """``views`` with each scene resolved (a scene XML or a shipped scene's name) and its sensor checked."""
    from ..jobs.render_basis import count_sensors
    from ..scene import scenes

    if not views:
        raise InputError("`views` is empty: give at least one scene and target")
    out = []
    for v in views:
        path = scenes.check_scene("`scene`", v.scene)
        n = count_sensors(path)
        if (
            isinstance(v.sensor, bool)
            or not isinstance(v.sensor, (int, np.integer))
            or not 0 <= v.sensor < n
        ):
            raise InputError(
                f"`sensor` must be an integer from 0 to {n - 1}: {path} has {n} sensor(s), "
                f"got {v.sensor!r}"
            )
        out.append(dataclasses.replace(v, scene=path, sensor=int(v.sensor)))
    return out


def _per_view_errors(images, data, exposure):
    """Relative MSE over each view's mask."""
    return [float(np.sum(np.square(exposure * im - t) * w)) for im, (t, w) in zip(images, data)]


def _basis_start(basis, manifold, target):
    """The basis match's point for ``target`` (a start)."""
    from ...basis.folder import Basis
    from ...basis.inverse import match as mt

    if isinstance(basis, str):
        basis = Basis.load(basis, manifold=manifold)
    return np.asarray(mt.match(basis, target, manifold=manifold).x, dtype=np.float64)
