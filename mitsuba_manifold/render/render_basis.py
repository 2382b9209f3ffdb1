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

import itertools
import os
import re
import time

import numpy as np

from ..basis import folder as basis_folder
from ..imaging import io as imageio
from .._util import names as names_mod, ownership, checks as validate
from . import scenes
from ..errors import FormatError, InputError, MismatchError, MitsubaManifoldError, did_you_mean
from .interrupt import StopRequest, render_in_passes
from .chunks import CHUNK_DIR
from .._util.locking import LOCK_NAME, FolderLock
from .scenes import check_variant, default_variant
from ..manifold.model import Manifold

MODES = basis_folder.MODES


def select_materials(manifold, materials="all", near=None, radius=None):
    """Names of the materials to render, in manifold order.

    Parameters
    ----------
    manifold : Manifold
    materials : "all" or list of str
    near : array_like (q,), optional
        With ``radius``: only materials whose latent point lies within ``radius`` of it, and
        those the blend at ``near`` itself needs (kept by the default prune), so that the
        centre of a ``--near`` basis can always be blended.
    """
    if near is not None or radius is not None:
        if near is None or radius is None:
            raise InputError("--near and --radius go together")
        near = np.asarray(near, dtype=np.float64).ravel()
        if near.size != manifold.q or not np.isfinite(near).all():
            raise InputError(f"--near must be {manifold.q} finite numbers (the manifold's latent "
                                   f"dimension), got {near.tolist()}")
        if not radius > 0:
            raise InputError(f"--radius must be > 0, got {radius}")
        dist = np.linalg.norm(manifold.latent - near, axis=1)
        if not any(dist <= radius):
            raise InputError(f"no material lies within {radius} of {near.tolist()} "
                                   f"(nearest: {manifold.names[int(dist.argmin())]} at {dist.min():.3g})")
        needed = set(manifold.prune(manifold.weights(near).w).keep.tolist())
        return [n for i, (n, dd) in enumerate(zip(manifold.names, dist)) if dd <= radius or i in needed]
    if materials in (None, "all") or materials == ["all"]:
        return list(manifold.names)
    unknown = [m for m in materials if m not in manifold.names]
    if unknown:
        raise InputError(f"unknown material(s) {unknown}{did_you_mean(unknown[0], manifold.names)}: the "
                               f"manifold has {manifold.n} materials ({', '.join(manifold.names[:6])}"
                               f"{', ...' if manifold.n > 6 else ''})")
    wanted = set(materials)
    return [n for n in manifold.names if n in wanted]


#: What a basis run leaves in its folder before its manifest: the lock, chunk folders,
#: temporary files of atomic writes killed with the process (:mod:`atomic`).
_OWN = re.compile(r"^(?:" + re.escape(LOCK_NAME) + "|" + re.escape(CHUNK_DIR) + r"|\..+\.tmp\.(?:exr|json|npz))$")


def check_foreign_folder(out, force=False, bases=None):
    """Refuse (unless ``force``) an existing ``out`` that holds files and no basis manifest:
    a folder of the user's (a database, blends), which a basis would fill with images that
    no blend may then be written beside. With ``bases`` (the names of the basis folders
    to render in it), ``out`` is the parent of several bases and may hold only bases."""
    if not os.path.isdir(out) or force or (bases is None and os.path.lexists(os.path.join(out, basis_folder.MANIFEST))):
        return
    foreign = sorted(f for f in os.listdir(out) if not _OWN.match(f) and (
        bases is None or f not in bases and not basis_folder.is_basis_folder(os.path.join(out, f))))
    if foreign:
        what = f"not a basis folder (no {basis_folder.MANIFEST})" if bases is None else "not a folder of bases"
        raise InputError(
            f"{out} is {what} and holds files render_basis did not make ({', '.join(foreign[:3])}"
            f"{' ...' if len(foreign) > 3 else ''}); choose a new or empty folder, or add --force")


def check_job_folders(jobs, out, force=False):
    """Before the first render: every folder of :func:`plan_views`'s ``jobs`` and, for
    several, their parent ``out`` (:func:`check_foreign_folder`)."""
    if len(jobs) > 1:
        check_foreign_folder(os.fspath(out), force, bases={os.path.basename(folder) for _, _, folder in jobs})
    for _, _, folder in jobs:
        check_foreign_folder(folder, force)


