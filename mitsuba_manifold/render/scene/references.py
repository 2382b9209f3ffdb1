"""Reference renders: Mitsuba's own image of a scene with the interpolated material, the ground
truth the ``L1-`` blends of paper Sec. 5.2 are compared with.
"""

from ...errors import MismatchError
from .loading import as_points, load_scene, set_points


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

    Loads the scene (:func:`~.loading.load_scene`), sets every manifold material to its latent
    point, and renders it with the scene's own integrator
    (:meth:`~.integrator.SceneIntegrator.reference`: ``path`` of the same settings where
    ``max_depth`` overrides it or the scene has none) in passes
    (:func:`~mitsuba_manifold.render.jobs.interrupt.render_in_passes`: Ctrl-C raises
    ``KeyboardInterrupt`` within a pass), as linear RGB of the film's crop window whatever its
    pixel format.

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
        As :func:`~.loading.load_scene` (``variant``: the active one unless given).
    sensor : int
        Which of the scene's sensors (views) to render: a basis's own (its manifest's
        ``sensor``), so that the reference compares with its blends pixel for pixel.

    Returns
    -------
    ndarray float32 (H, W, 3)
    """
    pts = as_points(x)
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
