"""Tutorial 1: a manifold of measured materials, and a walk across it rendered with manifold_brdf.

    python3 docs/tutorials/manifold_tour.py --out out/tutorials        # about a minute
    python3 docs/tutorials/manifold_tour.py --out /tmp/t --small       # seconds (the tests)

Writes OUT/manifold_tour.png: spheres along the path between two measured materials.
"""

import argparse
import os

import numpy as np

from mitsuba_manifold import Manifold

MATERIALS = [
    "blue-rubber",
    "white-paint",
    "gold-metallic-paint",
    "chrome",
    "red-fabric",
    "green-metallic-paint",
    "pink-fabric",
    "black-obsidian",
]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/tutorials")
    ap.add_argument("--small", action="store_true", help="tiny tables and images (for the tests)")
    args = ap.parse_args()
    bins, res, spp = ((16, 16, 32), 32, 4) if args.small else ((90, 90, 180), 160, 256)

    # 1. A database: the built-in measured MERL set (NBRDF fits of the measurements), tabulated on
    #    demand at the resolution asked for; here 8 of its 100 materials.
    db = "merl@{}x{}x{}".format(*bins)
    os.makedirs(args.out, exist_ok=True)

    # 2. Fit the manifold: a latent point per material (q = 4 by default).
    m = Manifold.fit(db, names=MATERIALS)
    m.save(os.path.join(args.out, "manifold.npz"))
    print(m.summary())

    # 3. Any latent point is a material: convex weights over the measured tables.
    x = 0.5 * (m.latent[m.index("blue-rubber")] + m.latent[m.index("white-paint")])
    b, w = m.weights(x)
    print(
        "weights at the midpoint:", {n: round(float(v), 3) for n, v in zip(m.names, w) if v > 0.01}
    )
    print("albedo (RGB):", np.round(m.albedo(x), 3))

    # 4. A path between two materials (even steps in a perceptual BRDF distance), rendered.
    import mitsuba as mi  # noqa: E402

    import mitsuba_manifold.render  # noqa: E402,F401  (registers manifold_brdf)
    from mitsuba_manifold.imaging.io import write_contact_sheet  # noqa: E402
    from mitsuba_manifold.render.scene.scenes import scene_path  # noqa: E402

    mi.set_variant("llvm_ad_rgb")
    points = m.path("blue-rubber", "white-paint", steps=5)
    scene = mi.load_file(
        scene_path("sphere"), manifold=os.path.join(args.out, "manifold.npz"), res=res, spp=spp
    )
    params = mi.traverse(scene)
    images = []
    for p in points:
        params["material.x"] = p
        params.update()
        images.append(np.array(mi.render(scene, seed=0)))
    labels = ["blue-rubber"] + [""] * (len(points) - 2) + ["white-paint"]
    write_contact_sheet(
        os.path.join(args.out, "manifold_tour.png"), np.stack(images), labels, columns=len(points)
    )
    print("wrote", os.path.join(args.out, "manifold_tour.png"))


if __name__ == "__main__":  # the database is written by worker processes, which import this file
    main()