def _open_folder(out, manifest, files, force=False, read_images=True):
    """Check ``out`` (locked by the caller) against ``manifest``; return the images still valid
    (all those listed without ``read_images``).

    A folder whose manifest has other settings is refused, unless it lists no image yet
    (nothing to lose). Files the run would write (``files``) that exist without being
    listed in the manifest are the user's: refused unless ``force``. Files the manifest
    lists as ``pending`` were being written by a run that was killed: they are this tool's,
    and are removed when ``read_images`` (the locked call) so they are rendered again.
    """
    check_foreign_folder(out, force)
    old = None
    listed = set()
    if os.path.exists(os.path.join(out, basis_folder.MANIFEST)):
        old = basis_folder.read_manifest(out)   # raises unless it is a basis manifest
        old = basis_folder.upgrade_manifest(old, manifest["manifold"])   # resume a version-1 basis
        listed.add(basis_folder.MANIFEST)
        listed |= _clear_pending(out, old, remove=read_images)
        diff = basis_folder.manifest_differences(old, manifest)
        if diff and old["images"]:
            raise InputError(
                f"{out} holds a basis made with other settings ({', '.join(diff)} differ); "
                "choose another folder or delete it")
        if diff:
            old = None
    listed |= {e["file"] for e in old["images"].values()} if old else set()
    foreign = sorted(f for f in files if f not in listed and os.path.lexists(os.path.join(out, f)))
    if foreign and not force:
        raise InputError(
            f"{out} holds files this basis did not make and would overwrite: {', '.join(foreign[:5])}"
            f"{' ...' if len(foreign) > 5 else ''}; choose another folder, or add --force")
    for f in foreign:
        if ownership.read_only(os.path.join(out, f)):
            raise InputError(f"{os.path.join(out, f)} is read-only; not replacing it")
    if old is None:
        return {}
    if not read_images:
        return dict(old["images"])
    kept = {}
    w, h = manifest["resolution"]
    for key, entry in old["images"].items():
        path = os.path.join(out, entry["file"])
        try:
            imageio.check_exr_header(path, (w, h))
            imageio.read_exr(path)  # a killed writer never leaves a partial file, but check anyway
        except (FormatError, OSError):
            continue
        kept[key] = entry
    return kept


def _clear_pending(out, old, remove):
    """The files ``old`` lists as pending and not as images (a killed run's); removed when
    ``remove`` (a read-only one is left, and then refused as the user's)."""
    done = {e["file"] for e in old["images"].values()}
    pending = {f for f in old.get("pending", []) if f not in done}
    for f in pending if remove else ():
        path = os.path.join(out, f)
        if os.path.lexists(path) and not ownership.read_only(path):
            os.remove(path)
    return {f for f in pending if not ownership.read_only(os.path.join(out, f))}


