"""Reference renders: Mitsuba's own image of a scene with the interpolated material, the ground
truth the ``L1-`` blends of paper Sec. 5.2 are compared with.

A blend (Eq. 13) is compared pixel for pixel with a render of the same scene, view (sensor),
load resolution, path depth, variant and targets as its basis, each manifold material at its
latent point, rendered with the scene's own integrator
(:meth:`~.integrator.SceneIntegrator.reference`). :class:`BasisView` is that view, read from a
basis once; :func:`render_reference_passes` is the one renderer of references, used by
:func:`render_reference`, ``blend.py --render-reference``, ``match.py --render-reference`` and
the explorer's reference jobs. It renders in passes
(:func:`~mitsuba_manifold.render.jobs.interrupt.render_passes`, Ctrl-C stops between passes):
their sample-weighted mean is the image, their spread its standard error per pixel
(:func:`~mitsuba_manifold.imaging.metrics.pass_standard_error`).
"""

import io
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Optional

import numpy as np

from ...errors import MismatchError
from .loading import as_points, load_scene, scene_resolution, set_points

if TYPE_CHECKING:
    import numpy as np


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
) -> "np.ndarray":
    """Mitsuba's own image of the scene with the interpolated material: the ground truth of a blend.

    The optional settings are those a basis records (resolution, depth, variant, targets,
    database, sensor): a caller renders the view a basis was rendered with.

    :func:`render_reference_passes` with the view given by its parameters: loads the scene
    (:func:`~.loading.load_scene`), sets every manifold material to its latent point, and
    renders it with the scene's own integrator
    (:meth:`~.integrator.SceneIntegrator.reference`: ``path`` of the same settings where
    ``max_depth`` overrides it or the scene has none) in passes
    (:func:`~mitsuba_manifold.render.jobs.interrupt.render_passes`: Ctrl-C raises
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
    view = BasisView(
        scene=scene_path,
        manifold=manifold_path,
        resolution=resolution,
        max_depth=max_depth,
        variant=variant,
        targets=None if targets is None else tuple(targets),
        sensor=int(sensor),
        database=database,
    )
    return render_reference_passes(view, x, spp, seed=seed).image  # Ctrl-C: KeyboardInterrupt


def reference_sensor(basis, scene, warn: Optional[Callable] = None) -> int:
    """The sensor a reference of ``basis`` renders: its manifest's, so that the reference
    compares with its blends pixel for pixel. ``warn`` (a line) is told when the manifest does
    not record its sensor (a basis of an earlier version) and ``scene`` has several views.
    """
    from .files import count_sensors

    if warn is not None and not basis.sensor_known and count_sensors(scene) > 1:
        warn(
            f"warning: the basis {basis.folder} does not record which of the {count_sensors(scene)} sensors of "
            f"{scene} it was rendered from (made by an earlier version); rendering the reference from sensor 0"
        )
    return int(basis.sensor)


@dataclass(frozen=True)
class BasisView:
    """What a reference of a basis renders: its scene as the basis loaded it.

    Attributes
    ----------
    scene, manifold : str
        The scene XML and the manifold (``.npz``) of its ``manifold_brdf``.
    resolution : tuple or None
        The resolution the scene is loaded with (None: its film's own size).
    max_depth : int or None
        The path depth the basis was rendered with.
    variant : str or None
        Mitsuba variant (None: the active one).
    targets : tuple of str or None
        BSDF ids of the rows of a (p, q) point.
    sensor : int
        The view.
    database : str or None
        The manifold's tables, if they moved.
    """

    scene: str
    manifold: str
    resolution: Optional[tuple] = None
    max_depth: Optional[int] = None
    variant: Optional[str] = None
    targets: Optional[tuple] = None
    sensor: int = 0
    database: Optional[str] = None

    @classmethod
    def of(cls, basis, scene=None, manifold=None, database=None, warn=None) -> "BasisView":
        """The view of ``basis`` (:class:`~mitsuba_manifold.basis.folder.Basis`); ``scene`` and
        ``manifold`` default to its manifest's, ``warn`` as :func:`reference_sensor`.
        """
        m = basis.manifest
        scene = scene or m.scene
        return cls(
            scene=scene,
            manifold=manifold or m.manifold,
            resolution=scene_resolution(m),
            max_depth=m.max_depth,
            variant=m.variant,
            targets=tuple(basis.targets),
            sensor=reference_sensor(basis, scene, warn),
            database=database,
        )

    def to_json(self) -> dict:
        """The view as JSON values (for a render in another process)."""
        return {
            "scene": self.scene,
            "manifold": self.manifold,
            "resolution": None if self.resolution is None else list(self.resolution),
            "max_depth": self.max_depth,
            "variant": self.variant,
            "targets": None if self.targets is None else list(self.targets),
            "sensor": int(self.sensor),
            "database": self.database,
        }

    @classmethod
    def from_json(cls, d) -> "BasisView":
        """The view :meth:`to_json` wrote."""
        return cls(
            scene=d["scene"],
            manifold=d["manifold"],
            resolution=None if d.get("resolution") is None else tuple(d["resolution"]),
            max_depth=d.get("max_depth"),
            variant=d.get("variant"),
            targets=None if d.get("targets") is None else tuple(d["targets"]),
            sensor=int(d.get("sensor", 0)),
            database=d.get("database"),
        )


@dataclass
class Reference:
    """A reference render: the mean ``image`` (H, W, 3) float32, ``pixel_se`` the standard error
    of each of its values (NaN for a render of one pass), rendered in ``passes`` passes.
    """

    image: np.ndarray
    pixel_se: np.ndarray
    passes: int

    def write(self, path) -> None:
        """Write the reference as ``.npz`` (atomically)."""
        from ..._util.atomic import write_bytes

        buf = io.BytesIO()
        np.savez(buf, image=self.image, pixel_se=self.pixel_se, passes=self.passes)
        write_bytes(path, buf.getvalue())

    @classmethod
    def read(cls, path) -> "Reference":
        """The reference :meth:`write` wrote."""
        with np.load(path) as z:
            return cls(z["image"], z["pixel_se"], int(z["passes"]))


def render_reference_passes(
    view: BasisView,
    x,
    spp: int,
    seed: int = 0,
    progress: Optional[Callable] = None,
    samples_per_pass: Optional[int] = None,
    min_passes: int = 1,
) -> "Reference":
    """Mitsuba's own image of ``view`` with every manifold material at its point ``x``.

    Parameters
    ----------
    view : BasisView
    x : array_like
        (q,): every manifold material at x; or (p, q): one point per target (``view.targets``).
    spp, seed : int
        Samples per pixel; the passes are seeded as
        :func:`~mitsuba_manifold.render.jobs.interrupt.render_passes` does, so that a render
        of one pass is exactly ``mi.render(..., spp, seed)``.
    progress : callable, optional
        ``progress(done, spp)`` after each pass.
    samples_per_pass : int, optional
        Paths per pass (default :data:`~mitsuba_manifold.render.jobs.interrupt.SAMPLES_PER_PASS`).
    min_passes : int
        Passes at least, where ``spp`` allows (two measure the render's own noise).

    Returns
    -------
    Reference
        The sample-weighted mean of the passes (linear RGB of the film's crop window, whatever
        its pixel format) and its standard error per pixel.
    """
    from ..jobs.interrupt import SAMPLES_PER_PASS, render_passes

    pts = as_points(x)
    if int(spp) < 1:
        raise MismatchError(f"`spp` must be >= 1, got {spp}")
    loaded = load_scene(
        view.scene,
        view.manifold,
        int(spp),
        view.resolution,
        view.max_depth,
        pts[0],
        view.variant,
        view.database,
        sensor=int(view.sensor),
    )
    set_points(loaded.targets, pts, view.targets)
    integrator = loaded.integrator.reference(loaded.scene)
    image, se, passes = render_passes(
        loaded.scene,
        integrator,
        int(spp),
        int(seed),
        sensor=int(view.sensor),
        samples_per_pass=SAMPLES_PER_PASS if samples_per_pass is None else samples_per_pass,
        min_passes=min_passes,
        progress=progress,
    )  # Ctrl-C: KeyboardInterrupt at the end of a pass
    return Reference(image, se, passes)
