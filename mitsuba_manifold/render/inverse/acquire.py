"""Acquire a material from one or more photographs of a known object under known light.

Each photo's scene (Mitsuba XML: camera, emitters, the object with a ``manifold_brdf``) is
loaded once and every training material's image in it is rendered in one pass
(:meth:`~.integrators.path.ManifoldPathIntegrator.render_onepass`: the paths are traced once,
each material's image is a product of the recorded vertices with its table). With one object
that does not see itself these L1- images are the whole image, and the image of any weights is
``base + sum_i w_i I_i`` exactly, so the weights are found by the convex programme of
:mod:`mitsuba_manifold.basis.inverse.acquisition` (light that scatters twice off the material, where the
object sees itself, is left out of the model). The images can be kept in ``basis_cache`` for the
next photo of the same scene.

The report says which outgoing directions and which incidences of the scene's point-like
lights the masked pixels show (:func:`coverage`, from rays through the pixel centres), how much
the near-equally good answers differ (:func:`~mitsuba_manifold.basis.inverse.acquisition.spread`), and
warns where the photos do not determine the material.
"""

from __future__ import annotations

import os
import time
import zipfile
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ..._util.cache import file_hash, key_hash
from ..._util.moved import image_field, renamed_argument, warn_renamed
from ...basis.inverse import acquisition as aq
from ...data.sources import BUILTIN_PREFIX
from ...errors import InputError
from ...manifold.file.shipped import SHIPPED, resolve_manifold

if TYPE_CHECKING:
    from typing import Any


#: The part of a pixel the material must bring (against what reaches it without the material)
#: for the default mask to keep it.
MASK_SHARE = 0.5
#: Coverage warnings: smallest half-angle (degrees) under which the specular peak counts as seen,
#: and the largest outgoing elevation (degrees) under which grazing views count as seen.
PEAK_SEEN_DEG = 5.0
GRAZING_DEG = 70.0


@image_field
@dataclass
class Photo:
    """One photograph: its scene (XML file or a shipped scene's name), the image to match (array
    ``(H, W, 3)`` linear, or a file: linear EXR, or PNG/JPEG in sRGB), an optional mask (array or
    file; default: the pixels where the material brings most of the light) and the sensor index.
    ``target``, the former name of ``image``, still works (``DeprecationWarning``).
    """

    scene: str
    image: object
    mask: object = None
    sensor: int = 0


class Rendered(NamedTuple):
    """What one photo's scene shows: the base image and every training material's image."""

    base: np.ndarray  # (H, W, 3)
    images: np.ndarray  # (N, H, W, 3)
    seconds: float
    cached: bool


class AcquireOutput(NamedTuple):
    """:func:`acquire`: the result (written with its own ``write``) and the images per photo."""

    result: aq.Acquisition
    photos: list  # the image to match (H, W, 3), linear, per photo
    masks: list  # (H, W) per photo
    renders: list  # the acquired material, per photo (none with render_spp 0)
    singles: list  # the best single training material, per photo (none with render_spp 0)

    @property
    def targets(self) -> list:
        """The former name of :attr:`photos`."""
        warn_renamed("AcquireOutput.targets", "AcquireOutput.photos")
        return self.photos


@dataclass
class _View:
    photo: Photo
    path: str
    target: np.ndarray = None
    mask: np.ndarray = None
    rendered: Rendered = None
    coverage: dict = field(default_factory=dict)


def _read_photo(photo, path) -> tuple[np.ndarray, Any]:
    """``(target float64 (H, W, 3), mask (H, W) or None)`` of a photo, checked."""
    from ...basis.inverse import targets

    what = f"target of {os.path.basename(path)}"
    if isinstance(photo.image, (str, os.PathLike)):
        if not os.path.isfile(photo.image):
            raise InputError(f"image {photo.image}: no such file")
        target, clipped = targets.read_target(os.fspath(photo.image))
    else:
        target = np.asarray(photo.image, dtype=np.float64)
        clipped = None
    shape = np.shape(target)
    target = targets.check_target(target, (shape[1], shape[0]) if len(shape) == 3 else (0, 0), what)
    mask = None
    if photo.mask is not None:
        if isinstance(photo.mask, (str, os.PathLike)):
            if not os.path.isfile(photo.mask):
                raise InputError(f"mask {photo.mask}: no such file")
            mask = targets.read_mask(os.fspath(photo.mask))
        else:
            mask = np.asarray(photo.mask, dtype=np.float64)
        mask = targets.check_mask(mask, (target.shape[1], target.shape[0]), f"mask of {what}")
    if clipped is not None and clipped.any():
        mask = (np.ones(target.shape[:2]) if mask is None else mask) * ~clipped
    return target, mask


