"""Tutorial 2: manifold_brdf in a scene of your own, and switching materials without reloading it.

    python3 docs/tutorials/own_scene.py --out out/tutorials            # after tutorial 1
    python3 docs/tutorials/own_scene.py --out /tmp/t --small

Reads OUT/manifold.npz (tutorial 1 makes it); writes OUT/own_scene.png.
"""

import argparse
import os
import sys

import mitsuba as mi
import numpy as np

import mitsuba_manifold.render  # noqa: F401  (registers manifold_brdf, manifold_path, manifold_aovs)
from mitsuba_manifold import Manifold
from mitsuba_manifold.imaging.io import write_contact_sheet

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", default="out/tutorials")
ap.add_argument("--small", action="store_true", help="tiny images (for the tests)")
args = ap.parse_args()
res, spp = (32, 4) if args.small else (192, 128)
manifold = os.path.abspath(os.path.join(args.out, "manifold.npz"))
if not os.path.isfile(manifold):  # tutorial 1 writes it
    sys.exit(
        f"error: {manifold} does not exist: run tutorial 1 first "
        f"(python3 docs/tutorials/manifold_tour.py --out {args.out})"
    )
m = Manifold.load(manifold)

mi.set_variant("llvm_ad_rgb")

# Any Mitsuba scene: give a shape a manifold_brdf. Exactly one of material, weights or x chooses
# the material (material="gold-metallic-paint" would too); x, a latent point, is the one that
# mi.traverse exposes. The manifold file is found like any other file of the scene.
gold = ", ".join(f"{v:.6g}" for v in m.latent[m.index("gold-metallic-paint")])
scene = mi.load_dict(
    {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 8},
        "sensor": {
            "type": "perspective",
            "fov": 30,
            "to_world": mi.ScalarTransform4f().look_at(
                origin=[0, 1.2, 4.5], target=[0, 0.1, 0], up=[0, 1, 0]
            ),
            "film": {
                "type": "hdrfilm",
                "width": res,
                "height": res,
                "rfilter": {"type": "gaussian"},
            },
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.6}},
        "sun": {
            "type": "point",
            "position": [2.5, 4.0, 2.0],
            "intensity": {"type": "rgb", "value": 25.0},
        },
        "floor": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f()
            .translate([0, -0.6, 0])
            .rotate([1, 0, 0], -90)
            .scale(4),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.45}},
        },
        "ball": {
            "type": "sphere",
            "radius": 0.6,
            "bsdf": {"type": "manifold_brdf", "manifold": manifold, "x": gold},
        },
    }
)
images = [np.array(mi.render(scene, seed=0))]

# The latent point is a scene parameter ("ball.bsdf.x" here; "<id>.x" for a <bsdf id="..."> of
# an XML scene): set it, update, render again (no reload).
params = mi.traverse(scene)
print("parameters:", [k for k in params.keys() if k.startswith("ball.bsdf")])
for a, b in [("gold-metallic-paint", "blue-rubber"), ("blue-rubber", "blue-rubber")]:
    params["ball.bsdf.x"] = 0.5 * (m.latent[m.index(a)] + m.latent[m.index(b)])
    params.update()
    images.append(np.array(mi.render(scene, seed=0)))

labels = ["x: gold-metallic-paint", "x: midpoint to blue-rubber", "x: blue-rubber"]
write_contact_sheet(os.path.join(args.out, "own_scene.png"), np.stack(images), labels, columns=3)
print("wrote", os.path.join(args.out, "own_scene.png"))
