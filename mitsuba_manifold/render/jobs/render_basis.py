"""Render the per-material basis images of a scene (paper Sec. 5.2, Eq. 12-13).

For a scene whose material to edit is a ``manifold_brdf``, the L1- image of any latent
point is ``base + sum_i w_i I_i``: ``base`` holds the paths that never scatter off the
material, ``I_i`` those that scatter off it exactly once with measured material ``i``.
:func:`render_basis` renders ``base.exr`` and one ``<material>.exr`` per requested
material into a folder with a ``manifest.json`` (format in :mod:`mitsuba_manifold.basis.folder`).

With several manifold materials in the scene (one target each, paper Sec. 6) the image
is multilinear in their weights: each image ``<a>+<b>.exr`` is the full L1- image with
target 1 set to material ``a`` and target 2 to ``b``, for every combination asked for.

Rendering is resumable: images already present and valid for the same manifest
settings are kept, every file is written to a temporary name and renamed, and the
manifest is updated after each image, so a killed run continues where it stopped.
"""

import contextlib
import functools
import itertools
import os
import shutil
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Optional, Union

import numpy as np

from ..._util import checks as validate
from ..._util import names as names_mod
from ..._util.cache import file_hash
from ..._util.interrupts import StopRequest
from ..._util.locking import FolderLock
from ..._util.moved import renamed_argument
from ...basis import folder as basis_folder
from ...basis.folder.output import check_foreign_folder, check_job_folders, open_folder
from ...basis.sampling import DEFAULT_SPP
from ...data.database import canonical_spec
from ...errors import InputError, MismatchError, MitsubaManifoldError, did_you_mean
from ...imaging import io as imageio
from ...manifold.model import Manifold
from ..scene import scenes
from ..scene.files import count_sensors
from ..scene.variants import check_variant
from .gi_basis import (
    CROSS_FILE,
    GI_SUFFIX,
    REST_TOL,
    carry_gi,
    describe_components,
    gi_levels,
    progress_bar,
    render_gi,
)
from .interrupt import render_in_passes

if TYPE_CHECKING:
    from typing import Any

    from ...basis.folder.manifest import Manifest


MODES = basis_folder.MODES
#: The former spelling of ``components="full"`` (still read, with a ``DeprecationWarning``).
DEPRECATED_FULL = "auto"

__all__ = [
    "CROSS_FILE",
    "GI_SUFFIX",
    "MODES",
    "REST_TOL",
    "BasisOptions",
    "FullGI",
    "RunBehaviour",
    "Sampling",
    "SceneSetup",
    "Selection",
    "describe_components",
    "check_foreign_folder",
    "check_job_folders",
    "count_sensors",
    "ensure_aovs",
    "plan_views",
    "render_basis",
    "select_materials",
]


def select_materials(manifold, materials="all", near=None, radius=None) -> list:
    """Names of the materials to render, in manifold order.

    Parameters
    ----------
    manifold : Manifold
    materials : "all" or list of str
    near : array_like (q,) or str, optional
        A latent point or a material's name (its point). With ``radius``: only materials
        whose latent point lies within ``radius`` of it, and those the blend at ``near``
        itself needs (kept by the default prune), so that the centre of a basis chosen by
        ``near`` can always be blended.
    """
    if near is not None or radius is not None:
        if near is None or radius is None:
            raise InputError("`near` and `radius` go together")
        near = manifold.point(near, "`near`")
        if not radius > 0:
            raise InputError(f"`radius` must be > 0, got {radius}")
        dist = np.linalg.norm(manifold.latent - near, axis=1)
        if not any(dist <= radius):
            raise InputError(
                f"no material lies within {radius} of {near.tolist()} "
                f"(nearest: {manifold.names[int(dist.argmin())]} at {dist.min():.3g})"
            )
        needed = set(manifold.prune(manifold.weights(near).w).keep.tolist())
        return [
            n for i, (n, dd) in enumerate(zip(manifold.names, dist)) if dd <= radius or i in needed
        ]
    if materials in (None, "all") or materials == ["all"]:
        return list(manifold.names)
    unknown = [m for m in materials if m not in manifold.names]
    if unknown:
        raise InputError(
            f"unknown material(s) {unknown}{did_you_mean(unknown[0], manifold.names)}: the "
            f"manifold has {manifold.n} materials ({', '.join(manifold.names[:6])}"
            f"{', ...' if manifold.n > 6 else ''})"
        )
    wanted = set(materials)
    return [n for n in manifold.names if n in wanted]