def _cache_path(folder, scene_path, manifold_path, size, opts, sensor) -> str:
    key = key_hash(
        file_hash(scene_path),
        file_hash(manifold_path),
        f"{size}:{opts.spp}:{opts.seed}:{opts.max_depth}:{sensor}",
        length=24,
    )
    return os.path.join(folder, f"acquire-basis-{key}.npz")


def render_training_images(
    scene_path, manifold_path, size, opts, sensor=0, database=None, bar=None
) -> Rendered:
    """Every training material's image (and the base image) in the scene at ``size`` (width,
    height), in one pass; from ``opts.basis_cache`` when it holds them.
    """
    from ..._util.atomic import atomic_write
    from ..jobs.render_basis import _integrator
    from ..scene import scenes

    cache = None
    if opts.basis_cache:
        cache = _cache_path(opts.basis_cache, scene_path, manifold_path, size, opts, sensor)
        if os.path.isfile(cache):
            try:
                with np.load(cache) as z:
                    return Rendered(z["base"], z["images"], 0.0, True)
            except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
                pass  # a damaged cache file is rendered again (and replaced)
    t0 = time.perf_counter()
    loaded = scenes.load_scene(
        scene_path, manifold_path, opts.spp, size, opts.max_depth, database=database, sensor=sensor
    )
    if len(loaded.targets) != 1:
        raise InputError(
            f"scene {scene_path} has {len(loaded.targets)} manifold_brdf materials: acquisition "
            "needs exactly one (the photographed object's)"
        )
    integrator = _integrator("l1", loaded.integrator)

    def advance(done, total) -> None:
        if bar is not None:
            bar.set_postfix_str(f"training images {done}/{total}")

    base, images = integrator.render_onepass(
        loaded.scene, spp=opts.spp, seed=opts.seed, sensor=sensor, progress=advance
    )
    names = list(loaded.targets[0].manifold.names)
    stack = np.stack([np.asarray(images[n], dtype=np.float32)[..., :3] for n in names])
    base = np.asarray(base, dtype=np.float32)[..., :3]
    out = Rendered(base, stack, time.perf_counter() - t0, False)
    if cache is not None:
        os.makedirs(opts.basis_cache, exist_ok=True)
        atomic_write(cache, lambda f: np.savez(f, base=base, images=stack))
    return out


def render_weights(
    scene_path, manifold_path, w, size, spp, seed=0, sensor=0, database=None
) -> np.ndarray:
    """Mitsuba's render of ``sum_i w_i table_i`` (``manifold_brdf`` with these weights, no
    pruning) in the scene with its own integrator: what the snippet renders.
    """
    import dataclasses

    from ..jobs.interrupt import render_in_passes
    from ..scene import scenes

    loaded = scenes.load_scene(
        scene_path, manifold_path, spp, size, None, database=database, sensor=sensor
    )
    for bsdf in loaded.targets:
        bsdf._options = dataclasses.replace(bsdf._options, prune=0.0)
        bsdf.set_weights(np.asarray(w, dtype=np.float64))
    integrator = loaded.integrator.reference(loaded.scene)
    img = render_in_passes(loaded.scene, integrator, int(spp), int(seed), sensor=int(sensor))
    return np.asarray(img, dtype=np.float32)[..., :3]


def default_mask(rendered) -> np.ndarray:
    """Pixels where the material (the mean training material) brings at least
    :data:`MASK_SHARE` of the light.
    """
    mat = rendered.images.mean(axis=0).sum(axis=-1)
    base = rendered.base.sum(axis=-1)
    return ((mat > 0) & (mat >= MASK_SHARE * (mat + base))).astype(np.float64)


def _frame(transform) -> np.ndarray:
    """The 4x4 matrix of an emitter's ``to_world`` (scalar or one-wide JIT transform)."""
    return np.array(transform.matrix, dtype=np.float64).reshape(4, 4, -1)[..., 0]


