"""Scenes, in one namespace: the names of :mod:`.files` (shipped scenes, what a scene XML says),
:mod:`.variants` (the variant a render runs in), :mod:`.integrator` (what the scene's integrator
renders), :mod:`.loading` (loading a scene with its ``$parameters``, latent points) and
:mod:`.references` (reference renders).

``from mitsuba_manifold.render.scene.scenes import scene_path, load_scene, render_reference``: the
functions are those of the modules above (one object, two names).
"""

from .files import (
    HIDING_WRAPPERS,
    SCENES_DIR,
    check_scene,
    check_scene_manifolds,
    check_wrappers,
    scene_manifolds,
    scene_parameters,
    scene_path,
    scene_sample_count,
    shipped_scenes,
)
from .integrator import DIRECT_LIKE, PATH_LIKE, RR_DEPTH, SceneIntegrator, scene_integrator
from .loading import (
    LoadedScene,
    as_points,
    check_film,
    image_size,
    load_scene,
    scene_at,
    scene_resolution,
    set_points,
)
from .references import render_reference
from .variants import check_variant, default_variant, release_render_memory, use_variant

__all__ = [
    "DIRECT_LIKE",
    "HIDING_WRAPPERS",
    "PATH_LIKE",
    "RR_DEPTH",
    "SCENES_DIR",
    "LoadedScene",
    "SceneIntegrator",
    "as_points",
    "check_film",
    "check_scene",
    "check_scene_manifolds",
    "check_variant",
    "check_wrappers",
    "default_variant",
    "image_size",
    "load_scene",
    "release_render_memory",
    "render_reference",
    "scene_at",
    "scene_integrator",
    "scene_manifolds",
    "scene_parameters",
    "scene_path",
    "scene_resolution",
    "scene_sample_count",
    "set_points",
    "shipped_scenes",
    "use_variant",
]
