"""A reference render of the explorer in its own process (``python -m`` this module).

The explorer starts it at a lower priority (``nice``) so that the blends of a drag take the CPU
first, and ends it at once when its job is cancelled (:mod:`.reference`). The process reads a
:class:`RenderSpec` (JSON file), renders the scene at the point in passes of :data:`PASS_SAMPLES`
paths (as :func:`~mitsuba_manifold.render.jobs.interrupt.render_in_passes`: different seeds,
sample-weighted mean; at least two passes where the spp allows, so that the passes measure the
render's own noise), prints ``done total`` after each pass, and writes a :class:`Reference` (the
mean image and its standard error per pixel, :func:`~mitsuba_manifold.imaging.metrics.pass_standard_error`)
to ``spec.out`` atomically at the end.
"""

import json
import sys
from dataclasses import asdict, dataclass
from typing import Optional

#: Paths per pass of a reference render (a fraction of a second on one core at 64x64).
PASS_SAMPLES = 1 << 18


@dataclass
class RenderSpec:
    """What one reference render renders, and where the image goes."""

    scene: str
    manifold: str
    x: list
    spp: int
    resolution: Optional[list]  # as the basis loaded the scene (None: the film's own size)
    size: list  # the image's (width, height)
    max_depth: int
    variant: str
    sensor: int
    out: str

    def write(self, path):
        from ..._util.atomic import write_bytes

        write_bytes(path, json.dumps(asdict(self)).encode())

    @classmethod
    def read(cls, path):
        with open(path) as f:
            return cls(**json.load(f))


@dataclass
class Reference:
    """A reference render: the mean ``image`` (H, W, 3) float32, ``pixel_se`` the standard error
    of each of its values (NaN for a render of one pass), rendered in ``passes`` passes.
    """

    image: object
    pixel_se: object
    passes: int

    def write(self, path):
        import io

        import numpy as np

        from ..._util.atomic import write_bytes

        buf = io.BytesIO()
        np.savez(buf, image=self.image, pixel_se=self.pixel_se, passes=self.passes)
        write_bytes(path, buf.getvalue())

    @classmethod
    def read(cls, path):
        import numpy as np

        with np.load(path) as z:
            return cls(z["image"], z["pixel_se"], int(z["passes"]))


def render(spec, progress=print):
    """The :class:`Reference` of ``spec``; ``progress(done, total)`` after each pass."""
    import mitsuba as mi
    import numpy as np

    from ...imaging.metrics import pass_standard_error
    from ...render.jobs.interrupt import sample_passes
    from ...render.scene.scenes import load_scene, set_points

    loaded = load_scene(
        spec.scene,
        spec.manifold,
        spec.spp,
        None if spec.resolution is None else tuple(spec.resolution),
        spec.max_depth,
        spec.x,
        spec.variant,
        sensor=spec.sensor,
    )
    set_points(loaded.targets, spec.x)
    integrator = loaded.integrator.reference(loaded.scene)  # the scene's own, as the basis's
    w, h = spec.size
    per_pass = min(PASS_SAMPLES, max(1, spec.spp // 2) * w * h)  # two passes at least
    acc, acc2, done = 0.0, 0.0, 0
    passes = sample_passes(spec.spp, w * h, per_pass)
    for k, spp in enumerate(passes):
        img = np.array(
            mi.render(
                loaded.scene, integrator=integrator, spp=spp, seed=1000 + k, sensor=spec.sensor
            ),
            dtype=np.float64,
        )[..., :3]
        acc, acc2 = acc + img * spp, acc2 + img * img * spp
        done += spp
        progress(done, spec.spp)
    se = pass_standard_error(acc, acc2, done, len(passes))
    return Reference((acc / done).astype(np.float32), se.astype(np.float32), len(passes))


def main(argv=None):
    spec = RenderSpec.read((argv or sys.argv[1:])[0])
    render(spec, lambda done, total: print(done, total, flush=True)).write(spec.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