def coverage(scene_path, manifold_path, size, mask, sensor=0, database=None) -> dict:
    """Which directions the masked pixels show: rays through the pixel centres hit the object;
    the outgoing elevation ``theta_o`` of each; for each point or small area light, the
    incidence ``theta_i`` and the half and difference angles ``theta_h``, ``theta_d`` (degrees,
    pixels where the light is above the surface; unshadowed); environment maps light every
    incidence above the surface. Percentiles 0, 5, 50, 95, 100 of each.
    """
    import mitsuba as mi

    from ..scene import scenes

    loaded = scenes.load_scene(
        scene_path, manifold_path, 1, size, None, database=database, sensor=sensor
    )
    scene = loaded.scene
    sens = scene.sensors()[sensor]
    w, h = size
    ys, xs = np.nonzero(mask > 0)
    pos = mi.Point2f((xs + 0.5) / w, (ys + 0.5) / h)
    rays, _ = sens.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(rays)
    valid = np.array(si.is_valid())
    n = np.array(si.sh_frame.n).T[valid] if np.array(si.sh_frame.n).ndim == 2 else np.zeros((0, 3))
    p = np.array(si.p).T[valid]
    d = -np.array(rays.d).T[valid]

    def pct(v) -> list:
        return [round(float(x), 1) for x in np.percentile(v, [0, 5, 50, 95, 100])] if len(v) else []

    cos_o = np.clip(np.sum(n * d, axis=1), -1, 1)
    out = {"pixels": int(valid.sum()), "theta_o": pct(np.degrees(np.arccos(cos_o))), "lights": []}
    for em in scene.emitters():
        kind = em.class_name() if hasattr(em, "class_name") else type(em).__name__
        entry = {"emitter": em.id() or kind, "kind": kind}
        pos_l = None
        if "Point" in kind or "Spot" in kind:
            pos_l = np.array(em.get_shape().bbox().center() if em.get_shape() else [0, 0, 0])
            params = mi.traverse(em)
            key = next((k for k in params.keys() if k.endswith("position")), None)
            if key is not None:
                pos_l = np.array(params[key]).reshape(-1)[:3]
            elif "to_world" in params:  # a spot light: the origin of its frame
                pos_l = _frame(params["to_world"])[:3, 3]
        elif "Directional" in kind:  # light from one direction: a point far along it
            toward = _frame(mi.traverse(em)["to_world"])[:3, 2]  # the frame's z: where light goes
            pos_l = -1e6 * toward / np.linalg.norm(toward)
        elif em.get_shape() is not None:
            pos_l = np.array(em.get_shape().bbox().center())
        if pos_l is None:
            entry["incidence"] = "every direction above the surface (environment)"
        else:
            li = pos_l[None, :] - p
            li /= np.linalg.norm(li, axis=1, keepdims=True)
            cos_i = np.sum(n * li, axis=1)
            lit = cos_i > 0
            hv = li + d
            hv /= np.linalg.norm(hv, axis=1, keepdims=True) + 1e-30
            th = np.degrees(np.arccos(np.clip(np.sum(n * hv, axis=1), -1, 1)))
            td = np.degrees(np.arccos(np.clip(np.sum(li * hv, axis=1), -1, 1)))
            entry.update(
                lit_pixels=int(lit.sum()),
                theta_i=pct(np.degrees(np.arccos(np.clip(cos_i[lit], -1, 1)))),
                theta_h=pct(th[lit]),
                theta_d=pct(td[lit]),
            )
        out["lights"].append(entry)
    return out


def coverage_warnings(cov) -> list:
    """Warnings of what the masked pixels do not show (from :func:`coverage` of every view)."""
    out: list = []
    if not cov:
        return out
    grazing = max((c["theta_o"][-1] for c in cov if c.get("theta_o")), default=0.0)
    if grazing < GRAZING_DEG:
        out.append(
            f"no pixel is seen beyond {grazing:.0f} degrees from the normal: the material at "
            "grazing views (Fresnel, retro-reflection) is extrapolated"
        )
    points = [lt for c in cov for lt in c["lights"] if "theta_h" in lt and lt["theta_h"]]
    envs = [lt for c in cov for lt in c["lights"] if "theta_h" not in lt]
    if points and min(lt["theta_h"][0] for lt in points) > PEAK_SEEN_DEG and not envs:
        out.append(
            "no point light's highlight falls on the masked pixels: the gloss (specular peak) is a guess"
        )
    if not points:
        out.append(
            "no point-like light: only an environment's highlights show the gloss; a flash or "
            "a lamp in the photo pins it down"
        )
    return out


