"""Scenes: the ones shipped with the package, loading with ``$parameters``, references.

The package ships its test and demo scenes (``scenes/`` in a checkout, ``mitsuba_manifold/scenes``
once installed):
:func:`scene_path` accepts one of their names (``"table"``) or a path to any scene XML.
:func:`load_scene` loads a scene with the manifold and latent point as parameters and
finds its manifold materials; :func:`render_reference` renders the full global
illumination of an interpolated material with Mitsuba's ``path`` (the ground truth the
``L1-`` blends of paper Sec. 5.2 are compared with).
"""

import os
import re
from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np

from ..._util.checks import scene_xml
from ...data.sources import BUILTIN_PREFIX
from ...errors import InputError, MismatchError, MitsubaManifoldError, VariantError, did_you_mean
from ...manifold.file.identity import manifold_identity
from ...manifold.file.shipped import SHIPPED, ambiguity, resolve_manifold


def _scenes_dir():
    """The shipped scenes: ``scenes/`` at the top of a checkout, installed as the package data
    ``mitsuba_manifold/scenes`` (``pyproject.toml`` maps one to the other).
    """
    package = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    for folder in (
        os.path.join(package, "scenes"),
        os.path.join(os.path.dirname(package), "scenes"),
    ):
        if os.path.isfile(os.path.join(folder, "table.xml")):
            return folder
    return os.path.join(package, "scenes")


#: Folder of the scenes shipped with the package.
SCENES_DIR = _scenes_dir()

_PARAM = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")


class _Loaded(NamedTuple):
    scene: object
    targets: list
    max_depth: int


class LoadedScene(_Loaded):
    """:func:`load_scene`: the scene, its ``manifold_brdf`` instances (shape order), the path
    depth (it unpacks as these three), and the attribute ``integrator``: what the scene's
    integrator renders (:class:`SceneIntegrator`).
    """

    integrator = None


#: Mitsuba integrators whose image is that of ``path`` (unbiased path tracers, without media),
#: by class name: the basis reproduces them.
PATH_LIKE = {
    "PathIntegrator": "path",
    "PRBIntegrator": "prb",
    "BasicPRBIntegrator": "prb_basic",
    "VolumetricSimplePathIntegrator": "volpath",
    "VolumetricPathIntegrator": "volpath",
    "VolpathMisIntegratorImpl": "volpathmis",
    "PRBVolpathIntegrator": "prbvolpath",
}
#: ... and those whose image is that of ``path`` with ``max_depth`` 2 (direct light, emitters seen).
DIRECT_LIKE = {"DirectIntegrator": "direct"}
#: Mitsuba's default Russian-roulette depth.
RR_DEPTH = 5


@dataclass(frozen=True)
class SceneIntegrator:
    """What a scene's integrator renders, as the basis and the references reproduce it.

    ``kind``: the integrator's plugin type (``path``, ``direct``, ...; ``path`` where the scene
    has none, as Mitsuba renders it); ``max_depth`` (-1: unbounded; ``direct`` is ``path`` with
    ``max_depth`` 2: the emitters seen and one scattering vertex lit by next-event estimation and
    MIS, the same image in expectation), ``rr_depth``, ``hide_emitters``; ``source``: ``"scene"``
    (the scene's own), ``"default"`` (the scene has none) or ``"option"`` (``max_depth`` set by
    the caller, overriding the scene's).
    """

    kind: str
    max_depth: int
    rr_depth: int
    hide_emitters: bool
    source: str

    def path_properties(self):
        """Properties of a ``manifold_path`` (or ``path``) integrator that renders these paths."""
        return {
            "max_depth": int(self.max_depth),
            "rr_depth": int(self.rr_depth),
            "hide_emitters": bool(self.hide_emitters),
        }

    def reference(self, scene):
        """The integrator Mitsuba renders the scene's reference with: the scene's own, or a
        ``path`` of these settings where the depth was overridden or the scene has none.
        """
        import mitsuba as mi

        own = scene.integrator()
        if self.source == "scene" and own is not None:
            return own
        return mi.load_dict({"type": "path", **self.path_properties()})

    def describe(self):
        """One phrase: ``path (max_depth 3, hide_emitters)``, with where it comes from."""
        depth = "unbounded" if self.max_depth < 0 else str(self.max_depth)
        extra = ", hide_emitters" if self.hide_emitters else ""
        where = {
            "scene": "the scene's integrator",
            "default": "no integrator in the scene: Mitsuba's default",
            "option": "max_depth set by the caller",
        }[self.source]
        return f"{self.kind} (max_depth {depth}, rr_depth {self.rr_depth}{extra}; {where})"

    def to_manifest(self):
        return asdict(self)


