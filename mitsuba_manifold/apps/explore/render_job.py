"""A reference render of the explorer in its own process (``python -m`` this module).

The explorer starts it at a lower priority (``nice``) so that the blends of a drag take the CPU
first, and ends it at once when its job is cancelled (:mod:`.reference`). The process reads a
:class:`RenderSpec` (JSON file), renders the scene at the point in passes of :data:`PASS_SAMPLES`
paths (as :func:`~mitsuba_manifold.render.interrupt.render_in_passes`: different seeds,
sample-weighted mean), prints ``done total`` after each pass, and writes the mean image (float32
``.npy``) to ``spec.out`` atomically at the end.
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


def render(spec, progress=print):
    """The mean image of ``spec`` (H, W, 3) float32; ``progress(done, total)`` after each pass."""
    import mitsuba as mi
    import numpy as np

    from ...render.interrupt import sample_passes
    from ...render.scenes import load_scene, set_points

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
    acc, done = None, 0
    for k, spp in enumerate(sample_passes(spec.spp, w * h, PASS_SAMPLES)):
        img = np.array(
            mi.render(
                loaded.scene, integrator=integrator, spp=spp, seed=1000 + k, sensor=spec.sensor
            ),
            dtype=np.float64,
        )[..., :3]
        acc = img * spp if acc is None else acc + img * spp
        done += spp
        progress(done, spec.spp)
    return (acc / spec.spp).astype(np.float32)


def main(argv=None):
    import io

    import numpy as np

    from ..._util.atomic import write_bytes

    spec = RenderSpec.read((argv or sys.argv[1:])[0])
    image = render(spec, lambda done, total: print(done, total, flush=True))
    buf = io.BytesIO()
    np.save(buf, image)
    write_bytes(spec.out, buf.getvalue())
    return 0


if __name__ == "__main__":
    sys.exit(main())