def acquire(  # noqa: PLR0915  the steps behind one progress bar, each a function of its own
    photos, manifold=None, options=None, database=None, training_images=None, **renamed
) -> AcquireOutput:
    """Acquire the material of ``photos`` (:class:`Photo`) over the manifold's training tables.

    Parameters
    ----------
    photos : list of Photo
    manifold : str
        The manifold file the scenes' ``manifold_brdf`` uses (its training tables are the basis;
        ``manifold_path``, its former name, is read with a ``DeprecationWarning``).
    options : AcquireOptions, optional
    database : str, optional
        Folder of the manifold's tables when moved.
    training_images : list of Rendered, optional
        Each photo's base image and training materials' images (``(N, H, W, 3)``, the manifold's
        order) when the caller has them already (a basis of the scene): nothing is rendered for
        them.

    Returns
    -------
    AcquireOutput

    Notes
    -----
    The steps, in order, behind one progress bar: the photos read, the training images
    rendered or taken, the programme chosen and solved, the spread, the coverage and the two
    renders.
    """
    from tqdm import tqdm

    from ...manifold.model import Manifold
    from ..scene import scenes

    manifold_path = renamed_argument(manifold, renamed, "manifold_path", "manifold", "acquire")
    if renamed:
        raise TypeError(f"acquire() got unexpected keywords {sorted(renamed)}")
    opts = (options or aq.AcquireOptions()).check()
    if opts.method == "latent":
        raise InputError(
            "`method` 'latent' is the latent-point search of match_render.match_render; "
            "call it (or match.py --render --method latent)"
        )
    if not photos:
        raise InputError("`photos` is empty: give at least one scene and photo")
    if training_images is not None and len(training_images) != len(photos):
        raise InputError(
            f"`training_images` has {len(training_images)} entries for {len(photos)} photos"
        )
    t_start = time.perf_counter()
    timings = {}
    given = os.fspath(manifold_path)
    manifold_path = resolve_manifold(given)  # a shipped name: its file, from here on
    # what the result records: a shipped manifold by its name (portable), a file by its path
    recorded = (
        given
        if given.startswith(BUILTIN_PREFIX)
        else BUILTIN_PREFIX + given
        if given in SHIPPED and manifold_path != given
        else os.path.abspath(manifold_path)
    )
    manifold = Manifold.load(manifold_path)
    scenes.use_variant(jit=True)
    views = []
    for ph in photos:
        path = scenes.check_scene("`scene`", ph.scene)
        target, mask = _read_photo(ph, path)
        views.append(_View(ph, path, target, mask))
    sets = 2 if opts.method == "plausible" else 1
    steps = len(views) + sets * len(aq.CV_GRID) * (opts.regularisation is None) + opts.bootstrap + 2
    bar = tqdm(total=steps, desc="acquire", disable=not opts.progress, leave=False)
    t0 = time.perf_counter()
    for v in views:
        size = (v.target.shape[1], v.target.shape[0])
        if training_images is not None:
            base, images = training_images[len([u for u in views if u.rendered])][:2]
            v.rendered = Rendered(base, images, 0.0, True)
        else:
            v.rendered = render_training_images(
                v.path, manifold_path, size, opts, v.photo.sensor, database, bar
            )
        if v.rendered.images.shape[0] != manifold.n:
            raise InputError(
                f"scene {v.path}: its manifold_brdf has {v.rendered.images.shape[0]} materials, "
                f"the manifold {manifold_path} {manifold.n}: give the scene's manifold"
            )
        if v.mask is None:
            v.mask = default_mask(v.rendered)
        bar.update(1)
    timings["training_images_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    photos_lin = _linear(views)
    cons = constraints_of(manifold, database)
    bar.update(1)
    timings["constraints_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    scores = {}
    feasible, lam = ("beyond" if opts.method == "plausible" else opts.method), opts.regularisation
    if lam is None:
        feasible, lam, scores = aq.choose(
            photos_lin, cons, opts.method, seed=opts.seed, progress=lambda: bar.update(1)
        )
    db = manifold.open_database(database) if feasible == "beyond" else None
    w, shrink, cons = aq.solve_programme(
        photos_lin, cons, feasible, lam, lambda i: db.reflectance(manifold.names[i]), manifold.n
    )
    timings["solve_s"] = time.perf_counter() - t0
    bar.update(1)
    t0 = time.perf_counter()
    sp = None
    if opts.bootstrap:
        sp = aq.spread(
            photos_lin,
            cons,
            feasible,
            lam,
            w,
            opts.bootstrap,
            opts.seed,
            progress=lambda: bar.update(1),
        )
    timings["spread_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    cov = [
        coverage(
            v.path,
            manifold_path,
            (v.target.shape[1], v.target.shape[0]),
            v.mask,
            v.photo.sensor,
            database,
        )
        for v in views
    ]
    timings["coverage_s"] = time.perf_counter() - t0
    bar.close()
    errors = [photos_lin.relative_error(np.eye(manifold.n)[i]) for i in range(manifold.n)]
    best = int(np.argmin(errors))
    warnings = coverage_warnings(cov)
    warnings += aq.answer_warnings(sp, shrink)
    result = aq.Acquisition(
        names=list(manifold.names),
        w=[float(v) for v in w],
        method=opts.method,
        error=photos_lin.relative_error(w),
        single={"name": manifold.names[best], "error": float(errors[best])},
        x=None,
        regularisation=float(lam),
        feasible=feasible,
        cross_validation={k: [list(v) for v in sc] for k, sc in scores.items()},
        coverage={"views": cov},
        spread=None if sp is None else sp.__dict__,
        warnings=warnings,
        time_s=time.perf_counter() - t_start,
        timings=timings,
        views=[
            {
                "scene": v.path,
                "target": os.path.abspath(v.photo.image)
                if isinstance(v.photo.image, (str, os.PathLike))
                else None,
                "mask": os.path.abspath(v.photo.mask)
                if isinstance(v.photo.mask, (str, os.PathLike))
                else None,
                "sensor": int(v.photo.sensor),
                "cached_training_images": bool(v.rendered.cached),
            }
            for v in views
        ],
        manifold=recorded,
    )
    t0 = time.perf_counter()
    renders: list
    singles: list
    renders, singles = [], []
    for v in views if opts.render_spp else []:
        size = (v.target.shape[1], v.target.shape[0])
        for what, weights in ((renders, w), (singles, np.eye(manifold.n)[best])):
            what.append(
                render_weights(
                    v.path,
                    manifold_path,
                    weights,
                    size,
                    opts.render_spp,
                    opts.seed + 1,
                    v.photo.sensor,
                    database,
                )
            )
    result.timings["renders_s"] = time.perf_counter() - t0
    result.time_s = time.perf_counter() - t_start
    return AcquireOutput(
        result, [v.target for v in views], [v.mask for v in views], renders, singles
    )


def _linear(views) -> aq.LinearPhotos:
    """The masked pixels of every view as rows of :class:`~..basis.acquisition.LinearPhotos`."""
    A, base, t, block, view = [], [], [], [], []
    offset = 0
    for k, v in enumerate(views):
        if v.rendered.images.shape[1:3] != v.target.shape[:2]:
            raise InputError(
                f"the training images of {v.path} are {v.rendered.images.shape[2]}x"
                f"{v.rendered.images.shape[1]}, the photo {v.target.shape[1]}x{v.target.shape[0]}"
            )
        sel = v.mask > 0
        ys, xs = np.nonzero(sel)
        n = v.rendered.images.shape[0]
        A.append(v.rendered.images[:, sel].reshape(n, -1).T.astype(np.float64))
        base.append(v.rendered.base[sel].reshape(-1).astype(np.float64))
        t.append(v.target[sel].reshape(-1))
        blocks = (ys // aq.CV_BLOCK) * 100000 + xs // aq.CV_BLOCK + offset
        block.append(np.repeat(blocks, 3))
        view.append(np.full(3 * len(ys), k))
        offset = int(blocks.max()) + 1 if len(blocks) else offset
    return aq.LinearPhotos(
        np.concatenate(A),
        np.concatenate(base),
        np.concatenate(t),
        np.concatenate(block),
        np.concatenate(view),
    ).check()


def constraints_of(manifold, database=None) -> aq.Constraints:
    """The plausibility constraints of the manifold's tables, kept in the database's cache folder
    (keyed by the tables' content hashes).
    """
    from ..._util.atomic import atomic_write

    db = manifold.open_database(database)
    key = key_hash(
        "\n".join(db.hashes(list(manifold.names))),
        f"{aq.CHECK_BINS}:{aq.CHECK_PER_MATERIAL}:v2",
        length=32,
    )
    path = os.path.join(db.cache_dir, f"acquire-constraints-{key}.npz")
    if os.path.isfile(path):
        try:
            with np.load(path) as z:
                return aq.Constraints(z["albedo"], z["check"], z["peak"], z["sample"])
        except (OSError, ValueError, KeyError):
            pass
    cons = aq.Constraints.of(lambda i: db.reflectance(manifold.names[i]), manifold.n, manifold.dims)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    atomic_write(
        path,
        lambda f: np.savez(
            f, albedo=cons.albedo, check=cons.check, peak=cons.peak, sample=cons.sample
        ),
    )
    return cons
