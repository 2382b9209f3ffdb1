"""Loading a scene XML with its ``$parameters`` set (the manifold, the latent point, the size, the
depth), finding its manifold materials (:func:`load_scene`), and setting them to latent points
(:func:`set_points`, :func:`scene_at`).
"""

import os
from typing import NamedTuple

import numpy as np

from ...errors import InputError, MismatchError
from ...manifold.file.identity import manifold_identity
from ...manifold.file.shipped import resolve_manifold
from .files import check_scene_manifolds, check_wrappers, other_manifold, scene_parameters
from .integrator import scene_integrator
from .variants import use_variant


class _Loaded(NamedTuple):
    scene: object
    targets: list
    max_depth: int


class LoadedScene(_Loaded):
    """:func:`load_scene`: the scene, its ``manifold_brdf`` instances (shape order), the path
    depth (it unpacks as these three), and the attribute ``integrator``: what the scene's
    integrator renders (:class:`~.integrator.SceneIntegrator`).
    """

    integrator = None


def load_scene(
    scene_path,
    manifold_path,
    spp=None,
    resolution=None,
    max_depth=None,
    x=None,
    variant=None,
    database=None,
    sensor=0,
):
    """Load a scene XML with its ``$parameters`` set, and find its manifold materials.

    Only the parameters the XML uses are passed (Mitsuba refuses others): ``$manifold``,
    ``$x``, ``$spp``, ``$max_depth``, ``$integrator`` (``path`` where the scene has no default for it,
    or ``manifold_path``) and the size through
    ``$res`` (square) or ``$width``/``$height``.

    Parameters
    ----------
    scene_path, manifold_path : str
    spp : int, optional
    resolution : int or (int, int), optional
        Square size or ``(width, height)``; checked against the film of ``sensor``.
    max_depth : int, optional
        Path depth, overriding the scene's integrator (its ``$max_depth`` where it takes one);
        default: the scene's own (:func:`~.integrator.scene_integrator`: its integrator's ``max_depth``,
        ``direct`` as 2, -1 where it has no integrator).
    x : array_like (q,), optional
        Default: the first material's latent point (a scene's own ``$x`` default may not
        fit the manifold's latent dimension).
    variant : str, optional
        The Mitsuba variant to load the scene in (activated: the scene lives in it). Default:
        the active variant, or :func:`~.variants.default_variant` when none is active yet; the active
        variant is never switched unless ``variant`` asks for another (:func:`~.variants.use_variant`).
    database : str, optional
        Folder of the manifold's tables when it is not where the manifold says (moved):
        the scene's ``$database`` if it takes one, else every ``manifold_brdf`` without a
        ``database`` parameter of its own (:func:`overrides.database_override`).

    sensor : int
        The sensor whose film ``resolution`` is checked against.

    Returns
    -------
    LoadedScene
        ``scene`` (mi.Scene), ``targets`` (the scene's ``manifold_brdf`` instances in shape
        order, checked to use ``manifold_path``), ``max_depth`` (int, the paths' depth) and
        ``integrator`` (:class:`~.integrator.SceneIntegrator`: what the scene's integrator renders).
    """
    import functools

    import mitsuba as mi

    from ...manifold.model import Manifold
    from ..integrators import manifold_bsdfs

    scene_path, manifold_path = os.fspath(scene_path), resolve_manifold(manifold_path)
    if not os.path.isfile(manifold_path):
        raise MismatchError(f"manifold {manifold_path} does not exist")
    manifold = functools.cache(
        lambda: Manifold.load(manifold_path)
    )  # loaded once, when first needed
    used, defaults = scene_parameters(scene_path)
    use_variant(variant)
    if spp is not None and int(spp) < 1:
        raise MismatchError(f"`spp` must be >= 1, got {spp}")
    if max_depth is not None and int(max_depth) < -1:
        raise MismatchError(
            f"`max_depth` must be -1 (unbounded) or an integer >= 0, got {max_depth}"
        )
    params, size = _scene_params(
        used,
        defaults,
        manifold_path,
        manifold,
        x=x,
        spp=spp,
        max_depth=max_depth,
        database=database,
        resolution=resolution,
    )
    check_scene_manifolds(scene_path, manifold_path, params)
    check_wrappers(scene_path)
    from ...errors import one_line
    from ..plugin.overrides import database_override

    try:
        with database_override(database):
            # optimize=False: Mitsuba would merge identical BSDF definitions, and two manifold
            # materials given the same x would silently become one target.
            scene = mi.load_file(scene_path, optimize=False, **params)
    except Exception as e:
        raise MismatchError(f"scene {scene_path}: cannot load: {one_line(e)}") from None
    targets = manifold_bsdfs(scene)
    if not targets:
        raise MismatchError(
            f"scene {scene_path} has no manifold_brdf material (give the material to edit "
            'type="manifold_brdf" and take the manifold as $manifold)'
        )
    want = manifold_identity(manifold())
    for bsdf in targets:  # ManifoldBRDF instances (manifold_bsdfs)
        if manifold_identity(bsdf.manifold) != want:
            raise MismatchError(
                other_manifold(scene_path, bsdf.id(), bsdf.manifold_path, manifold_path)
            )
    sensors = scene.sensors()
    if not 0 <= int(sensor) < len(sensors):
        raise InputError(
            f"`sensor` {sensor} does not exist: {scene_path} has {len(sensors)} sensor(s)"
        )
    film_size = tuple(int(v) for v in sensors[int(sensor)].film().size())
    took = "res" in params or "width" in params or "height" in params
    if size is not None and not took and film_size != size:
        raise MismatchError(
            f"scene {scene_path} renders {film_size[0]}x{film_size[1]}"
            f"{f' from sensor {sensor}' if sensor else ''}, not {size[0]}x{size[1]} "
            "(it takes no $res/$width/$height parameter for this size)"
        )
    integrator = scene_integrator(scene, scene_path, max_depth)
    check_film(scene_path, sensors[int(sensor)].film())
    loaded = LoadedScene(scene, targets, integrator.max_depth)
    loaded.integrator = integrator
    return loaded


