"""Refining a blend to the exact full-GI image of its point (``blend.py --refine``).

With a full-GI basis of one target the refinement is, by default, a *control variate*: one-pass
paths at the point (sampled with the point's own material,
:func:`~.integrators.onepass.render_onepass_gi` with ``point``) give, from the same paths, the
point's ``L2+`` image ``R`` and the blend's model of it, ``Q = sum_i w_i R_i + sum_{i<j} w_i w_j
C_ij`` (the weights and cross terms the blend used), so that

    refined(x) = blend(x) + mean(R - Q)

has the expectation of the point's full-GI render (up to the denoiser's change of the blend's
L2+ with ``l2="denoised"``; exactly with ``l2="raw"``). ``R - Q`` is 0 on every path with two
vertices on the material (the cross terms make the model exact there) and at every training
material, so its noise is that of the three-plus-vertex paths' departure from the quadratic
model: far below that of rendering ``L2+`` itself, and few samples suffice. The correction covers
paths with at most :data:`CV_LEVELS` vertices on the material (the basis's ``levels`` if fewer);
beyond, the blend's model stands: per path, the quadratic model's departure grows about as
``w^(1-k)`` with the ``k`` vertices on the material (``w`` the dominant weight), so a correction
through a few vertices leaves less noise than one through many, while paths through many
vertices carry little light (:func:`~.render_basis.render_basis`'s ``levels``; figures in
docs/benchmarks.md). At a training material (one material, no cross
term) ``R - Q`` is 0 on every path, so nothing is rendered.

Otherwise (an L1- basis; several targets; ``control_variate=False``): a basis gives any latent point's ``L1-``
image exactly (Eq. 13 is affine in the weights: ``base + sum_i w_i touch_i``); what no finite
set of per-material images gives exactly is the light that touched the material twice or more
(``L2+``, second order in the weights). The
refinement renders only that part, at the point itself: ``manifold_path`` with
``component="l2+"`` and every target at its latent point, in independent passes, so that

    refined(x) = blend_L1(x) + rest(x)

is an unbiased estimate of the full-GI render of ``x`` (the L1- blend's own noise is the
basis's). The passes also estimate the refinement's noise: the per-pixel standard error
of their mean, reported as a relative MSE (the metric of :mod:`mitsuba_manifold.imaging.metrics`).
:func:`refine_passes` yields the estimate after each pass (progressive: a viewer shows them
as they come); :func:`refine` returns the last.
"""

import collections
import contextlib
import os
import threading
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Optional, Union

import numpy as np

from ..._util.interrupts import StopRequest
from ..._util.moved import renamed_argument, renamed_field
from ...basis.blend import blend, latent_points
from ...errors import InputError, MitsubaManifoldError
from ...imaging.metrics import REL_EPS, pass_standard_error
from ..integrators.onepass import POINT
from ..integrators.proxy import forget_point
from ..scene import scenes

if TYPE_CHECKING:
    from collections.abc import Iterator
    from typing import Any


@dataclass
class Refined:
    """A refined blend: ``image = l1 + rest``; ``pixel_se`` (H, W, 3) the standard error of
    ``rest`` per pixel (from the passes; NaN after one pass); ``noise_rel_mse`` its mean of
    ``se^2 / (scale^2 + eps)``; ``spp`` and ``passes`` rendered so far, in ``seconds``.

    ``scale`` is the basis's own blend of the point (full GI where it holds it, else L1-), not
    ``image``: a firefly of the refinement inflates ``image`` where it is, so relative to it
    the noise would look small exactly where it is largest.
    """

    image: np.ndarray
    l1: np.ndarray
    rest: np.ndarray
    pixel_se: np.ndarray
    noise_rel_mse: float
    spp: int
    passes: int
    seconds: float
    scale: np.ndarray = None
    method: str = "l2+"

    def rel_mse(self, other) -> float:
        """Mean ``(other - image)^2 / (scale^2 + eps)``: ``other`` against the refinement, on the
        refinement's noise scale.
        """
        scale = self.image if self.scale is None else self.scale
        d = np.asarray(other, np.float64) - self.image
        return float(np.mean(d * d / (np.asarray(scale, np.float64) ** 2 + REL_EPS)))

    def summary(self) -> str:
        """One line: what was rendered and its estimated noise."""
        noise = "n/a (one pass)" if self.passes < 2 else f"{self.noise_rel_mse:.3g}"
        what = (
            "the blend's L2+ corrected at the point (control variate)"
            if self.method == CONTROL_VARIATE
            else "L2+ rendered at the point"
        )
        if self.passes == 0:
            return (
                f"refined: nothing to render, the blend is exact at a training material (the control "
                f"variate's correction is 0 on every path), {self.seconds:.2f} s"
            )
        return (
            f"refined: {what} with {self.spp} spp in {self.passes} passes, "
            f"{self.seconds:.2f} s; estimated noise of the refinement (rel. MSE, on the blend's scale) {noise}"
        )