def _depth_of(integrator, name, text):
    """An integer property of a Mitsuba integrator: its attribute, else its ``to_string``."""
    value = getattr(integrator, name, None)
    if value is None:
        m = re.search(rf"{name}\s*=\s*(-?\d+)", text)
        value = int(m.group(1)) if m else None
    if value is None:
        return None
    value = int(value)
    return -1 if value >= 0xFFFFFFFF or value < 0 else value


def scene_integrator(scene, scene_path, max_depth=None):
    """The :class:`SceneIntegrator` of a loaded scene, or an :class:`InputError` naming the
    setting the basis cannot reproduce (raised before anything is rendered).

    ``max_depth`` (given by the caller): overrides the scene's depth where it differs (a
    ``direct`` integrator becomes ``path`` of that depth); the scene's ``rr_depth`` and
    ``hide_emitters`` are kept.
    """
    own = scene.integrator()
    if own is None:
        found = SceneIntegrator("path", -1, RR_DEPTH, False, "default")
    else:
        cls = own.class_name() if hasattr(own, "class_name") else type(own).__name__
        cls = (
            type(own).__name__
            if cls
            in (
                "SamplingIntegrator",
                "MonteCarloIntegrator",
                "ADIntegrator",
                "RBIntegrator",
                "PSIntegrator",
            )
            else cls
        )
        text = str(own)
        hide = bool(getattr(own, "hide_emitters", False))
        if cls in DIRECT_LIKE:
            found = SceneIntegrator(DIRECT_LIKE[cls], 2, RR_DEPTH, hide, "scene")
        elif cls in PATH_LIKE:
            if PATH_LIKE[cls].startswith(("volpath", "prbvolpath")) and _has_media(scene):
                raise InputError(
                    f"scene {scene_path}: integrator {PATH_LIKE[cls]!r} with participating media: "
                    "the basis renders surfaces only; remove the media (or render the scene without "
                    "the manifold basis)"
                )
            depth = _depth_of(own, "max_depth", text)
            rr = _depth_of(own, "rr_depth", text)
            found = SceneIntegrator(
                PATH_LIKE[cls],
                -1 if depth is None else depth,
                RR_DEPTH if rr is None or rr < 1 else rr,
                hide,
                "scene",
            )
        else:
            raise InputError(
                f"scene {scene_path}: its integrator ({cls}) renders something the basis cannot "
                "reproduce (the basis renders what `path` and `direct` do): give the scene "
                '<integrator type="path"> (with its max_depth) or type="direct"'
            )
    if max_depth is not None and int(max_depth) != found.max_depth:
        found = SceneIntegrator(
            "path", int(max_depth), found.rr_depth, found.hide_emitters, "option"
        )
    return found


def _has_media(scene):
    """Whether any shape or sensor of ``scene`` bounds or holds a participating medium."""
    for shape in scene.shapes():
        for name in ("interior_medium", "exterior_medium"):
            get = getattr(shape, name, None)
            if get is not None and get() is not None:
                return True
    return any(getattr(s, "medium", lambda: None)() is not None for s in scene.sensors())


def shipped_scenes():
    """Names of the scenes shipped with the package (``table``, ``sphere``, ...)."""
    return sorted(f[:-4] for f in os.listdir(SCENES_DIR) if f.endswith(".xml"))


def scene_path(scene):
    """Path of a scene given as a shipped scene's name (``"table"``) or as a path to an XML file."""
    scene = os.fspath(scene)
    if os.path.isfile(scene):
        scene_xml(scene)  # a scene XML, or an error naming the file
        return os.path.abspath(scene)
    shipped = os.path.join(SCENES_DIR, scene + ".xml")
    if os.sep not in scene and not scene.endswith(".xml") and os.path.isfile(shipped):
        return shipped
    raise MismatchError(
        f"scene {scene} does not exist (nor is it the name of a shipped scene: "
        f"{', '.join(shipped_scenes())})"
    )