def _scene_params(
    used, defaults, manifold_path, manifold, *, x, spp, max_depth, database, resolution
):
    """The ``$parameters`` to load a scene with (only those its XML uses) and the image size
    asked for (None: the film's own); ``manifold`` loads the manifold when first called.
    """
    params = {}
    if "manifold" in used:
        params["manifold"] = os.path.abspath(manifold_path)
    if "x" in used:
        if x is None:
            x = manifold().latent[0]
        params["x"] = ", ".join(repr(float(v)) for v in np.ravel(x))
    if database is not None and "database" in used:
        params["database"] = os.path.abspath(database)
    if "spp" in used and spp is not None:
        params["spp"] = str(int(spp))
    if "integrator" in used and defaults.get("integrator") in (None, "manifold_path"):
        params["integrator"] = "path"  # the scene's own default integrator type is kept
    if "max_depth" in used and max_depth is not None:
        params["max_depth"] = str(int(max_depth))
    size = None
    if resolution is not None:
        size = (
            (int(resolution), int(resolution))
            if np.isscalar(resolution)
            else tuple(int(v) for v in resolution)
        )
        if "res" in used and size[0] == size[1]:
            params["res"] = str(size[0])
        for name, value in zip(("width", "height"), size):
            if name in used:
                params[name] = str(value)
    return params, size


def scene_resolution(manifest):
    """The ``resolution`` a basis's scene was loaded with (None: the scene's own film size), to
    load it again as the basis saw it (its references, refinements); a manifest that does not
    record it (an earlier version) was rendered at its image size. ``manifest`` is a
    :class:`~mitsuba_manifold.basis.folder.Manifest`
    (:attr:`~mitsuba_manifold.basis.folder.Manifest.loaded_resolution`).
    """
    return manifest.loaded_resolution


def image_size(film):
    """``(width, height)`` of the images a film gives: its crop window's size."""
    return tuple(int(v) for v in film.crop_size())


def check_film(scene_path, film):
    """Raise unless the basis can render ``film``'s images: a film that develops an image
    (``hdrfilm``; every pixel format: the basis and references are RGB, the film's format being a
    fixed map of it).
    """
    name = film.class_name() if hasattr(film, "class_name") else type(film).__name__
    if name != "HDRFilm":
        raise InputError(
            f"scene {scene_path}: film {name} is not supported (the basis stores linear RGB "
            'images): use <film type="hdrfilm">'
        )


def scene_at(
    scene_path,
    manifold_path,
    x,
    spp=None,
    resolution=None,
    max_depth=None,
    variant=None,
    targets=None,
    database=None,
):
    """``(scene, max_depth)``: the scene loaded (:func:`load_scene`) with every manifold material
    at its latent point: ``x`` (q,) for all of them, or (p, q) one per target (``targets``: the
    BSDF ids of the rows, default the scene's manifold materials in the order of its shapes).
    """
    pts = as_points(x)
    loaded = load_scene(
        scene_path, manifold_path, spp, resolution, max_depth, pts[0], variant, database
    )
    set_points(loaded.targets, pts, targets)
    return loaded.scene, loaded.max_depth


def set_points(found, x, targets=None):
    """Every manifold material ``found`` (:attr:`LoadedScene.targets`) at its latent point: ``x``
    (q,) for all of them, or (p, q) one per target (``targets`` as :func:`scene_at`).
    """
    pts = as_points(x)
    ids = [b.id() for b in found]
    if len(pts) == 1:
        rows = [0] * len(found)
    else:
        order = ids if targets is None else list(targets)
        if len(order) != len(pts) or sorted(order) != sorted(ids):
            raise MismatchError(
                f"`x` gives {len(pts)} latent points for targets {order}; the scene's manifold "
                f"materials are {ids}"
            )
        rows = [order.index(i) for i in ids]
    for bsdf, row in zip(found, rows):
        bsdf.set_latent(pts[row])


def as_points(x):
    """``x`` as a (p, q) array of finite latent points, or the error naming it."""
    pts = np.atleast_2d(np.asarray(x, dtype=np.float64))
    if pts.ndim != 2 or not np.isfinite(pts).all():
        raise MismatchError(
            f"`x` must be finite numbers of shape (q,) or (p, q), got {np.shape(x)}"
        )
    return pts