def render_basis(scene_path, manifold_path, out, spp=64, materials="all", near=None, radius=None,
                 mode="per-material", seed=0, resolution=None, max_depth=None, variant=None,
                 progress=False, chunk_spp=None, x=None, database=None, force=False, sensor=0, aovs=False):
    """Render ``base.exr`` and the per-material images of ``scene_path`` into ``out``.

    Parameters
    ----------
    scene_path, manifold_path : str
    out : str
        Folder (created; resumed when it holds a basis with the same settings). It is
        locked (:class:`FolderLock`) while the images are written.
    spp : int
        Samples per pixel of every image.
    materials, near, radius
        Selection, see :func:`select_materials`.
    mode : {"per-material", "onepass"}
        One render per material, or all materials from one set of paths
        (:meth:`ManifoldPathIntegrator.render_onepass`, one target only).
    seed : int
        Same seed for every image (correlated noise makes blends smoother).
    resolution : int or (int, int), optional
        Image size, for scenes that take ``$res`` or ``$width``/``$height``.
    max_depth : int, optional
        Path depth (-1: unbounded; default: the scene's ``$max_depth`` default, else -1).
    variant : str, optional
        Mitsuba variant (default: the active one, else CUDA when available, else LLVM).
    progress : bool
        Progress bar with ETA.
    x : array_like (q,), optional
        The scene's ``$x`` (default: the first material's latent point, which fits any
        manifold whatever its latent dimension).
    database : str, optional
        Folder of the manifold's tables, if it moved (:func:`scenes.load_scene`).
    force : bool
        Render into an existing ``out`` that holds files but no basis manifest
        (:func:`check_foreign_folder`), and overwrite files in ``out`` that this basis did not make.
    chunk_spp : int, optional
        Samples per pixel per pass of the one-pass renderer.
    sensor : int
        Which of the scene's sensors (views) to render (recorded in the manifest when not 0).
    aovs : bool
        Also write the denoising guides ``aovs.npz`` (:func:`guides.add_aovs`; one target).

    Ctrl-C (SIGINT) stops the render at the end of the current pass (renders are cut into
    passes of :data:`interrupt.SAMPLES_PER_PASS` paths) and raises ``KeyboardInterrupt``;
    every image listed in the manifest is then complete.

    Returns
    -------
    dict
        The manifest written.
    """
    import mitsuba as mi

    if mode not in MODES:
        raise InputError(f"mode must be one of {MODES}, got {mode!r}")
    if int(spp) < 1:
        raise InputError(f"spp must be >= 1, got {spp}")
    if variant is not None:
        check_variant(variant, jit=True)
    if os.path.exists(out) and not os.path.isdir(out):
        raise InputError(f"output folder {out} is a file")
    manifold = Manifold.load(manifold_path)
    if x is not None:
        x = validate.latent_point("--x", x, manifold.q)
    chosen = select_materials(manifold, materials, near, radius)
    try:
        names_mod.check_unique(chosen)
    except InputError as e:
        raise InputError(str(e)) from None
    try:
        scene_path = scenes.scene_path(scene_path)   # a scene XML, or a shipped scene's name ("table")
    except MitsubaManifoldError as e:
        raise InputError(str(e)) from None
    if resolution is not None:  # images held at once: all of them in one pass, else a film and two sums
        w, h = (int(resolution),) * 2 if np.isscalar(resolution) else (int(v) for v in resolution)
        held = len(chosen) + 2 if mode == "onepass" else 6
        validate.fits_in_memory("resolution", 2 * held * w * h * 3 * 4, f"{mode} images of {w}x{h}")
    scene, targets, max_depth = scenes.load_scene(scene_path, manifold_path, spp, resolution, max_depth,
                                                     x=x, variant=variant or mi.variant() or default_variant(),
                                                     database=database)
    if mode == "onepass" and len(targets) != 1:
        raise InputError(f"onepass mode renders scenes with one manifold material; {scene_path} has "
                               f"{len(targets)}: use --mode per-material (mode='per-material' in Python)")
    sensors = scene.sensors()
    if not 0 <= int(sensor) < len(sensors):
        raise InputError(f"sensor {sensor} does not exist: {scene_path} has {len(sensors)} sensor(s)")
    size = tuple(int(v) for v in sensors[int(sensor)].film().size())
    manifest = basis_folder.make_manifest(scene_path, manifold_path, size, spp, mi.variant(), seed, max_depth,
                                       mode, [b.id() for b in targets])
    if int(sensor):
        manifest["sensor"] = int(sensor)
    if len(targets) == 1:
        jobs = [(basis_folder.BASE, None)] + [(basis_folder.image_key([name]), (name,)) for name in chosen]
    else:
        jobs = [(basis_folder.image_key(combo), combo) for combo in itertools.product(chosen, repeat=len(targets))]
    files = [key + ".exr" for key, _ in jobs] + [basis_folder.MANIFEST]
    if os.path.isdir(out):  # refuse before locking: a refused run adds nothing to the folder
        _open_folder(out, manifest, files, force, read_images=False)
    with FolderLock(out, "basis folder"), StopRequest() as stop:
        manifest["images"] = _open_folder(out, manifest, files, force)
        basis_folder.write_manifest(out, manifest)
        todo = [(key, combo) for key, combo in jobs if key not in manifest["images"]]

        def save(images, seconds):
            """Write ``{key: image}`` (EXR files in parallel), then list them in the manifest.

            The files are first listed as ``pending``: a run killed between writing a file
            and listing it leaves a file its resume knows to be its own."""
            from concurrent.futures import ThreadPoolExecutor
            manifest["pending"] = sorted(key + ".exr" for key in images)
            basis_folder.write_manifest(out, manifest)
            with ThreadPoolExecutor(min(len(images), os.cpu_count() or 1)) as pool:  # OpenEXR drops the GIL
                list(pool.map(lambda kv: imageio.write_exr(os.path.join(out, kv[0] + ".exr"), kv[1]),
                              images.items()))
            for key in images:
                manifest["images"][key] = {"file": key + ".exr", "time_s": float(seconds)}
            del manifest["pending"]
            basis_folder.write_manifest(out, manifest)

        if todo and mode == "onepass":
            _render_onepass(scene, targets[0], todo, spp, seed, max_depth, save, progress, chunk_spp, stop,
                            int(sensor))
        elif todo:
            _render_each(scene, targets, todo, spp, seed, max_depth, save, progress, stop, int(sensor))
        if aovs:
            ensure_aovs(out, manifest)
    return manifest