def default_variant():
    """The variant named by the environment variable ``MM_VARIANT`` when set (``llvm_ad_rgb`` or
    ``cuda_ad_rgb``, the latter refused where CUDA does not run), else ``cuda_ad_rgb`` when a GPU
    works, else ``llvm_ad_rgb``.
    """
    import mitsuba as mi

    chosen = os.environ.get("MM_VARIANT")
    if chosen:
        usable = [v for v in ("llvm_ad_rgb", "cuda_ad_rgb") if v in mi.variants()]
        if chosen not in usable:
            raise VariantError(
                f"MM_VARIANT={chosen}: the tools render in "
                f"{' or '.join(usable)}; unset MM_VARIANT or name one of those"
            )
        if chosen.startswith("cuda") and not _cuda_works():
            raise VariantError(
                f"MM_VARIANT={chosen}: no CUDA device or driver works here; unset "
                "MM_VARIANT or use llvm_ad_rgb"
            )
        return chosen
    if "cuda_ad_rgb" in mi.variants() and _cuda_works():
        return "cuda_ad_rgb"
    return "llvm_ad_rgb"


def _cuda_works():
    """Whether Dr.Jit's CUDA backend runs here (a device and a driver)."""
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # no driver
        return False


def use_variant(variant=None, jit=False):
    """The variant to render in, active and with the package's plugins; returns ``mi``.

    Never switches the variant unless asked, as Mitsuba itself:

    - ``variant`` given: that one (checked, :func:`check_variant`), activated as
      ``mi.set_variant(variant)`` would (the scenes loaded then live in it);
    - else the active variant, checked (an unsuitable one is refused, not replaced);
    - else (no variant is active yet) :func:`default_variant`, activated.

    To render in another variant for a while, wrap the calls in Mitsuba's own
    ``with mi.util.scoped_set_variant("llvm_ad_rgb"): ...``.

    Parameters
    ----------
    jit : bool
        Require a JIT variant, as the ``manifold_path`` integrator does.
    """
    import mitsuba as mi

    from ..plugin import plugins

    if variant is not None:
        check_variant(variant, jit=jit)
        if mi.variant() != variant:
            mi.set_variant(variant)
    elif mi.variant() is not None:
        try:
            check_variant(mi.variant(), "the active Mitsuba variant", jit)
        except InputError as e:
            raise InputError(f"{e}; call mi.set_variant(...) or pass `variant`") from None
    else:
        mi.set_variant(default_variant())
    plugins.install()
    plugins.register()
    return mi


def release_render_memory():
    """Give the memory Dr.Jit keeps for reuse after a render back to the system.

    Dr.Jit caches the buffers a kernel frees (the paths and splats of a pass) for later kernels
    of the same sizes; after a large render they would stay in the process, beside the NumPy
    arrays of the next steps, until it ends. Called where a large render is done.
    """
    import drjit as dr

    dr.flush_malloc_cache()


def scene_parameters(scene):
    """Names of the ``$parameters`` a scene XML uses, and its ``<default>`` values."""
    root = scene_xml(scene)  # exists, and is a scene XML (not a table or an image)
    defaults = {el.get("name"): el.get("value") for el in root.iter("default")}
    used = {
        name for el in root.iter() for value in el.attrib.values() for name in _PARAM.findall(value)
    }
    return used, defaults


def scene_sample_count(scene, sensor=0):
    """Samples per pixel the sampler of sensor ``sensor`` of a scene XML declares: its
    ``sample_count``, or the ``<default>`` of the ``$parameter`` it takes; None where it
    declares none (or gives no integer).
    """
    root = scene_xml(scene)
    defaults = {el.get("name"): el.get("value") for el in root.iter("default")}
    sensors = root.findall("sensor")
    if not 0 <= int(sensor) < len(sensors):
        return None
    for el in sensors[int(sensor)].iter("integer"):
        if el.get("name") == "sample_count":
            value = _PARAM.sub(lambda m: str(defaults.get(m.group(1), "")), el.get("value") or "")
            try:
                return int(value)
            except ValueError:
                return None
    return None


def scene_manifolds(scene, params=None):
    """``(bsdf id, manifold file)`` of each ``manifold_brdf`` of a scene XML: its ``manifold``
    value with ``$parameters`` taken from ``params``, else the scene's ``<default>``s, and a
    relative path resolved against the scene's folder (as Mitsuba's file resolver does), or
    a shipped manifold's name where no file of that name exists there.
    """
    root = scene_xml(scene)
    values = {**{el.get("name"): el.get("value") for el in root.iter("default")}, **(params or {})}
    folder = os.path.dirname(os.path.abspath(scene))
    found = []
    for bsdf in root.iter("bsdf"):
        named = [el.get("value") for el in bsdf if el.get("name") == "manifold"]
        if bsdf.get("type") != "manifold_brdf" or not named or named[0] is None:
            continue
        value = _PARAM.sub(lambda m: str(values.get(m.group(1), m.group(0))), named[0])
        path = os.path.join(folder, value)
        if value in SHIPPED or value.startswith(BUILTIN_PREFIX):
            if value in SHIPPED and os.path.lexists(path):
                raise ambiguity(value, path)
            path = resolve_manifold(value)
        elif not os.path.exists(path) and os.path.exists(value):
            path = value
        found.append((bsdf.get("id"), os.path.abspath(path)))
    return found