@dataclass(frozen=True)
class Selection:
    """Which materials are rendered (:func:`select_materials`).

    Parameters
    ----------
    materials : "all" or list of str
    near, radius
        With both: the materials within ``radius`` of the latent point ``near`` (and those
        the blend at ``near`` needs).
    """

    materials: Union[str, Sequence[str]] = "all"
    near: Optional[Sequence[float]] = None
    radius: Optional[float] = None


@dataclass(frozen=True)
class Sampling:
    """How the images are sampled.

    Parameters
    ----------
    spp : int
        Samples per pixel of every image.
    seed : int
        Same seed for every image (correlated noise makes blends smoother).
    mode : {"per-material", "onepass"}
        One render per material, or all materials from one set of paths
        (:meth:`ManifoldPathIntegrator.render_onepass`, one target only).
    chunk_spp : int, optional
        Samples per pixel per pass of the one-pass renderer.
    """

    spp: int = 64
    seed: int = 0
    mode: str = "per-material"
    chunk_spp: Optional[int] = None


@dataclass(frozen=True)
class SceneSetup:
    """How the scene is loaded (:func:`scenes.load_scene`).

    Parameters
    ----------
    resolution : int or (int, int), optional
        Image size, for scenes that take ``$res`` or ``$width``/``$height``.
    max_depth : int, optional
        Path depth (-1: unbounded), overriding the scene's integrator; default: the scene's own
        (:func:`scenes.scene_integrator`). The basis renders what the scene's integrator does:
        its type (``path`` and the unbiased path tracers; ``direct`` as ``path`` of depth 2),
        ``max_depth``, ``rr_depth`` and ``hide_emitters``; other integrators are refused before
        anything is rendered.
    variant : str, optional
        Mitsuba variant, activated (default: the active one, or :func:`scenes.default_variant`
        when none is active; see :func:`scenes.use_variant`). It must be a JIT RGB variant.
    x : array_like (q,) or str, optional
        The scene's ``$x``, a latent point or a material's name (default: the first
        material's latent point, which fits any manifold whatever its latent dimension).
    database : str, optional
        Folder of the manifold's tables, if it moved.
    sensor : int
        Which of the scene's sensors (views) to render (recorded in the manifest).
    """

    resolution: Optional[Union[int, tuple[int, int]]] = None
    max_depth: Optional[int] = None
    variant: Optional[str] = None
    x: Optional[Sequence[float]] = None
    database: Optional[str] = None
    sensor: int = 0


