"""The reference of a blend: Mitsuba's own render of a basis's view with the material at a point.

A blend (Eq. 13) is compared pixel for pixel with a render of the same scene, view (sensor),
load resolution, path depth, variant and targets as its basis, each manifold material set to
its latent point and rendered with the scene's own integrator
(:meth:`~mitsuba_manifold.render.scene.scenes.SceneIntegrator.reference`). :class:`BasisView` is
that view, read from a basis once; :func:`render_reference_passes` is the one renderer of
references, used by ``blend.py --render-reference``, ``match.py --render-reference`` and the
explorer's reference jobs. It renders in passes (:func:`~mitsuba_manifold.render.jobs.interrupt.sample_passes`,
Ctrl-C stops between passes), their sample-weighted mean the image and their spread its
standard error per pixel (:func:`~mitsuba_manifold.imaging.metrics.pass_standard_error`).
"""

import io
from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from ...errors import MismatchError


def reference_sensor(basis, scene, warn: Optional[Callable] = None) -> int:
    """The sensor a reference of ``basis`` renders: its manifest's, so that the reference
    compares with its blends pixel for pixel. ``warn`` (a line) is told when the manifest does
    not record its sensor (a basis of an earlier version) and ``scene`` has several views.
    """
    from ..jobs.render_basis import count_sensors

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
        from .scenes import scene_resolution

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
) -> Reference:
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
    from .scenes import _points, load_scene, set_points

    pts = _points(x)
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
