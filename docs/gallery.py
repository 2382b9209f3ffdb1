"""The documentation's images: the gallery, and the tutorials' pictures.

    python3 docs/gallery.py          # docs/_static/gallery/, tutorials/, readme_materials.png
    python3 docs/gallery.py --out /tmp/g --small --no-tutorials      # seconds (what the tests run)

The gallery: measured materials of the built-in database on the shipped ``sphere`` scene, and a
grid of latent points around them (the materials between the measured ones). The tutorials
(docs/tutorials/*.py) run in order at their documentation sizes and their PNGs are copied beside.
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile

import numpy as np

from mitsuba_manifold import Manifold

HERE = os.path.dirname(os.path.abspath(__file__))
TUTORIALS = ["manifold_tour", "own_scene", "basis_blend", "inverse", "acquire"]
#: Materials of the gallery (names of the built-in database).
MATERIALS = [
    "blue-rubber",
    "white-paint",
    "gold-metallic-paint",
    "chrome",
    "red-fabric",
    "green-metallic-paint",
    "pink-fabric",
    "black-obsidian",
    "alum-bronze",
    "yellow-paint",
    "silver-metallic-paint",
    "dark-red-paint",
    "blue-metallic-paint",
    "orange-paint",
    "violet-acrylic",
    "white-marble",
]


def render_spheres(manifold_path, points, res, spp):
    """Images of the ``sphere`` scene at each latent point (one scene, ``x`` set by traverse)."""
    import mitsuba as mi

    import mitsuba_manifold.render  # noqa: F401
    from mitsuba_manifold.render.scene.scenes import scene_path

    mi.set_variant("llvm_ad_rgb")
    scene = mi.load_file(scene_path("sphere"), manifold=manifold_path, res=res, spp=spp)
    params = mi.traverse(scene)
    images = []
    for p in points:
        params["material.x"] = p
        params.update()
        images.append(np.array(mi.render(scene, seed=0)))
    return np.stack(images)


def gallery(out, small):
    from mitsuba_manifold.imaging.io import write_contact_sheet

    bins, res, spp = ((16, 16, 32), 24, 4) if small else ((90, 90, 180), 128, 256)
    materials = MATERIALS[:6] if small else MATERIALS
    work = tempfile.mkdtemp(prefix="gallery-")  # the tables are large: never under docs/
    m = Manifold.fit("merl@{}x{}x{}".format(*bins), names=materials)  # the measured MERL set
    path = os.path.join(work, "manifold.npz")
    m.save(path)
    os.makedirs(out, exist_ok=True)
    sheet = os.path.join(out, "measured.png")
    write_contact_sheet(sheet, render_spheres(path, m.latent, res, spp), list(m.names), columns=8)
    # A 5x5 grid over the first two latent axes, the other coordinates at the data's mean.
    lo, hi = np.percentile(m.latent, [10, 90], axis=0)
    centre = m.latent.mean(axis=0)
    k = 3 if small else 5
    grid = [
        np.concatenate([[a, b], centre[2:]])
        for b in np.linspace(hi[1], lo[1], k)
        for a in np.linspace(lo[0], hi[0], k)
    ]
    labels = [f"({p[0]:.2f}, {p[1]:.2f})" for p in grid]
    write_contact_sheet(
        os.path.join(out, "latent_grid.png"),
        render_spheres(path, grid, res, spp),
        labels,
        columns=k,
    )
    shutil.rmtree(work)
    return [sheet, os.path.join(out, "latent_grid.png")]


#: The README's first picture: training materials of the shipped ``merl`` manifold and points
#: between them (name, or ``(a, b, t)``: the point a fraction ``t`` of the way from a to b).
README_POINTS = [
    "gold-metallic-paint",
    ("gold-metallic-paint", "blue-metallic-paint", 0.5),
    "blue-metallic-paint",
    "red-fabric",
    ("red-fabric", "white-paint", 0.5),
    "chrome",
]


def readme_picture(path, res=160, spp=256):
    """The README's first picture: :data:`README_POINTS` on the ``sphere`` scene (a sky map and a
    point light), rendered from the shipped manifold ``merl``.
    """
    from mitsuba_manifold.imaging.io import write_contact_sheet

    m = Manifold.load("merl")
    points, labels = [], []
    for p in README_POINTS:
        if isinstance(p, str):
            points.append(m.point(p))
            labels.append(p)
        else:
            a, b, t = p
            points.append((1 - t) * m.point(a) + t * m.point(b))
            labels.append("between")
    write_contact_sheet(path, render_spheres("merl", points, res, spp), labels, columns=6)
    return path


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(HERE, "_static", "gallery"))
    ap.add_argument("--tutorials-out", default=os.path.join(HERE, "_static", "tutorials"))
    ap.add_argument("--small", action="store_true", help="tiny tables and images (for the tests)")
    ap.add_argument("--no-tutorials", action="store_true", help="the gallery only")
    args = ap.parse_args()
    for f in gallery(args.out, args.small):
        print("wrote", f)
    if not args.small:
        print("wrote", readme_picture(os.path.join(HERE, "_static", "readme_materials.png")))
    if args.no_tutorials:
        return
    work = tempfile.mkdtemp(prefix="tutorials-")
    os.makedirs(args.tutorials_out, exist_ok=True)
    for name in TUTORIALS:
        cmd = [sys.executable, os.path.join(HERE, "tutorials", f"{name}.py"), "--out", work]
        subprocess.run(cmd + (["--small"] if args.small else []), check=True)
    for f in sorted(os.listdir(work)):
        if f.endswith(".png"):
            shutil.copy(os.path.join(work, f), os.path.join(args.tutorials_out, f))
            print("wrote", os.path.join(args.tutorials_out, f))
    shutil.rmtree(work)


if __name__ == "__main__":
    main()
