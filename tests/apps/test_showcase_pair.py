"""The main job's showcase pair follows its stated rule: latent neighbours with a genuine,
unclamped midpoint whose ends differ most in colour (CIELAB of their albedos)."""

import numpy as np
import pytest

from mitsuba_manifold import Manifold
from mitsuba_manifold.manifold.appearance import lab


@pytest.mark.render  # the GI comparison's module imports the rendering subsystem
def test_the_pair_is_the_most_colourful_admissible_neighbour_pair():
    from mitsuba_manifold.apps.gi_comparison import gi_pair

    m = Manifold.load("merl")
    a, b = gi_pair(m)
    i, j = m.index(a), m.index(b)
    d2 = ((m.latent[:, None] - m.latent[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    assert d2[i].argmin() == j or d2[j].argmin() == i  # latent neighbours
    x = 0.5 * (m.latent[i] + m.latent[j])
    _, w = m.weights(x)
    assert w[i] + w[j] >= 0.6 and m.negative_fraction(x) <= 1e-3
    colour = lab(m.albedos)
    chosen = np.linalg.norm(colour[i] - colour[j])
    assert chosen > 20  # a change of hue a viewer sees, not two greys
    for k in range(m.n):  # no admissible neighbour pair differs more
        n = int(d2[k].argmin())
        if np.linalg.norm(colour[k] - colour[n]) > chosen + 1e-9:
            y = 0.5 * (m.latent[k] + m.latent[n])
            _, v = m.weights(y)
            assert v[k] + v[n] < 0.6 or m.negative_fraction(y) > 1e-3