@dataclass(frozen=True)
class FullGI:
    """The full-GI part of a one-pass basis.

    Parameters
    ----------
    components : {"full", "l1"}
        The components of the image the basis holds (see the glossary). ``"full"`` (one-pass
        mode): all light, so also the full-GI images (``touch + L2+`` of every material,
        :func:`~.integrators.onepass.render_onepass_gi`) and the cross terms of the pairs blended
        together (:mod:`mitsuba_manifold.basis.crossterms`), left out (and said why in the
        manifest's ``left_out``) where the scene does not need them: L2+ below
        :data:`REST_TOL` of the material's light (a convex object alone: exactly 0). ``"l1"``:
        the L1- basis only. Per-material mode renders L1- only. ``"auto"``, this value's former
        spelling, is read as ``"full"`` with a ``DeprecationWarning``.
    levels : int, optional
        Most vertices on the material per path in the L2+ images (more are cut, counted in
        ``gi_stats``); default: all a path of ``max_depth`` can have (:data:`.gi_basis.MAX_LEVELS`
        if unbounded); the light each cut level loses is in ``docs/benchmarks.md``.
    cross_tol : float
        Smallest weight product of a candidate pair (one that some explored point blends).
    cross_light_tol : float
        Of the candidates, a cross term is stored when leaving it out could change the ``L2+``
        light of its pair by at least this share, weight product included, measured on the
        first pass (:class:`~.integrators.multisplats.PairSelection`); 0 stores every candidate.
    cross_fraction : float
        Share of the splats the cross terms use (unbiased; bounds their cost, but below 1 the
        per-path cancellation between the cross terms and the ``L2+`` images is lost and a
        midpoint of white-paint and blue-rubber takes the noise of white-paint's ``L2+``: a
        cross term enters a blend with weight ``w_i w_j <= 1/4``, so its noise matters less).
    cross_keep : list of (str, str), optional
        Store exactly these pairs (names) instead of choosing them on the first pass: the
        chunks of a chunked basis keep the pairs its first chunk chose.
    """

    components: str = "l1"
    levels: Optional[int] = None
    cross_tol: float = 1e-3
    cross_light_tol: float = 0.005
    cross_fraction: float = 1.0
    cross_keep: Optional[Sequence[tuple[str, str]]] = None

    def __post_init__(self) -> None:
        if self.components == DEPRECATED_FULL:
            warnings.warn(
                f"`components={DEPRECATED_FULL!r}` is now spelled `components='full'` (all light: "
                "the full-GI images where the scene needs them); the old spelling goes in the next "
                "release",
                DeprecationWarning,
                stacklevel=3,
            )
            object.__setattr__(self, "components", "full")


@dataclass(frozen=True)
class RunBehaviour:
    """How the run behaves towards its folder and its user.

    Parameters
    ----------
    force : bool
        Render into an existing ``out`` that holds files but no basis manifest
        (:func:`check_foreign_folder`), and overwrite files in ``out`` that this basis did not make.
    progress : bool
        Progress bar with ETA.
    aovs : bool
        Also write the denoising guides ``aovs.npz`` (:func:`guides.add_aovs`; one target).
    """

    force: bool = False
    progress: bool = False
    aovs: bool = False


@dataclass(frozen=True)
class BasisOptions:
    """How :func:`render_basis` renders a basis, in five groups (a field not set keeps its
    group's default); :meth:`updated` sets fields by their names, the keywords of
    :func:`render_basis`.

    Parameters
    ----------
    selection : Selection
        Which materials.
    sampling : Sampling
        Samples per pixel, seed, mode.
    scene : SceneSetup
        How the scene is loaded: resolution, depth, variant, ``$x``, database, sensor.
    gi : FullGI
        The full-GI images and cross terms of a one-pass basis.
    run : RunBehaviour
        Folder and progress.
    """

    selection: Selection = field(default_factory=Selection)
    sampling: Sampling = field(default_factory=Sampling)
    scene: SceneSetup = field(default_factory=SceneSetup)
    gi: FullGI = field(default_factory=FullGI)
    run: RunBehaviour = field(default_factory=RunBehaviour)

    def updated(self, **settings) -> "BasisOptions":
        """These options with ``settings`` changed: fields of the groups by their own names
        (``spp=64``, ``mode="onepass"``), or whole groups (``gi=FullGI(...)``).

        Raises
        ------
        TypeError
            A name that is neither a field of a group nor a group.
        """
        groups: dict[str, dict] = {g: {} for g in _GROUPS}
        whole = {}
        for name, value in settings.items():
            if name in _GROUPS:
                whole[name] = value
            elif name in _GROUP_OF:
                groups[_GROUP_OF[name]][name] = value
            else:
                raise TypeError(
                    f"render_basis() got an unexpected keyword argument {name!r}; "
                    f"the options are {', '.join(sorted(_GROUP_OF))}"
                )
        out = replace(self, **whole)
        return replace(out, **{g: replace(getattr(out, g), **kw) for g, kw in groups.items() if kw})

    def keywords(self, *names) -> dict:
        """The fields ``names`` (default all) as ``{name: value}``: the keywords of :func:`render_basis`."""
        names = names or tuple(_GROUP_OF)
        return {n: getattr(getattr(self, _GROUP_OF[n]), n) for n in names}


