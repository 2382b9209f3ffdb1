"""Figures of a fitted manifold as a look-dev artist reads them: names that do not pile up or
leave the map, no empty band above it, file names that match the axes shown."""

import numpy as np
import pytest

from mitsuba_manifold.imaging import plots
from mitsuba_manifold.manifold.model import Manifold


def synthetic(q, n=60, seed=0):
    """A manifold of ``n`` long-named materials, half of them in one tight cluster."""
    rng = np.random.default_rng(seed)
    latent = np.concatenate(
        [rng.normal(0, 2.0, (n - n // 2, q)), rng.normal(0.5, 0.05, (n // 2, q))]
    )
    names = [f"specular-material-{i:02d}" for i in range(n)]
    return Manifold(
        names,
        latent,
        "db",
        ["0" * 8] * n,
        albedos=rng.uniform(0, 1, (n, 3)),
        interpolant={"kind": "shepard", "power": 2.0, "taper": 0.2, "spread": 0.3},
    )


def test_label_points_names_a_subset_that_never_overlaps_and_stays_inside():
    m = synthetic(2)
    fig, ax = plots.subplots(figsize=(6, 5))
    ax.scatter(*m.latent.T)
    fig.canvas.draw()
    named = plots.label_points(ax, m.latent, m.names)
    renderer = fig.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    boxes = [t.get_window_extent(renderer) for t in ax.texts]
    assert 10 <= named == len(boxes) < m.n  # the cluster cannot all be named
    for k, b in enumerate(boxes):
        assert frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1
        assert not any(b.overlaps(o) for o in boxes[k + 1 :])
    assert all(t.get_path_effects() for t in ax.texts)  # a halo: readable on light and dark colours


def test_latent_map_fills_the_image(tmp_path):
    from PIL import Image

    path = plots.latent_map(synthetic(2), str(tmp_path / "map.png"))
    px = np.asarray(Image.open(path).convert("L")).astype(int)
    filled = (px < 245).mean(axis=1) > 0.5  # rows across the heat map and colour bar
    top = np.argmax(filled)
    assert filled.mean() > 0.85 and top < 0.08 * len(filled), (filled.mean(), top)


@pytest.mark.parametrize("q, second", [(3, "latent_map_dims12.png"), (4, "latent_map_dims23.png")])
def test_second_latent_map_is_named_after_its_axes(tmp_path, q, second):
    paths = plots.write_fit_plots(synthetic(q, n=12), str(tmp_path))
    assert [p.split("/")[-1] for p in paths] == ["latent_map.png", second]
    assert second in plots.FIT_PLOTS
    dims = plots.second_slice(q)
    assert second == f"latent_map_dims{dims[0]}{dims[1]}.png"
