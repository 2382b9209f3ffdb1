"""The targets of full-GI bases (``tools/bench.py gi-targets``): on the shipped ``table``
and on ``facing`` (a sphere on a floor before a wall, all of the material; not shipped), L1- and
full-GI bases (time, size, what they hold), and at a training point, the midpoint of the GI pair,
the extrapolated point and the pair's second material: bias and relative MSE of the L1- blend,
the full-GI blend, the refined blend (``blend.py --refine`` on the full-GI basis, an eighth of the
direct render's samples) and a 256-spp direct render against 4096-spp references (:func:`.gi.targets`); then the
blend time at 256x256 for every material of the manifold (:func:`.gi.blend_time`).
"""

import os

from mitsuba_manifold.data.database import database_cache

from .common import work_manifold
from .gi import FACING, blend_time, targets


def run(folder, manifold=None, scenes=("table", FACING), res=64, basis_spp=256, ref_spp=4096):
    """The measurements above, as a dict ``{"targets": ..., "blend": ...}``."""
    manifold = manifold or work_manifold(folder)
    out = os.path.join(database_cache(folder), "bench_gi_targets")
    report = {
        "targets": targets(
            folder,
            manifold,
            scenes=scenes,
            res=res,
            basis_spp=basis_spp,
            ref_spp=ref_spp,
            out=out,
            both_ends=True,
        )
    }
    report["blend"] = blend_time(manifold, out, res=256)
    return report
