"""The Fig. 9 benchmark's report of every neighbour pair."""

import pytest

from benchmarks import fig9
from mitsuba_manifold.manifold import space
from mitsuba_manifold.manifold.model import Manifold


@pytest.fixture(scope="module")
def m(small_manifold):
    return Manifold.load(small_manifold)


def test_fig9_every_neighbour_pair_measures_each_pair_once(m):
    rep = fig9.every_pair_report(m, progress=False)
    want = [[m.names[i], m.names[j]] for i, j in space.all_neighbour_pairs(m.latent)]
    assert [r["pair"] for r in rep["rows"]] == want
    assert rep["largest_step"] == max(r["largest_step"] for r in rep["rows"]) <= 1.0
    assert rep["steps_over_target"] == sum(
        r["largest_step"] > fig9.TARGETS["largest_step"] for r in rep["rows"]
    )


def test_fig9_off_ends_is_the_largest_distance_to_the_nearer_end():
    """Points on the chord stay half-way at most (0.5); a path through a third material far from
    both ends reads that material's distance to the nearer end."""
    import numpy as np

    t = np.linspace(0.0, 1.0, 21)
    chord = np.abs(t[:, None] - t[None])  # points evenly along a straight line, d(A, B) = 1
    assert fig9.measure(chord)["off_ends"] == pytest.approx(0.5)
    P = np.stack([t, np.zeros_like(t)], 1)
    P[10, 1] = 2.0  # the middle point is a material far from both ends
    detour = np.linalg.norm(P[:, None] - P[None], axis=-1)
    assert fig9.measure(detour)["off_ends"] == pytest.approx(np.hypot(0.5, 2.0))