#: :class:`Refined` ``method`` of the control variate (a full-GI basis of one target).
CONTROL_VARIATE = "control variate"
#: Most vertices on the material of the paths that the control variate corrects (the module).
CV_LEVELS = 5


def _pass_plan(spp, passes) -> list:
    spp, passes = int(spp), int(passes)
    if spp < 1:
        raise InputError(f"`spp` must be >= 1, got {spp}")
    if not 1 <= passes <= spp:
        raise InputError(f"`passes` must be in 1..spp ({spp}), got {passes}")
    return [spp // passes + (1 if k < spp % passes else 0) for k in range(passes)]


class _SceneCache:
    """The scene of the last refinement, kept for the next one: the explorer refines on every
    release, and loading the scene with its table at the point is a large share of a short
    refinement. Keyed by everything the scene is loaded
    with but the point, and by the scene's and manifold's files (size and time: a manifold fitted
    again is loaded again; not the files the XML references, nor the tables). A refinement takes
    the scene out while it renders (one running beside it loads its own) and puts it back when it
    ends or is stopped, not when it failed. One entry, locked.
    """

    def __init__(self) -> None:
        self.key, self.value, self.lock = None, None, threading.Lock()

    @contextlib.contextmanager
    def take(self, basis, scene, manifold_path, database, x) -> "Iterator[Any]":
        """The :class:`~.scenes.LoadedScene` of ``basis``'s scene (or ``scene``): the kept one (its
        materials where the last refinement put them; its variant activated, as loading it does),
        or one loaded with its materials at ``x``.
        """
        m = basis.manifest
        path, manifold_path = scene or m.scene, manifold_path or m.manifold
        key = self._key(basis, path, manifold_path, database)
        with self.lock:
            loaded = self.value if key is not None and self.key == key else None
            self.key, self.value = None, None
        if loaded is None:
            loaded = scenes.load_scene(
                path,
                manifold_path,
                None,
                scenes.scene_resolution(m),
                m.max_depth,
                x[0],
                m.variant,
                database,
                sensor=int(basis.sensor),
            )
        else:
            scenes.use_variant(m.variant)
        keep = False
        try:
            yield loaded
            keep = True
        except (GeneratorExit, KeyboardInterrupt):  # closed early or stopped between passes: whole
            keep = True
            raise
        finally:
            if keep and key is not None:
                with self.lock:
                    self.key, self.value = key, loaded

    def clear(self) -> None:
        with self.lock:
            self.key, self.value = None, None

    @staticmethod
    def _key(basis, path, manifold_path, database) -> "Optional[tuple]":
        """What the scene is loaded with but the point; None where a file cannot be read (nothing
        is kept then, and loading says what is wrong).
        """
        m = basis.manifest
        try:
            files = tuple(
                (os.path.abspath(f), os.stat(f).st_size, os.stat(f).st_mtime_ns)
                for f in (scenes.scene_path(path), manifold_path)
            )
        except (OSError, MitsubaManifoldError):
            return None
        return (
            files,
            tuple(basis.resolution),
            m.max_depth,
            m.variant,
            tuple(basis.targets),
            database,
        )


_SCENES = _SceneCache()


def forget_kept(scene=True) -> None:
    """Drop what a refinement keeps for the next: the last point's tables and, with ``scene``, the
    loaded scene (a benchmark times a refinement at a new point, or one starting from nothing).
    """
    forget_point()
    if scene:
        _SCENES.clear()


def _rest_integrator(basis, paths):
    import mitsuba as mi

    target = "all" if basis.p == 1 else ",".join(basis.targets)
    return mi.load_dict(
        {"type": "manifold_path", "component": "l2+", "target": target, **paths.path_properties()}
    )


@renamed_field("manifold_path", "manifold_file")
@dataclass(frozen=True)
class RefineRequest:
    """How a refinement renders (:func:`refine_passes`; every field has the default of the keyword).

    Attributes
    ----------
    spp, passes, seed : int
        Samples per pixel of the ``L2+`` render in all, cut into ``passes`` independent passes
        (at least 2 to estimate the noise).
    database : str, optional
        Folder of the manifold's tables if it moved.
    prune : float, optional
        The blend's pruning (default: the blend's); the rendered material prunes as
        ``manifold_brdf`` does at the same point.
    scene, manifold_file : str, optional
        The scene and manifold files to render (default: the manifest's; the explorer passes
        the ones it resolved, e.g. ``--scene``).
    l2 : {"denoised", "raw"}
        The blend's ``L2+`` (:func:`~mitsuba_manifold.basis.blend.blend`) that the control variate
        corrects; ``"raw"`` makes the refinement unbiased, ``"denoised"`` keeps the denoiser's change.
    control_variate : {"auto", True, False}
        Use the control variate where the basis allows it (a full-GI basis of one target; ``"auto"``
        and ``True``), or render the ``L2+`` at the point (``False``; the control variate needs
        fewer samples for the same error, docs/benchmarks.md).
    """

    spp: int = 64
    passes: int = 4
    seed: int = 0
    database: Optional[str] = None
    prune: Optional[float] = None
    scene: Optional[str] = None
    manifold_file: Optional[str] = None
    l2: str = "denoised"
    control_variate: Union[str, bool] = "auto"


def refine_passes(
    basis, manifold, x=None, request=None, *, stop=None, blend_image=None, **settings
) -> "Iterator[Refined]":
    """Yield a :class:`Refined` estimate after each of ``request.passes`` passes (``spp`` in all):
    the ``L1-`` blend plus the ``L2+`` rendered at the point, or with ``control_variate`` and a
    full-GI basis of one target the control variate of the module's docstring.

    Parameters
    ----------
    basis : Basis
        Its manifest names the scene, the view (``sensor``), the size and the path depth; the
        ``L1-`` part is its blend (:func:`~mitsuba_manifold.basis.blend.blend`, ``component="l1"``).
    manifold : Manifold
    x : array_like
        The point (q,), or (p, q) for a basis of several targets (as :func:`blend`).
    request : RefineRequest, optional
        How to render; ``settings`` (its fields as keywords) replace its fields.
    stop : StopRequest, optional
        Checked after each pass (Ctrl-C ends the refinement there: ``KeyboardInterrupt``).
    blend_image : ndarray, optional
        The basis's blend of the point (:class:`Refined` ``scale``), when the caller has it
        (the explorer does); default: blended here (with ``l2``). The control variate corrects it.
    """
    import mitsuba as mi

    if "manifold_path" in settings:
        settings["manifold_file"] = renamed_argument(
            None, settings, "manifold_path", "manifold_file", "refine_passes"
        )
    r = replace(request or RefineRequest(), **settings)
    plan = _pass_plan(r.spp, r.passes)
    kw = {} if r.prune is None else {"prune": r.prune}
    if r.control_variate not in ("auto", True, False):
        raise InputError(
            f"`control_variate` must be 'auto', True or False, got {r.control_variate!r}"
        )
    if r.control_variate and "l2+" in basis.components and basis.p == 1:
        yield from _control_variate(basis, manifold, x, plan, r, stop, blend_image, kw)
        return
    l1, _ = blend(basis, manifold, x=x, component="l1", **kw)
    scale = blend_image
    if scale is None:
        scale = blend(basis, manifold, x=x, **kw)[0] if "l2+" in basis.components else l1
    points = latent_points(basis, manifold, x)
    with _SCENES.take(basis, r.scene, r.manifold_file, r.database, points) as loaded:
        scenes.set_points(loaded.targets, points, basis.targets)
        integrator = _rest_integrator(basis, loaded.integrator)

        def rest(n, pass_seed) -> "np.ndarray":
            return np.array(
                mi.render(
                    loaded.scene,
                    integrator=integrator,
                    spp=n,
                    sensor=int(basis.sensor),
                    seed=pass_seed,
                ),
                np.float64,
            )[..., :3]

        yield from _progressive(plan, r.seed, stop, integrator, rest, l1, scale, "l2+")


def _progressive(plan, seed, stop, integrator, render, start, scale, method):
    """Yield the :class:`Refined` ``start + mean`` of ``render(spp, seed)`` after each pass of
    ``plan`` (independent seeds); ``stop`` (or Ctrl-C) ends it after a pass.
    """
    t0, total, total2, done = time.perf_counter(), 0.0, 0.0, 0
    own = stop is None
    stop = stop or StopRequest()
    with stop if own else contextlib.nullcontext():
        for k, n in enumerate(plan):
            img = render(n, (int(seed) + k * 0x9E3779B9) & 0xFFFFFFFF)
            total, total2, done = total + n * img, total2 + n * img * img, done + n
            if integrator.should_stop():
                stop.requested = True
            stop.check()
            yield _estimate(
                start, total, total2, done, k + 1, time.perf_counter() - t0, scale, method
            )


def _control_variate(basis, manifold, x, plan, request, stop, blend_image, kw):
    """:func:`refine_passes` with a full-GI basis: ``blend + mean(R - Q)`` (the module) of
    ``request``, a :class:`RefineRequest`.
    """
    import mitsuba as mi

    shown, info = blend(basis, manifold, x=x, component="full", l2=request.l2, **kw)
    base = shown if blend_image is None else np.asarray(blend_image, np.float32)
    by_key = {basis.key([n]): n for n in manifold.names}
    summed = info.plan
    names, w = [by_key[k] for k in summed.keys], np.asarray(summed.image_weights, np.float64)
    rows, prods = summed.cross if summed.cross is not None else ((), ())
    row_pair = {r: p for p, r in basis.cross_terms()[0].items()}
    pairs = [row_pair[int(r)] for r in rows]
    if len(names) == 1 and not pairs:  # a training material: R = Q on every path
        zero = np.zeros_like(base, np.float32)
        yield Refined(base, base, zero, zero, 0.0, 0, 0, 0.0, base, CONTROL_VARIATE)
        return
    m = basis.manifest
    # the scene's own material is not evaluated: on the target the paths use the proxy of the
    # point's weights (the point's column, onepass), so a cached scene is not moved to the point
    points = latent_points(basis, manifold, x)
    with _SCENES.take(
        basis, request.scene, request.manifold_file, request.database, points
    ) as loaded:
        integrator = mi.load_dict(
            {"type": "manifold_path", "component": "l1", **loaded.integrator.path_properties()}
        )

        def correction(n, pass_seed):  # R - Q from one pass's paths
            r = integrator.render_onepass_gi(
                loaded.scene,
                materials=names,
                spp=n,
                sensor=int(basis.sensor),
                seed=pass_seed,
                levels=min(int(m.levels or 5), CV_LEVELS),
                pairs=pairs,
                point=w,
                touch=False,
            )
            q = sum(wi * r.rest[name].astype(np.float64) for wi, name in zip(w, names))
            q = q + sum(float(pr) * r.cross[p] for pr, p in zip(prods, pairs))
            return r.rest[POINT].astype(np.float64) - q

        yield from _progressive(
            plan, request.seed, stop, integrator, correction, base, base, CONTROL_VARIATE
        )


def _estimate(l1, total, total2, done, passes, seconds, scale=None, method="l2+") -> "Refined":
    """The refined image from the spp-weighted sums of the pass images and their squares
    (``scale``: of :class:`Refined`; default the refined image).
    """
    rest = total / done
    se = pass_standard_error(total, total2, done, passes)
    image = (l1 + rest).astype(np.float32)
    ref = np.asarray(image if scale is None else scale, np.float64)
    noise = float(np.mean(se**2 / (ref**2 + REL_EPS))) if passes > 1 else float("nan")
    return Refined(
        image,
        l1,
        rest.astype(np.float32),
        se.astype(np.float32),
        noise,
        int(done),
        passes,
        seconds,
        None if scale is None else np.asarray(scale, np.float32),
        method,
    )


def refine(basis, manifold, x=None, request=None, **settings) -> "Refined | None":
    """The last estimate of :func:`refine_passes` (all ``spp`` samples): a :class:`Refined`."""
    last = collections.deque(refine_passes(basis, manifold, x, request, **settings), maxlen=1)
    return last[0] if last else None
