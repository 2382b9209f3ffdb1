"""A reference render of the explorer in its own process (``python -m`` this module).

The explorer starts it at a lower priority (``nice``) so that the blends of a drag take the CPU
first, and ends it at once when its job is cancelled (:mod:`.reference`). The process reads a
:class:`RenderSpec` (JSON file), renders the scene at the point in passes of :data:`PASS_SAMPLES`
paths with the package's one reference renderer
(:func:`~mitsuba_manifold.render.scene.references.render_reference_passes`; at least two passes where
the spp allows, so that the passes measure the render's own noise), prints ``done total`` after
each pass, and writes a :class:`~mitsuba_manifold.render.scene.references.Reference` (the mean image
and its standard error per pixel) to ``spec.out`` atomically at the end.
"""

import json
import sys
from dataclasses import dataclass

from ...render.scene.references import BasisView, Reference

#: Paths per pass of a reference render (a fraction of a second on one core at 64x64).
PASS_SAMPLES = 1 << 18
#: Seed of a reference job's first pass.
SEED = 1000

__all__ = ["PASS_SAMPLES", "Reference", "RenderSpec", "main", "render"]


@dataclass
class RenderSpec:
    """What one reference render renders (the basis's ``view`` at ``x``, ``spp`` samples per
    pixel), and where the image goes (``out``).
    """

    view: BasisView
    x: list
    spp: int
    out: str

    def write(self, path) -> None:
        from ..._util.atomic import write_bytes

        d = {"view": self.view.to_json(), "x": list(self.x), "spp": int(self.spp), "out": self.out}
        write_bytes(path, json.dumps(d).encode())

    @classmethod
    def read(cls, path) -> "RenderSpec":
        with open(path) as f:
            d = json.load(f)
        return cls(BasisView.from_json(d["view"]), d["x"], int(d["spp"]), d["out"])


def render(spec, progress=print) -> Reference:
    """The :class:`Reference` of ``spec`` (:func:`~mitsuba_manifold.render.scene.references.render_reference_passes`,
    at least two passes of at most :data:`PASS_SAMPLES` paths); ``progress(done, total)`` after
    each pass.
    """
    from ...render.scene.references import render_reference_passes

    return render_reference_passes(
        spec.view,
        spec.x,
        spec.spp,
        seed=SEED,
        progress=progress,
        samples_per_pass=PASS_SAMPLES,
        min_passes=2,
    )


def main(argv=None) -> int:
    spec = RenderSpec.read((argv or sys.argv[1:])[0])
    render(spec, lambda done, total: print(done, total, flush=True)).write(spec.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