def _check_scene_manifolds(scene, manifold_path, params):
    """Raise unless every ``manifold_brdf`` of the scene uses ``manifold_path`` (the file, or
    one of the same content): a scene naming its own manifold is not rendered with another's
    latent points.
    """
    want, identity = os.path.realpath(manifold_path), None
    for bsdf_id, path in scene_manifolds(scene, params):
        if os.path.realpath(path) == want:
            continue
        from ...manifold.model import Manifold

        try:
            identity = identity or manifold_identity(Manifold.load(manifold_path))
            if manifold_identity(Manifold.load(path)) == identity:
                continue
        except (MitsubaManifoldError, OSError):
            pass
        raise MismatchError(_other_manifold(scene, bsdf_id, path, manifold_path))


#: BSDFs that hide the BSDF they hold from Mitsuba's scene traversal (the basis cannot find a
#: ``manifold_brdf`` inside them, nor record its vertices in their perturbed frames).
HIDING_WRAPPERS = ("normalmap", "bumpmap")


def _check_wrappers(scene):
    """Raise (before loading) if a ``manifold_brdf`` of the scene XML sits inside a
    :data:`HIDING_WRAPPERS` BSDF, naming it and what works instead.
    """
    root = scene_xml(scene)
    ids = {
        b.get("id") for b in root.iter("bsdf") if b.get("type") == "manifold_brdf" and b.get("id")
    }
    for wrapper in root.iter("bsdf"):
        if wrapper.get("type") not in HIDING_WRAPPERS:
            continue
        inner = [
            el
            for el in wrapper.iter()
            if el is not wrapper
            and (
                (el.tag == "bsdf" and el.get("type") == "manifold_brdf")
                or (el.tag == "ref" and el.get("id") in ids)
            )
        ]
        if inner:
            name = wrapper.get("id") or wrapper.get("type")
            raise InputError(
                f"scene {scene}: the manifold_brdf is inside the {wrapper.get('type')} BSDF {name!r}, "
                "which the basis cannot render (it perturbs the shading frame the measured tables are "
                "looked up in, and hides the material from the scene's traversal): give the shape the "
                "manifold_brdf itself (or inside twosided), without the "
                f"{wrapper.get('type')}"
            )


