"""Tutorial 4: inverse rendering: recover a material's latent point from an image, with Adam.

    python3 docs/tutorials/inverse.py --out out/tutorials              # after tutorial 1
    python3 docs/tutorials/inverse.py --out /tmp/t --small

Reads OUT/manifold.npz (tutorial 1 makes it). Makes its own image to match (a render of a known point),
starts from a training material and follows the gradient of the image loss through Mitsuba's
``prb`` integrator. Writes OUT/inverse.png (image to match | start | result) and OUT/inverse_loss.png.
"""

import argparse
import os
import sys

import drjit as dr
import mitsuba as mi
import numpy as np

import mitsuba_manifold.render  # noqa: F401  (registers manifold_brdf)
from mitsuba_manifold import Manifold
from mitsuba_manifold.imaging.io import write_contact_sheet
from mitsuba_manifold.imaging.plots import save, subplots
from mitsuba_manifold.render.scene.scenes import scene_path

ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ap.add_argument("--out", default="out/tutorials")
ap.add_argument("--small", action="store_true", help="tiny images, few iterations (for the tests)")
args = ap.parse_args()
res, spp, iterations = (24, 4, 4) if args.small else (128, 16, 60)
manifold = os.path.join(args.out, "manifold.npz")
if not os.path.isfile(manifold):  # tutorial 1 writes it
    sys.exit(
        f"error: {manifold} does not exist: run tutorial 1 first "
        f"(python3 docs/tutorials/manifold_tour.py --out {args.out})"
    )
m = Manifold.load(manifold)

mi.set_variant("llvm_ad_rgb")
scene = mi.load_file(scene_path("sphere"), manifold=manifold, res=res)  # <bsdf id="material">
params = mi.traverse(scene)
prb = mi.load_dict({"type": "prb", "max_depth": 8})

# The image to match: the material a third of the way from gold-metallic-paint to white-paint.
gold, white = m.latent[m.index("gold-metallic-paint")], m.latent[m.index("white-paint")]
x_true = gold + (white - gold) / 3
params["material.x"] = x_true
params.update()
image_to_match = mi.render(scene, params, integrator=prb, spp=64 * spp, seed=1000)

# The start: halfway (at a training point itself the weights are flat: no gradient).
x_start = gold + (white - gold) / 2
params["material.x"] = x_start
params.update()
start = mi.render(scene, params, integrator=prb, spp=8 * spp, seed=1001)

opt = mi.ad.Adam(lr=0.02, beta_2=0.9)  # a short memory of gradient sizes: they shrink a lot
opt["material.x"] = params["material.x"]
params.update(opt)  # x grad-enabled: the BSDF follows x differentiably
losses, best = [], (np.inf, None)
for it in range(iterations):
    x_now = np.array(params["material.x"]).ravel()
    # Two independent renders: the mean of (a - t)(b - t) is the noise-free error, where that of
    # (a - t)^2 adds the render's variance, which would favour the materials that render smoothly.
    a = mi.render(scene, params, integrator=prb, spp=spp, seed=2 * it)
    b = mi.render(scene, params, integrator=prb, spp=spp, seed=2 * it + 1)
    loss = dr.mean((a - image_to_match) * (b - image_to_match), axis=None)
    dr.backward(loss)
    opt.step()
    params.update(opt)
    losses.append(float(loss.array[0]))
    best = min(best, (losses[-1], x_now), key=lambda b: b[0])  # keep the best point seen
x_found = best[1]
print("true x:", np.round(x_true, 3), " found x:", np.round(x_found, 3))

params["material.x"] = x_found  # a plain value: no gradient from here on
params.update()
result = mi.render(scene, params, integrator=prb, spp=8 * spp, seed=1002)
write_contact_sheet(
    os.path.join(args.out, "inverse.png"),
    np.stack([np.array(image_to_match), np.array(start), np.array(result)]),
    ["image to match", "start", f"best of {iterations} Adam steps"],
    columns=3,
)
fig, ax = subplots(figsize=(4, 2.6), layout="constrained")
ax.semilogy(np.maximum(losses, 1e-7))  # the two-render estimate can dip below 0 near the optimum
ax.set_xlabel("iteration")
ax.set_ylabel("image MSE")
save(fig, os.path.join(args.out, "inverse_loss.png"))
print("wrote", os.path.join(args.out, "inverse.png"))