#: The groups of :class:`BasisOptions` and, for each field of a group, its group.
_GROUPS = {f.name: f.default_factory for f in fields(BasisOptions)}
_GROUP_OF = {f.name: g for g, cls in _GROUPS.items() for f in fields(cls)}


def render_basis(scene=None, manifold=None, out=None, options=None, **settings) -> "Manifest":  # noqa: C901  the images planned in one place, before the lock
    """Render ``base.exr`` and the per-material images of ``scene`` into ``out``.

    Ctrl-C (SIGINT) stops the render at the end of the current pass (renders are cut into
    passes of :data:`interrupt.SAMPLES_PER_PASS` paths) and raises ``KeyboardInterrupt``;
    every image listed in the manifest is then complete.

    Parameters
    ----------
    scene : str
        The scene: an XML file or a shipped scene's name (``scene_path``, its former name, is
        read with a ``DeprecationWarning``).
    manifold : str
        The manifold file (``manifold_path``, its former name, likewise).
    out : str
        Folder (created; resumed when it holds a basis with the same settings). It is
        locked (:class:`FolderLock`) while the images are written.
    options : BasisOptions, optional
        How to render (default: :class:`BasisOptions`'s defaults).
    **settings
        Fields of the groups of :class:`BasisOptions` by name (``render_basis(scene, manifold,
        out, spp=64, mode="onepass")``), which override those of ``options``
        (:meth:`BasisOptions.updated`).

    Returns
    -------
    Manifest
        The manifest written.

    Raises
    ------
    TypeError
        A keyword that is no field of :class:`BasisOptions`.
    MitsubaManifoldError
        An option (:class:`InputError`), the scene, the manifold or the folder at fault, raised
        before anything is rendered.
    """
    scene_path = renamed_argument(scene, settings, "scene_path", "scene", "render_basis")
    manifold_path = renamed_argument(
        manifold, settings, "manifold_path", "manifold", "render_basis"
    )
    if out is None:
        raise TypeError("render_basis() missing its argument `out` (the basis folder)")
    o = (options or BasisOptions()).updated(**settings)
    scene_path, manifold, chosen, x = _check_request(scene_path, manifold_path, out, o)
    mi = scenes.use_variant(o.scene.variant, jit=True)
    loaded = scenes.load_scene(
        scene_path,
        manifold_path,
        o.sampling.spp,
        o.scene.resolution,
        o.scene.max_depth,
        x=x,
        database=o.scene.database,
        sensor=int(o.scene.sensor),
    )
    (scene, targets, max_depth), paths = loaded, loaded.integrator
    if o.sampling.mode == "onepass" and len(targets) != 1:
        raise InputError(
            f"onepass mode renders scenes with one manifold material; {scene_path} has "
            f"{len(targets)}: use `mode` 'per-material'"
        )
    sensors = scene.sensors()
    if not 0 <= int(o.scene.sensor) < len(sensors):
        raise InputError(
            f"`sensor` {o.scene.sensor} does not exist: {scene_path} has {len(sensors)} sensor(s)"
        )
    size = scenes.image_size(sensors[int(o.scene.sensor)].film())  # the crop window's
    manifest = basis_folder.Manifest.new(
        scene_path,
        manifold_path,
        basis_folder.RenderSettings(
            resolution=size,
            spp=o.sampling.spp,
            variant=mi.variant(),
            seed=o.sampling.seed,
            max_depth=max_depth,
            mode=o.sampling.mode,
            sensor=int(o.scene.sensor),
        ),
        targets=[b.id() for b in targets],
    )
    manifest.integrator = paths.to_manifest()
    manifest.scene_resolution = (
        None if o.scene.resolution is None else list(_size(o.scene.resolution))
    )
    scatters_twice = (
        max_depth < 0 or max_depth > 2
    )  # depth 2 (direct): one scattering vertex per path
    gi = o.sampling.mode == "onepass" and o.gi.components == "full" and scatters_twice
    if gi:
        o = o.updated(levels=gi_levels(o.gi.levels, max_depth))
        manifest.levels = o.gi.levels
    elif o.sampling.mode == "onepass" and o.gi.components == "full":
        manifest.left_out = {
            "l2+": f"the scene's paths scatter once at most ({paths.describe()}): "
            "its L1- images are its full-GI images"
        }
    else:
        manifest.left_out = {
            "l2+": "per-material mode renders L1- images only"
            if o.sampling.mode != "onepass"
            else "components 'l1' asked for"
        }
    if len(targets) == 1:
        jobs = [(basis_folder.BASE, None)] + [
            (basis_folder.image_key([name]), (name,)) for name in chosen
        ]
    else:
        jobs = [
            (basis_folder.image_key(combo), combo)
            for combo in itertools.product(chosen, repeat=len(targets))
        ]
    files = [key + ".exr" for key, _ in jobs] + [basis_folder.MANIFEST]
    if gi:
        files += [key + GI_SUFFIX for key, combo in jobs if combo is not None] + [CROSS_FILE]
    if os.path.isdir(out):  # refuse before locking: a refused run adds nothing to the folder
        open_folder(out, manifest, files, o.run.force, read_images=False)
    with _removed_if_nothing_made(out), FolderLock(out, "basis folder"), StopRequest() as stop:
        manifest.images = open_folder(out, manifest, files, o.run.force)
        if gi:
            carry_gi(out, manifest)
        manifest.write(out)
        todo = [(key, combo) for key, combo in jobs if key not in manifest.images]
        if gi and (
            todo
            or (
                "l2+" in manifest.held_components
                and any(
                    key not in (manifest.gi_images or {})
                    for key, combo in jobs
                    if combo is not None
                )
            )
        ):
            todo = jobs  # the full-GI images and cross terms come from one pass over every material
        save = functools.partial(_save, out, manifest)
        if todo and gi:
            render_gi(scene, manifold, todo, o, paths, out, manifest, save, stop)
            if o.run.progress:
                print(describe_components(manifest))
        elif todo and o.sampling.mode == "onepass":
            _render_onepass(scene, targets[0], todo, o, paths, save, stop)
        elif todo:
            _render_each(scene, targets, todo, o, paths, save, stop)
        del scene, loaded, targets, paths, sensors  # the AOVs load the scene again
        scenes.release_render_memory()
        if o.run.aovs:
            ensure_aovs(out, manifest)
            scenes.release_render_memory()
    return manifest


