"""The latent map of the page: albedo over a 2-D slice of the latent space (paper Fig. 7).

The slice spans latent coordinates ``dims`` through a point ``center`` (the other
coordinates stay at the center's values, so for ``q > 2`` the map follows the sliders).
Colour: the albedo (mean over RGB) of the interpolated material, on one scale for every
slice and zoom (0 to a little above the brightest measured material's), so that colours
compare across the sliders of ``q > 2``. The region where the
data lives is where the GP variance (Eq. 2) is below half its prior value ``1 + mu``;
outside it the map is dimmed. Where any albedo channel leaves [0, 1] (a physically
impossible material: extrapolation, negative weights) the map is hatched.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Variance (as a fraction of the prior) below which a point counts as inside the data.
DATA_VARIANCE = 0.5
MARGIN = 0.25
CMAP = "viridis"
#: Points of the grid evaluated at once between two calls of :func:`render`'s ``pause``.
CHUNK = 1152


@dataclass
class LatentMap:
    """One rendered map: the RGBA image (row 0 at the top = largest second coordinate)."""

    image: np.ndarray
    dims: tuple
    extent: tuple  # (x0_min, x0_max, x1_min, x1_max)
    albedo_range: tuple  # (lo, hi) of the colour scale
    outside_fraction: float
    colormap: list  # CSS colours from lo to hi, for the legend

    def info(self) -> dict:
        return {
            "dims": list(self.dims),
            "extent": list(self.extent),
            "albedo_range": list(self.albedo_range),
            "outside_fraction": self.outside_fraction,
            "colormap": self.colormap,
        }


def extent(manifold, dims, margin=MARGIN) -> tuple[float, float, float, float]:
    """Bounds of the slice: the latent points' bounding box of ``dims`` plus ``margin`` each side
    (made square in latent units so distances look right).
    """
    pts = manifold.latent[:, list(dims)]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre, half = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-3) * (1 + 2 * margin)
    return (
        float(centre[0] - half),
        float(centre[0] + half),
        float(centre[1] - half),
        float(centre[1] + half),
    )


def _grid(center, dims, ext, resolution) -> np.ndarray:
    """Latent points of a resolution x resolution grid over ``ext`` (top row first)."""
    xs = np.linspace(ext[0], ext[1], resolution)
    ys = np.linspace(ext[3], ext[2], resolution)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.tile(np.asarray(center, dtype=np.float64), (gx.size, 1))
    pts[:, dims[0]], pts[:, dims[1]] = gx.ravel(), gy.ravel()
    return pts


def _albedo(manifold, pts):
    if manifold.albedos is None:
        return np.full((len(pts), 3), 0.5)
    return manifold.albedo(pts)


def colour_range(manifold) -> tuple[float, float]:
    """The albedo range of the colour scale: the same for every slice and zoom of a manifold."""
    if manifold.albedos is None:
        return 0.0, 1.0
    return 0.0, float(min(1.0, max(1.1 * np.asarray(manifold.albedos).mean(axis=-1).max(), 0.05)))


def render(manifold, center, dims=(0, 1), resolution=192, bounds=None, pause=None) -> LatentMap:
    """A :class:`LatentMap` of the slice through ``center`` (q,) spanning ``dims``, over
    ``bounds`` ``(x0_min, x0_max, x1_min, x1_max)`` (default: :func:`extent`).

    The grid's albedo and variance are evaluated :data:`CHUNK` points at a time (each point on
    its own: the map is the same whatever the chunks), and ``pause()``, when given, is called
    before each chunk: it may wait (the explorer lets a drag's frames go first) or raise to
    abandon a map nobody waits for any more.
    """
    from matplotlib import colormaps

    dims = tuple(int(d) for d in dims)
    ext = extent(manifold, dims) if bounds is None else tuple(float(v) for v in bounds)
    pts = _grid(center, dims, ext, resolution)
    alb, var = np.empty((len(pts), 3)), np.empty(len(pts))
    for k in range(0, len(pts), CHUNK):
        if pause is not None:
            pause()
        alb[k : k + CHUNK] = _albedo(manifold, pts[k : k + CHUNK])
        var[k : k + CHUNK] = manifold.variance(pts[k : k + CHUNK])
    alb = alb.reshape(resolution, resolution, 3)
    var = var.reshape(resolution, resolution) / (1.0 + manifold.noise)
    mean = alb.mean(axis=-1)
    lo, hi = colour_range(manifold)
    rgba = colormaps[CMAP](np.clip((mean - lo) / (hi - lo), 0, 1)).astype(np.float64)
    inside = var < DATA_VARIANCE
    rgba[~inside, :3] *= 0.45
    bad = ((alb < 0) | (alb > 1)).any(axis=-1)
    r, c = np.mgrid[:resolution, :resolution]
    stripe = (r + c) % 6 == 0
    hatch = bad & stripe
    rgba[hatch, :3] = 0.35 * rgba[hatch, :3] + 0.65 * np.array([1.0, 0.3, 0.25])
    image = np.round(np.clip(rgba, 0, 1) * 255).astype(np.uint8)
    stops = colormaps[CMAP](np.linspace(0, 1, 9))
    css = [f"rgb({int(255 * s[0])},{int(255 * s[1])},{int(255 * s[2])})" for s in stops]
    return LatentMap(image, dims, ext, (lo, hi), float(bad.mean()), css)
