"""Denoising guides of a basis rendered with Mitsuba: first-hit normals, the albedo of the other
BSDFs and the viewing-angle histogram on the manifold material (the ``manifold_aovs``
integrator), combined with the measured tables' directional albedos into a
:class:`~mitsuba_manifold.basis.denoise.BasisAOVs` saved beside the basis.
"""

import time

import numpy as np

from ...basis import folder as basis_folder
from ...basis.denoise import THETA_BINS, BasisAOVs, directional_albedos
from ...errors import MismatchError
from ...manifold.model import Manifold
from ..scene import scenes


def first_hit_aovs(scene, targets, spp=16, seed=0, sensor=0, bins=THETA_BINS):
    """``(normal, albedo_base, hist)`` images of a loaded scene: (H, W, 3), (H, W, 3), (H, W, bins)."""
    import mitsuba as mi

    from ..integrators.common import carriers

    integ = mi.load_dict({"type": "manifold_aovs", "bins": int(bins)})
    integ.targets = [
        c for c, m in carriers(scene) if any(m is t for t in targets)
    ]  # twosided wrappers too
    img = np.array(
        mi.render(scene, integrator=integ, spp=int(spp), seed=int(seed), sensor=int(sensor)),
        dtype=np.float32,
    )
    aov = img[..., img.shape[-1] - 6 - bins :]
    return aov[..., 0:3].copy(), aov[..., 3:6].copy(), aov[..., 6:].copy()


def render_aovs(
    scene_path, manifold_path, names, spp=16, seed=0, resolution=None, sensor=0, max_depth=None
):
    """First-hit AOVs and directional albedos of ``names`` for a scene (a :class:`BasisAOVs`)."""
    t0 = time.perf_counter()
    scene, targets, _ = scenes.load_scene(
        scene_path, manifold_path, spp, resolution, max_depth, sensor=sensor
    )
    normal, albedo_base, hist = first_hit_aovs(scene, targets, spp, seed, sensor)
    db = Manifold.load(manifold_path).open_database(None, names)
    table = directional_albedos(db, list(names))
    return BasisAOVs(
        normal, albedo_base, hist, table, list(names), int(spp), time.perf_counter() - t0
    )


def add_aovs(folder, spp=16, seed=0):
    """Render the AOVs of the basis in ``folder`` (one target) and save them beside it."""
    manifest = basis_folder.Manifest.read(folder)
    if len(manifest.targets) != 1:
        raise MismatchError(
            f"{folder}: AOVs of a blend are linear for one target; this basis has "
            f"{len(manifest.targets)}"
        )
    names = [
        basis_folder.key_materials(k, manifest.version)[0]
        for k in manifest.images
        if k != basis_folder.BASE
    ]
    aovs = render_aovs(
        manifest.scene,
        manifest.manifold,
        names,
        spp,
        seed,
        scenes.scene_resolution(manifest),
        manifest.sensor_index,
        manifest.max_depth,
    )
    aovs.save(folder, manifest)
    return aovs