@contextlib.contextmanager
def _removed_if_nothing_made(out):
    """A folder this run creates is removed again if the run fails before its first image (a bad
    table): nothing but its manifest would be left. Ctrl-C keeps it: the same command resumes.
    """
    created = not os.path.exists(out)
    try:
        yield
    except Exception:
        if created and os.path.isdir(out) and set(os.listdir(out)) <= {basis_folder.MANIFEST}:
            shutil.rmtree(out, ignore_errors=True)
        raise


def _check_request(scene_path, manifold_path, out, o) -> "tuple[Any, Manifold, list, Any]":
    """Everything :func:`render_basis` can check before loading the scene; returns the scene's
    path, the manifold, the materials chosen and the latent point ``x`` (or None).
    """
    if o.sampling.mode not in MODES:
        raise InputError(f"`mode` must be one of {MODES}, got {o.sampling.mode!r}")
    if o.gi.components not in ("full", "l1"):
        raise InputError(
            f"`components` must be 'full' (full GI where the scene needs it) or 'l1', got {o.gi.components!r}"
        )
    if int(o.sampling.spp) < 1:
        raise InputError(f"`spp` must be >= 1, got {o.sampling.spp}")
    gi_levels(o.gi.levels, -1)  # checked
    if o.scene.variant is not None:
        check_variant(o.scene.variant, jit=True)
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"`out` {out} is a file, not a folder")
    manifold = Manifold.load(manifold_path)
    if o.scene.database is not None:  # moved tables: the weights beyond the data read them too
        manifold.database = canonical_spec(o.scene.database, "`database`")
    x = None if o.scene.x is None else manifold.point(o.scene.x, "`x`")
    chosen = select_materials(manifold, o.selection.materials, o.selection.near, o.selection.radius)
    try:
        names_mod.check_unique(chosen)
    except InputError as e:
        raise InputError(str(e)) from None
    try:
        scene_path = scenes.scene_path(
            scene_path
        )  # a scene XML, or a shipped scene's name ("table")
    except MitsubaManifoldError as e:
        raise InputError(str(e)) from None
    if (
        o.scene.resolution is not None
    ):  # images held at once: all of them in one pass, else a film and two sums
        w, h = _size(o.scene.resolution)
        held = len(chosen) + 2 if o.sampling.mode == "onepass" else 6
        validate.fits_in_memory(
            "`resolution`", 2 * held * w * h * 3 * 4, f"{o.sampling.mode} images of {w}x{h}"
        )
    return scene_path, manifold, chosen, x