def _other_manifold(scene, bsdf_id, path, manifold_path):
    if not os.path.isfile(path):
        return (
            f"scene {scene}: material {bsdf_id!r} names the manifold {path} (which does not exist), not "
            f'{manifold_path}: use value="$manifold" in the scene'
        )
    return (
        f"scene {scene}: material {bsdf_id!r} names the manifold {path}, not {manifold_path}: use "
        f'value="$manifold" in the scene, or pass `manifold_path`={path}'
    )


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
        default: the scene's own (:func:`scene_integrator`: its integrator's ``max_depth``,
        ``direct`` as 2, -1 where it has no integrator).
    x : array_like (q,), optional
        Default: the first material's latent point (a scene's own ``$x`` default may not
        fit the manifold's latent dimension).
    variant : str, optional
        The Mitsuba variant to load the scene in (activated: the scene lives in it). Default:
        the active variant, or :func:`default_variant` when none is active yet; the active
        variant is never switched unless ``variant`` asks for another (:func:`use_variant`).
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
        ``integrator`` (:class:`SceneIntegrator`: what the scene's integrator renders).
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
    _check_scene_manifolds(scene_path, manifold_path, params)
    _check_wrappers(scene_path)
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
                _other_manifold(scene_path, bsdf.id(), bsdf.manifold_path, manifold_path)
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


def render_reference(  # noqa: PLR0913  a render's own five and the view settings a basis records
    scene_path,
    manifold_path,
    x,
    spp,
    seed=0,
    resolution=None,
    max_depth=None,
    variant=None,
    targets=None,
    database=None,
    sensor=0,
):
    """Mitsuba's own image of the scene with the interpolated material: the ground truth of a blend.

    The optional settings are those a basis records (resolution, depth, variant, targets,
    database, sensor): a caller renders the view a basis was rendered with.

    Loads the scene (:func:`load_scene`), sets every manifold material to its latent
    point, and renders it with the scene's own integrator (:meth:`SceneIntegrator.reference`:
    ``path`` of the same settings where ``max_depth`` overrides it or the scene has none) in
    passes (:func:`interrupt.render_in_passes`: Ctrl-C raises ``KeyboardInterrupt`` within a
    pass), as linear RGB of the film's crop window whatever its pixel format.

    Parameters
    ----------
    scene_path, manifold_path : str
    x : array_like
        (q,): every manifold material of the scene at x; or (p, q): one point per target.
    targets : list of str, optional
        BSDF ids of the rows of a (p, q) ``x`` (a basis's ``targets``); default: the
        scene's manifold materials in the order of its shapes.
    spp, seed : int
    resolution, max_depth, variant, database
        As :func:`load_scene` (``variant``: the active one unless given).
    sensor : int
        Which of the scene's sensors (views) to render: a basis's own (its manifest's
        ``sensor``), so that the reference compares with its blends pixel for pixel.

    Returns
    -------
    ndarray float32 (H, W, 3)
    """
    pts = _points(x)
    if int(spp) < 1:
        raise MismatchError(f"`spp` must be >= 1, got {spp}")
    loaded = load_scene(
        scene_path,
        manifold_path,
        spp,
        resolution,
        max_depth,
        pts[0],
        variant,
        database,
        sensor=sensor,
    )
    set_points(loaded.targets, pts, targets)
    from ..jobs.interrupt import render_in_passes

    integrator = loaded.integrator.reference(loaded.scene)
    return render_in_passes(
        loaded.scene, integrator, int(spp), int(seed), sensor=int(sensor)
    )  # Ctrl-C: KeyboardInterrupt


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
    pts = _points(x)
    loaded = load_scene(
        scene_path, manifold_path, spp, resolution, max_depth, pts[0], variant, database
    )
    set_points(loaded.targets, pts, targets)
    return loaded.scene, loaded.max_depth


def set_points(found, x, targets=None):
    """Every manifold material ``found`` (:attr:`LoadedScene.targets`) at its latent point: ``x``
    (q,) for all of them, or (p, q) one per target (``targets`` as :func:`scene_at`).
    """
    pts = _points(x)
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


def _points(x):
    """``x`` as a (p, q) array of finite latent points, or the error naming it."""
    pts = np.atleast_2d(np.asarray(x, dtype=np.float64))
    if pts.ndim != 2 or not np.isfinite(pts).all():
        raise MismatchError(
            f"`x` must be finite numbers of shape (q,) or (p, q), got {np.shape(x)}"
        )
    return pts


def check_scene(name, value):
    """A shipped scene's name or a readable scene XML; returns its path. The error names the
    option and the value, and suggests the closest shipped scene names.
    """
    try:
        path = scene_path(value)
        scene_parameters(path)
    except MitsubaManifoldError as e:
        shipped = shipped_scenes()
        hint = did_you_mean(value, shipped) if os.sep not in str(value) else ""
        if os.path.isfile(value):
            raise InputError(f"{name}: {e}") from None
        raise InputError(
            f"{name} {value!r}: no such file nor shipped scene{hint}; shipped scenes: "
            f"{', '.join(shipped)}"
        ) from None
    return path


def check_variant(value, name="`variant`", jit=False):
    """A Mitsuba variant that is installed and renders measured RGB tables.

    Parameters
    ----------
    jit : bool
        Also require a JIT variant (``llvm_*``/``cuda_*``), as the ``manifold_path``
        integrator does (``scalar_rgb`` renders ``manifold_brdf`` but not a basis).
    """
    import mitsuba as mi

    known = list(mi.variants())
    if value not in known:
        raise InputError(
            f"{name} {value!r} is not a Mitsuba variant of this installation "
            f"(installed: {', '.join(known)})"
        )
    rgb = value.endswith("_rgb") and "polarized" not in value
    if not rgb or (jit and not value.startswith(("llvm_", "cuda_"))):
        usable = [
            v
            for v in known
            if v.endswith("_rgb")
            and "polarized" not in v
            and (not jit or v.startswith(("llvm_", "cuda_")))
        ]
        need = "an RGB JIT variant" if jit else "an RGB variant"
        raise InputError(
            f"{name} {value!r} cannot be used here: this needs {need} "
            f"({', '.join(usable) or 'none installed'})"
        )
    if value.startswith("cuda_"):
        import drjit as dr

        try:
            ok = dr.has_backend(dr.JitBackend.CUDA)
        except Exception:
            ok = False
        if not ok:
            raise InputError(f"{name} {value!r} needs a CUDA GPU, and none is usable here")
    return value