def ensure_aovs(out, manifest, spp=16):
    """Write ``out/aovs.npz`` (:mod:`~mitsuba_manifold.render.guides`) unless one made for this basis is there."""
    from . import guides
    try:
        guides.BasisAOVs.load(out, manifest)
    except MismatchError:
        guides.add_aovs(out, spp=spp)


def _integrator(component, max_depth, target="all"):
    import mitsuba as mi
    return mi.load_dict({"type": "manifold_path", "component": component, "max_depth": int(max_depth),
                         "target": target})


def _bar(total, enabled, desc):
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="image", disable=not enabled)


def _render_each(scene, targets, todo, spp, seed, max_depth, save, progress, stop, sensor=0):
    """One render per image: base (component 'base'), then 'touch' per material or 'l1' per combination."""
    single = len(targets) == 1
    touch = _integrator("touch", max_depth)
    l1 = _integrator("l1", max_depth, target=",".join(b.id() for b in targets)) if not single else None
    with _bar(len(todo), progress, "rendering basis") as bar:
        for key, combo in todo:
            t0 = time.perf_counter()
            if combo is None:
                img = render_in_passes(scene, _integrator("base", max_depth), spp, seed, stop, sensor)
            else:
                for bsdf, name in zip(targets, combo):
                    bsdf.set_material(name)
                img = render_in_passes(scene, touch if single else l1, spp, seed, stop, sensor)
            save({key: img}, time.perf_counter() - t0)
            bar.set_postfix_str(key)
            bar.update()


def _render_onepass(scene, target, todo, spp, seed, max_depth, save, progress, chunk_spp, stop, sensor=0):
    """All material images from one set of paths (issue 5); base comes from the same paths."""
    from tqdm import tqdm
    integrator = _integrator("l1", max_depth)
    names = [combo[0] for key, combo in todo if combo is not None]
    keys = {combo[0]: key for key, combo in todo if combo is not None}
    t0 = time.perf_counter()
    with tqdm(desc="rendering basis (one pass)", unit="step", disable=not progress) as bar:
        def advance(done, total):
            stop.check()
            bar.total = total
            bar.update(done - bar.n)
        kwargs = {"materials": names, "spp": spp, "seed": seed, "progress": advance, "sensor": sensor}
        if chunk_spp:
            kwargs["spp_per_pass"] = chunk_spp
        base, images = integrator.render_onepass(scene, **kwargs)
    seconds = (time.perf_counter() - t0) / max(len(todo), 1)
    out = {keys[name]: np.asarray(images[name], dtype=np.float32)[..., :3] for name in names}
    if any(combo is None for _, combo in todo):
        out[basis_folder.BASE] = np.asarray(base, dtype=np.float32)[..., :3]
    save(out, seconds)


def count_sensors(scene_path):
    """Sensors (views) declared at the top level of a scene XML."""
    return len(validate.scene_xml(scene_path).findall("sensor"))   # or a MismatchError naming the file


def plan_views(scenes, views, out):
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
            raise InputError(f"sensor {bad[0]} does not exist: {scene} has {n} sensor(s) "
                                   f"(--views takes indices 0..{n - 1} or 'all')")
        jobs += [(scene, v, len(chosen)) for v in chosen]
    stems = [os.path.splitext(os.path.basename(s))[0] for s in scenes]
    if len(set(stems)) != len(stems):
        raise InputError(f"scenes {list(scenes)} share a file name; render them in separate calls")
    if len(jobs) == 1:
        return [(jobs[0][0], jobs[0][1], os.fspath(out))]
    return [(scene, v, os.path.join(os.fspath(out), os.path.splitext(os.path.basename(scene))[0]
                                    + (f"-view{v}" if n > 1 else "")))
            for scene, v, n in jobs]