def _save(out, manifest, images, seconds, section="images", suffix=".exr") -> None:
    """Write ``{key: image}`` into ``out`` (EXR files in parallel), then list them in the
    :class:`Manifest`'s ``section`` (``"images"``, or ``"gi_images"`` with ``suffix``
    :data:`GI_SUFFIX`).

    The files are first listed as ``pending``: a run killed between writing a file
    and listing it leaves a file its resume knows to be its own.
    """
    from concurrent.futures import ThreadPoolExecutor

    manifest.pending = sorted(key + suffix for key in images)
    manifest.write(out)
    with ThreadPoolExecutor(min(len(images), os.cpu_count() or 1)) as pool:  # OpenEXR drops the GIL
        list(
            pool.map(
                lambda kv: imageio.write_exr(os.path.join(out, kv[0] + suffix), kv[1]),
                images.items(),
            )
        )
    entries = manifest.section(section)
    for (
        key
    ) in images:  # each file's hash: an image edited later is found (open_folder, Basis.image)
        entries[key] = basis_folder.ImageEntry(
            file=key + suffix,
            time_s=float(seconds),
            sha256=file_hash(os.path.join(out, key + suffix)),
        )
    manifest.pending = None
    manifest.write(out)


def ensure_aovs(out, manifest, spp=16) -> None:
    """Write ``out/aovs.npz`` (:mod:`~mitsuba_manifold.render.jobs.guides`) unless one made for this basis is there."""
    from . import guides

    try:
        guides.BasisAOVs.load(out, manifest)
    except MismatchError:
        guides.add_aovs(out, spp=spp)


def _size(resolution) -> tuple:
    """``(width, height)`` of a ``resolution`` option (a square's side, or the pair)."""
    return (int(resolution),) * 2 if np.isscalar(resolution) else tuple(int(v) for v in resolution)


def _integrator(component, paths, target="all"):
    """A ``manifold_path`` of ``component`` rendering the paths of the scene's integrator
    (:class:`~.scenes.SceneIntegrator` ``paths``: depth, Russian roulette, emitters hidden).
    """
    import mitsuba as mi

    return mi.load_dict(
        {
            "type": "manifold_path",
            "component": component,
            "target": target,
            **paths.path_properties(),
        }
    )


def _bar(total, enabled, desc):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="image", disable=not enabled)


