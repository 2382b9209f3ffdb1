"""The bases of an explorer: a short name for each folder, and the scene its reference renders use."""

import os

from ...basis.folder import scene_hash
from ...render.scene import scenes


def names(folders):
    """Short unique names of basis folders (their base names, numbered when they repeat)."""
    out = {}
    for folder in folders:
        base = os.path.basename(os.path.normpath(folder)) or "basis"
        name, k = base, 2
        while name in out:
            name, k = f"{base}-{k}", k + 1
        out[name] = folder
    return out


def scene_of(basis, scene=None):
    """Scene XML of a basis for reference renders (checked by hash), or None when it is gone."""
    if scene is not None:
        path = scenes.scene_path(scene)
        basis.check_scene(path)
        return path
    path = basis.manifest.scene
    if os.path.isfile(path):
        return path
    name = os.path.splitext(os.path.basename(path))[
        0
    ]  # moved: a shipped scene of that name and hash
    if (
        name in scenes.shipped_scenes()
        and scene_hash(scenes.scene_path(name)) == basis.manifest.scene_hash
    ):
        return scenes.scene_path(name)
    return None


def warm(bases):
    """The first basis's cross terms (the one the page opens on) in float32 before the first drag
    (:meth:`~mitsuba_manifold.basis.folder.Basis.warm_cross_terms`); other bases convert theirs as they are blended.
    """
    for basis in list(bases.values())[:1]:
        try:
            basis.warm_cross_terms()
        except (OSError, ValueError, MemoryError) as e:  # blends then convert them on first use
            print(
                f"explore: {basis.folder}: cross terms not prepared ahead ({type(e).__name__}: {e})",
                flush=True,
            )