def _render_each(scene, targets, todo, o, paths, save, stop) -> None:
    """One render per image: base (component 'base'), then 'touch' per material or 'l1' per combination."""
    spp, seed, sensor = o.sampling.spp, o.sampling.seed, int(o.scene.sensor)
    single = len(targets) == 1
    touch = _integrator("touch", paths)
    l1 = _integrator("l1", paths, target=",".join(b.id() for b in targets)) if not single else None
    with _bar(len(todo), o.run.progress, "rendering basis") as bar:
        for key, combo in todo:
            t0 = time.perf_counter()
            if combo is None:
                img = render_in_passes(scene, _integrator("base", paths), spp, seed, stop, sensor)
            else:
                for bsdf, name in zip(targets, combo):
                    bsdf.set_material(name)
                img = render_in_passes(scene, touch if single else l1, spp, seed, stop, sensor)
            save({key: img}, time.perf_counter() - t0)
            bar.set_postfix_str(key)
            bar.update()


def _render_onepass(scene, target, todo, o, paths, save, stop) -> None:
    """All material images from one set of paths; base comes from the same paths."""
    integrator = _integrator("l1", paths)
    names = [combo[0] for key, combo in todo if combo is not None]
    keys = {combo[0]: key for key, combo in todo if combo is not None}
    t0 = time.perf_counter()
    with progress_bar("rendering basis (one pass)", o.run.progress, stop) as advance:
        kwargs = {
            "materials": names,
            "spp": o.sampling.spp,
            "seed": o.sampling.seed,
            "progress": advance,
            "sensor": int(o.scene.sensor),
        }
        if o.sampling.chunk_spp:
            kwargs["spp_per_pass"] = o.sampling.chunk_spp
        base, images = integrator.render_onepass(scene, **kwargs)
    seconds = (time.perf_counter() - t0) / max(len(todo), 1)
    out = {keys[name]: np.asarray(images[name], dtype=np.float32)[..., :3] for name in names}
    if any(combo is None for _, combo in todo):
        out[basis_folder.BASE] = np.asarray(base, dtype=np.float32)[..., :3]
    save(out, seconds)


def view_spp(jobs, spp=None) -> dict:
    """Samples per pixel of each view of ``jobs`` (:func:`plan_views`): ``spp`` where given,
    else the scene's own for that sensor, else :data:`DEFAULT_SPP`.
    """
    from ..scene.scenes import scene_sample_count

    return {
        (scene, sensor): spp or scene_sample_count(scene, sensor) or DEFAULT_SPP
        for scene, sensor, _ in jobs
    }


def plan_views(scenes, views, out) -> list:
    """``(scene, sensor, folder)`` for each scene and view asked for.

    One scene and one view render into ``out``; otherwise each basis goes to
    ``out/<scene name>`` (one view) or ``out/<scene name>-view<j>``.

    Parameters
    ----------
    scenes : list of str
    views : "all" or list of int
        Sensor indices (``all``: every sensor of each scene).
    out : str
    """
    jobs = []
    for scene in scenes:
        n = count_sensors(scene)
        chosen = list(range(n)) if views == "all" else [int(v) for v in views]
        bad = [v for v in chosen if not 0 <= v < n]
        if bad:
            raise InputError(
                f"sensor {bad[0]} does not exist: {scene} has {n} sensor(s) "
                f"(`views` takes indices 0..{n - 1} or 'all')"
            )
        jobs += [(scene, v, len(chosen)) for v in chosen]
    stems = [os.path.splitext(os.path.basename(s))[0] for s in scenes]
    if len(set(stems)) != len(stems):
        raise InputError(f"scenes {list(scenes)} share a file name; render them in separate calls")
    if len(jobs) == 1:
        return [(jobs[0][0], jobs[0][1], os.fspath(out))]
    return [
        (
            scene,
            v,
            os.path.join(
                os.fspath(out),
                os.path.splitext(os.path.basename(scene))[0] + (f"-view{v}" if n > 1 else ""),
            ),
        )
        for scene, v, n in jobs
    ]
